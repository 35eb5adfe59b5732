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
    monkeypatch.setattr(resources, "cpu_speed", lambda: 1.0)
    assert resources.load_slowdown(threads) == pytest.approx(expected)
    # and times the CPU seconds the arithmetic takes now over the model's: three times as many, three times as long
    monkeypatch.setattr(resources, "cpu_speed", lambda: 3.0)
    assert resources.load_slowdown(threads) == pytest.approx(max(1.0, 3.0 * (others + threads) / cpus))


def test_the_cpu_speed_is_the_probe_s_cpu_seconds_over_its_reference(monkeypatch):
    ticks = iter([10.0, 10.0 + 2 * resources.PROBE_REFERENCE_CPU_S])  # the probe took twice its reference
    monkeypatch.setattr(resources.time, "process_time", lambda: next(ticks))
    assert resources.cpu_speed() == pytest.approx(2.0, rel=1e-12)
    ticks = iter([0.0, resources.PROBE_REFERENCE_CPU_S / 2])  # half the pieces in half the reference: as fast
    assert resources.cpu_speed(resources.PROBE_PIECES // 2) == pytest.approx(1.0, rel=1e-12)


def test_the_runnable_count_leaves_the_reader_out_and_falls_back_to_the_load_average(monkeypatch, tmp_path):
    now = resources.runnable_now(samples=3, gap_s=0.0)
    assert now is None or now >= 0.0  # this process, reading, is not counted
    monkeypatch.setattr(resources, "runnable_now", lambda: None)
    monkeypatch.setattr(resources.os, "getloadavg", lambda: (5.0, 1.0, 1.0))
    monkeypatch.setattr(resources, "usable_cpus", lambda: 2)
    monkeypatch.setattr(resources, "cpu_speed", lambda: 1.0)
    assert resources.load_slowdown() == pytest.approx(3.0)  # (5 + 1) / 2, the 1-minute average where nothing better


def test_the_panels_cost_line_scales_by_the_load():
    from pemviz.app.form import run_cost
    from pemviz.config import ExperimentConfig

    cfg = ExperimentConfig.of(n_stages=2, n_per_stage=50, n_final=60, pretrain_rollouts=20)
    assert run_cost(cfg, slowdown=1.5).seconds == pytest.approx(1.5 * run_cost(cfg, slowdown=1.0).seconds)


def test_other_tasks_count_by_their_niceness_and_their_session_s_group(monkeypatch):
    import io

    stats = {  # pid -> /proc/<pid>/stat: state (field 3) and nice (field 19), a name with a space and a parenthesis
        "11": "11 (busy one) R 1 1 1 0 -1 0 0 0 0 0 0 0 0 0 20 0 1 0 5 0 0",
        "12": "12 (nice) 10) R 1 1 1 0 -1 0 0 0 0 0 0 0 0 0 30 10 1 0 5 0 0",
        "13": "13 (idle) S 1 1 1 0 -1 0 0 0 0 0 0 0 0 0 20 0 1 0 5 0 0",
        "14": "14 (other) R 1 1 1 0 -1 0 0 0 0 0 0 0 0 0 20 0 1 0 5 0 0",
        "15": "15 (other too) R 1 1 1 0 -1 0 0 0 0 0 0 0 0 0 30 10 1 0 5 0 0",
    }
    groups = {"self": "/autogroup-1 nice 0", "11": "/autogroup-1 nice 0", "12": "/autogroup-1 nice 0"}
    groups |= {"13": "/autogroup-2 nice 0", "14": "/autogroup-2 nice 0", "15": "/autogroup-3 nice 0"}

    def read(path, **kw):
        _, _, pid, name = path.split("/")
        if name == "autogroup":
            if pid not in groups:
                raise OSError(path)
            return io.StringIO(groups[pid])
        return io.StringIO(stats[pid])

    monkeypatch.setattr(resources.os, "listdir", lambda path: ["self", "11", "12", "13", "14", "15", "99"])
    monkeypatch.setattr(resources.os, "getpid", lambda: 99)
    monkeypatch.setattr(resources.os, "getpriority", lambda which, who: 10)  # this run under nice -n 10
    monkeypatch.setattr(resources, "open", read, raising=False)
    # the kernel's weights (sched_prio_to_weight): nice 0 1024, nice 10 110. In this run's group, the nice-0 task
    # counts 1024 / 110 and the nice-10 one 1; each other group with a runnable task 1 whatever its tasks' nice (the
    # sleeping task of group 2 does not count, nor twice its two tasks)
    assert resources.competing_now() == pytest.approx(1024 / 110 + 1.0 + 2.0, rel=1e-3)
    monkeypatch.setattr(resources.os, "getpriority", lambda which, who: 0)
    assert resources.competing_now() == pytest.approx(1.0 + 110 / 1024 + 2.0, rel=1e-3)
    groups.clear()  # no autogroups: every task by its nice against this one's
    assert resources.competing_now() == pytest.approx(1.0 + 110 / 1024 + 1.0 + 110 / 1024, rel=1e-3)
    assert resources.runnable_now(samples=3, gap_s=0.0) == pytest.approx(2.0 + 2 * 110 / 1024, rel=1e-3)
