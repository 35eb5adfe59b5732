"""Time predictions on a loaded machine: the slowdown read from the runnable tasks now (not the lagging load average),
hand-computed, and the console's first prediction and the panel's cost line scaled by it before anything is
measured."""

from __future__ import annotations

import pytest

from pemviz.engine import resources


@pytest.mark.parametrize(
    "others, cpus, threads, expected",
    [
        (0.0, 2, 1, 1.0),  # idle: the run has a CPU of its own
        (1.0, 2, 1, 1.0),  # one busy process on two CPUs: still one free
        (2.0, 2, 1, 1.5),  # two busy processes: three tasks share two CPUs, the run gets 2/3 of one
        (6.0, 4, 2, 2.0),  # six others and a two-thread run on four CPUs: 8 / 4
    ],
)
def test_the_slowdown_is_the_tasks_per_cpu_when_they_outnumber_the_cpus(monkeypatch, others, cpus, threads, expected):
    monkeypatch.setattr(resources, "runnable_now", lambda: others)
    monkeypatch.setattr(resources, "usable_cpus", lambda: cpus)
    assert resources.load_slowdown(threads) == pytest.approx(expected)


def test_the_runnable_count_leaves_the_reader_out_and_falls_back_to_the_load_average(monkeypatch, tmp_path):
    now = resources.runnable_now(samples=3, gap_s=0.0)
    assert now is None or now >= 0.0  # this process, reading, is not counted
    monkeypatch.setattr(resources, "runnable_now", lambda: None)
    monkeypatch.setattr(resources.os, "getloadavg", lambda: (5.0, 1.0, 1.0))
    monkeypatch.setattr(resources, "usable_cpus", lambda: 2)
    assert resources.load_slowdown() == pytest.approx(3.0)  # (5 + 1) / 2, the 1-minute average where nothing better


def test_the_panels_cost_line_scales_by_the_load():
    from pemviz.app.form import run_cost
    from pemviz.config import ExperimentConfig

    cfg = ExperimentConfig.of(n_stages=2, n_per_stage=50, n_final=60, pretrain_rollouts=20)
    assert run_cost(cfg, slowdown=1.5).seconds == pytest.approx(1.5 * run_cost(cfg, slowdown=1.0).seconds)


def test_other_sessions_count_once_and_this_session_s_tasks_by_their_niceness(monkeypatch):
    import io

    stat = "{pid} ({name}) {state} 1 1 1 0 -1 0 0 0 0 0 0 0 0 0 20 {nice} 1 0 5 0 0"  # field 3 the state, 19 the nice
    files = {
        "/proc/sys/kernel/sched_autogroup_enabled": "1\n",
        "/proc/99/autogroup": "/autogroup-4 nice 0\n",  # this run's session
        "/proc/11/stat": stat.format(pid=11, name="busy one", state="R", nice=0),
        "/proc/11/autogroup": "/autogroup-4 nice 0\n",
        "/proc/12/stat": stat.format(pid=12, name="nice) 10", state="R", nice=10),
        "/proc/12/autogroup": "/autogroup-4 nice 0\n",
        "/proc/13/stat": stat.format(pid=13, name="idle", state="S", nice=0),
        "/proc/13/autogroup": "/autogroup-4 nice 0\n",
        "/proc/21/stat": stat.format(pid=21, name="other", state="R", nice=0),  # another session, three busy
        "/proc/21/autogroup": "/autogroup-7 nice 0\n",
        "/proc/22/stat": stat.format(pid=22, name="other", state="R", nice=10),
        "/proc/22/autogroup": "/autogroup-7 nice 0\n",
        "/proc/23/stat": stat.format(pid=23, name="other", state="R", nice=0),
        "/proc/23/autogroup": "/autogroup-7 nice 0\n",
    }
    monkeypatch.setattr(resources.os, "listdir", lambda path: ["self", "11", "12", "13", "21", "22", "23", "99"])
    monkeypatch.setattr(resources.os, "getpid", lambda: 99)
    monkeypatch.setattr(resources.os, "getpriority", lambda which, who: 10)  # this run under nice -n 10
    monkeypatch.setattr(resources, "open", lambda path, **kw: io.StringIO(files[path]), raising=False)
    # the kernel's weights (sched_prio_to_weight): nice 0 1024, nice 10 110; the sleeping task does not count, the
    # other session counts once
    assert resources.competing_now() == pytest.approx(1024 / 110 + 110 / 110 + 1, rel=1e-3)
    files["/proc/sys/kernel/sched_autogroup_enabled"] = "0\n"  # no autogroups: every task by its weight
    assert resources.competing_now() == pytest.approx(3 * 1024 / 110 + 2, rel=1e-3)
    monkeypatch.setattr(resources.os, "getpriority", lambda which, who: 0)
    assert resources.competing_now() == pytest.approx(3 + 2 * 110 / 1024, rel=1e-3)
