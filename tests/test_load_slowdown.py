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


def test_other_tasks_count_by_their_niceness_against_the_run_s(monkeypatch):
    import io

    stats = {  # pid -> /proc/<pid>/stat: state (field 3) and nice (field 19), a name with a space and a parenthesis
        "11": "11 (busy one) R 1 1 1 0 -1 0 0 0 0 0 0 0 0 0 20 0 1 0 5 0 0",
        "12": "12 (nice) 10) R 1 1 1 0 -1 0 0 0 0 0 0 0 0 0 30 10 1 0 5 0 0",
        "13": "13 (idle) S 1 1 1 0 -1 0 0 0 0 0 0 0 0 0 20 0 1 0 5 0 0",
    }
    monkeypatch.setattr(resources.os, "listdir", lambda path: ["self", "11", "12", "13", "99"])
    monkeypatch.setattr(resources.os, "getpid", lambda: 99)
    monkeypatch.setattr(resources.os, "getpriority", lambda which, who: 10)  # this run under nice -n 10
    monkeypatch.setattr(resources, "open", lambda path, **kw: io.StringIO(stats[path.split("/")[2]]), raising=False)
    # the kernel's weights (sched_prio_to_weight): nice 0 1024, nice 10 110; the sleeping task does not count
    assert resources.relative_weight() == pytest.approx((1024 / 110 + 110 / 110) / 2, rel=1e-3)
    monkeypatch.setattr(resources.os, "getpriority", lambda which, who: 0)
    assert resources.relative_weight() == pytest.approx((1.0 + 110 / 1024) / 2, rel=1e-3)
