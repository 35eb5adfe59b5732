"""Time predictions on a loaded machine: the CPU share a run gets from the other tasks' runnable time (Linux's
autogroups: a session's tasks split its share), hand-computed; the speed a pilot of the scene's own rollouts reads;
and the console's first prediction and the panel's cost line scaled by both before anything is measured."""

from __future__ import annotations

import io
import types

import numpy as np
import pytest
from pemviz.engine import resources
from pemviz.engine.resources import Competition, LoadReading, TaskTimes, competition, crowding
from pemviz.settings import SCENARIO_COST_PARTS

NICE5 = 1.25**-5  # a session at autogroup nice 5 against this one at 0: 1024 / 1.25^5 of 1024 (sched_prio_to_weight)


@pytest.mark.parametrize(
    "c, cpus, threads, expected",
    [
        (Competition(), 2, 1, 1.0),  # idle: the run has a CPU of its own
        (Competition(((1.0, 1.0),)), 2, 1, 1.0),  # one other busy session on two CPUs: still one free
        (Competition(((1.0, 1.0), (1.0, 2.0))), 2, 1, 1.5),  # two sessions, one busy on 2 tasks: (2 + 1)(1 + 0) / 2
        # the session's own other tasks split its share: (G + 1)(1 + inside) / C = 3 x 2 / 2, not (2 + 1 + 1) / 2 = 2
        (Competition(((1.0, 1.0), (1.0, 2.0)), inside=1.0, inside_tasks=1.0), 2, 1, 3.0),
        (Competition(((1.0, 1.0), (1.0, 2.0)), inside=2.0, inside_tasks=2.0), 2, 1, 4.5),  # 3 x 3 / 2, not 2.5
        (Competition((), inside=6.0, inside_tasks=6.0), 4, 2, 2.0),  # no other session: 8 tasks on 4 CPUs
        # a session at nice 5 weighs 0.328: the run gets 1 / 1.328 of the one CPU
        (Competition(((NICE5, 3.0),)), 1, 1, 1.0 + NICE5),
        # an inside task at nice 5 against this one's 0 takes 0.328 of the session's one CPU: 1.328 / 1
        (Competition(((1.0, 1.0),), inside=NICE5, inside_tasks=1.0), 2, 1, 1.0 + NICE5),
        # a session that can use one CPU leaves the other three of four to this one's 1 + 3 tasks: 4 / 3, where
        # (G + 1)(1 + inside) / C says 2
        (Competition(((1.0, 1.0),), inside=3.0, inside_tasks=3.0), 4, 1, 4.0 / 3.0),
        # a session busy half the time on one CPU takes its half: the run gets the other half
        (Competition(((1.0, 0.5),)), 1, 1, 2.0),
        # one with a hundredth of a task's time leaves 0.99 of the CPU
        (Competition(((1.0, 0.01),)), 1, 1, 1.0 / 0.99),
    ],
)
def test_the_crowding_is_the_session_s_share_split_among_its_tasks(c, cpus, threads, expected):
    assert crowding(c, cpus, threads) == pytest.approx(expected, rel=1e-12)


BUSY = ((1.0, 1.0),)  # another session with one task runnable throughout


@pytest.mark.parametrize(
    "reading, workers, expected",
    [
        (LoadReading(2), 1, 1.0),
        (LoadReading(2), 2, 2.0),  # idle: a CPU each
        (LoadReading(2), 4, 2.0),  # 4 x 1 / (4 / 2): four workers on two CPUs add nothing
        (LoadReading(4), 3, 3.0),
        # another busy session: the run's session gets one CPU whatever its tasks (autogroups): 2 x 1 / 2
        (LoadReading(2, Competition(BUSY)), 2, 1.0),
        # two: two thirds of a CPU with one thread or two, 2 x 1.5 / 3
        (LoadReading(2, Competition(BUSY * 2)), 2, 1.0),
        # a session busy half the time leaves 1.5 CPUs to two workers: 2 x 1 / (2 / 1.5)
        (LoadReading(2, Competition(((1.0, 0.5),))), 2, 1.5),
        # one at nice 5 (weight 0.328) takes 0.328 / 1.328 of the two CPUs from two workers: 2 x 1 / (1.328 / 1)
        (LoadReading(2, Competition(((NICE5, 1.0),))), 2, 2.0 / (1.0 + NICE5)),
        # the load average where the tasks' times cannot be read: 2 x max(1, (5 + 1) / 2) / ((5 + 2) / 2)
        (LoadReading(2, None, 5.0), 2, 2.0 * 3.0 / 3.5),
        (LoadReading(2, None, None), 2, 2.0),  # neither: an idle machine
    ],
)
def test_the_pool_s_speed_up_is_the_crowding_of_one_thread_over_that_of_the_workers(reading, workers, expected):
    assert reading.pool_speedup(workers) == pytest.approx(expected, rel=1e-12)


def test_a_pooled_batch_s_first_estimate_falls_with_the_workers_and_rises_with_the_load():
    """A million plain braking rollouts, as the console prices them: the model's seconds of the stage times one
    thread's crowding (the slowdown :func:`pemviz.engine.cost.start_reading` gives with speed 1). Idle on 2 CPUs, the
    second worker takes 1.77 times off (2 / COST.pool_share), more workers nothing; beside two other busy sessions the
    pool is slower than one process (COST.pool_share: 0.91-1.06 of one worker's speed measured so); each added busy
    session makes every count of workers slower."""
    from pemviz.config import ExperimentConfig
    from pemviz.engine.cost import COST, stage_cost

    def priced(workers: int, sessions: int) -> float:
        cfg = ExperimentConfig.of(method="mc", n_per_stage=10**6, workers=workers)
        load = LoadReading(2, Competition(BUSY * sessions))
        return stage_cost(cfg, "final", 10**6, model="plain", load=load).simulate_s * load.crowding(1)

    idle = [priced(w, 0) for w in (1, 2, 3, 4)]
    assert idle[0] / idle[1] == pytest.approx(2.0 / COST.pool_share, rel=1e-12)
    assert idle[0] > idle[1] == pytest.approx(idle[3], rel=1e-12) and idle[1] <= idle[2]
    assert priced(2, 2) / priced(1, 2) == pytest.approx(COST.pool_share, rel=1e-12)
    for w in (1, 2, 4):
        by_load = [priced(w, g) for g in range(5)]
        assert all(a <= b for a, b in zip(by_load, by_load[1:], strict=False)) and by_load[0] < by_load[-1]


def _times(at, tasks, group="/autogroup-1", group_nice=0, nice=0):
    return TaskTimes(at, tasks, group, group_nice, nice)


def test_the_competition_is_each_thread_s_runnable_share_of_the_window_summed_per_session():
    s = 1_000_000_000
    before = _times(
        10.0,
        {
            "21": ("/autogroup-1", 0, 0, 5 * s),  # this session, nice 0: runnable the whole 0.5 s
            "22": ("/autogroup-1", 0, 5, 0),  # this session, nice 5: a fifth of the window
            "31": ("/autogroup-2", 0, 0, 7 * s),  # another session, two threads: 0.5 + 0.25 of a task
            "32": ("/autogroup-2", 0, 0, 0),
            "41": ("/autogroup-3", 5, 0, 0),  # a session at nice 5, more than the window (clipped to all of it)
            "51": ("", 0, 0, 0),  # a kernel thread: the root group
            "61": ("/autogroup-4", 0, 0, 3 * s),  # asleep throughout: no claim
            "71": ("/autogroup-5", 0, 0, 0),  # gone by the second reading
            "81": ("/autogroup-6", 0, 0, 0),  # its tid reused by a process of another session: not compared
        },
    )
    after = _times(
        10.5,
        {
            "21": ("/autogroup-1", 0, 0, 5 * s + s // 2),
            "22": ("/autogroup-1", 0, 5, s // 10),
            "31": ("/autogroup-2", 0, 0, 7 * s + s // 4),
            "32": ("/autogroup-2", 0, 0, s // 8),
            "41": ("/autogroup-3", 5, 0, s),
            "51": ("", 0, 0, s // 100),
            "61": ("/autogroup-4", 0, 0, 3 * s),
            "81": ("/autogroup-7", 0, 0, s),
            "91": ("/autogroup-8", 0, 0, s),  # new since the first reading: not compared
        },
    )
    c = competition(before, after)
    assert c.inside_tasks == pytest.approx(1.0 + 0.2)
    assert c.inside == pytest.approx(1.0 + 0.2 * NICE5)
    got = [x for pair in sorted(c.groups) for x in pair]
    assert got == pytest.approx([NICE5, 1.0, 1.0, 0.02, 1.0, 0.75])
    # without autogroups every thread is in this one's group, by its nice
    c = competition(_times(10.0, before.tasks, group=None), _times(10.5, after.tasks, group=None))
    assert c.groups == ()
    assert c.inside_tasks == pytest.approx(1.0 + 0.2 + 0.75 + 1.0 + 0.02)


def test_the_slowdown_is_the_crowding_times_the_speed_over_the_window(monkeypatch):
    s = 1_000_000_000
    two = {"31": ("/autogroup-2", 0, 0, 0), "41": ("/autogroup-3", 0, 0, 0)}
    busy = {k: (*v[:3], s // 4) for k, v in two.items()}  # both runnable throughout the 0.25 s
    readings = iter([_times(100.0, two), _times(100.25, busy)])
    slept: list[float] = []
    monkeypatch.setattr(resources, "tasks_now", lambda: next(readings))
    monkeypatch.setattr(resources, "usable_cpus", lambda: 2)
    monkeypatch.setattr(resources.time, "perf_counter", lambda: 100.1)
    monkeypatch.setattr(resources.time, "sleep", slept.append)
    # two other busy sessions on two CPUs: (2 + 1) / 2 = 1.5, times the speed 3
    assert resources.load_slowdown(speed=3.0) == pytest.approx(4.5)
    assert slept == [pytest.approx(resources.LOAD_WINDOW_S - 0.1)]  # opened at 100.0, now 100.1 (patched)
    # a window opened earlier: no wait where it is already longer
    early = _times(99.0, {"31": ("/autogroup-2", 0, 0, 0)})
    readings = iter([_times(100.1, {"31": ("/autogroup-2", 0, 0, 0)})])
    slept.clear()
    assert resources.load_slowdown(since=early, speed=2.5) == pytest.approx(2.5)  # asleep throughout: the run alone
    assert slept == [0.0]
    # one older than LOAD_WINDOW_MAX_S is not used: a new window opens
    stale = _times(100.1 - resources.LOAD_WINDOW_MAX_S - 1.0, early.tasks)
    readings = iter([_times(99.9, two), _times(100.1, {k: (*v[:3], s) for k, v in two.items()})])
    assert resources.load_slowdown(since=stale) == pytest.approx(1.5)  # both busy in the new window; speed 1
    assert next(readings, None) is None  # both readings were taken


def test_the_slowdown_falls_back_to_the_load_average(monkeypatch):
    monkeypatch.setattr(resources, "tasks_now", lambda: None)
    monkeypatch.setattr(resources.os, "getloadavg", lambda: (5.0, 1.0, 1.0))
    monkeypatch.setattr(resources, "usable_cpus", lambda: 2)
    assert resources.load_slowdown(speed=2.0) == pytest.approx(6.0)  # (5 + 1) / 2 x 2: the 1-minute average


def test_the_scene_s_speed_is_its_pilot_s_cpu_seconds_over_the_model_s(monkeypatch):
    """A fake scene whose pilot batches cost 2, 9, 2.5 and 3 times what the model expects of them (the pilot's share
    included) reads 2.75, their median: the warm-up of 50 (10 times) is not counted; each batch is drawn on a fresh
    seed-0 stream, and timed in this thread's CPU seconds."""
    from pemviz.config import ExperimentConfig
    from pemviz.engine import cost, experiment
    from pemviz.scenarios.problems import build_problem

    cfg, n = ExperimentConfig.of(), experiment.PILOT_ROLLOUTS
    # what the model expects of a batch at braking's share (COST.probe_share), fixed before a share is declared; by
    # hand: 50 rollouts, 100 x (7.19e-5 + 50 x 3.53e-7) = 0.008955 s of the model, times the share
    expected = cost.pilot_seconds(cfg, n, 100)
    assert expected == pytest.approx(0.008955 * cost.COST.probe_share, rel=1e-12)
    clock, asked = [0.0], []
    factors = [10.0, 2.0, 9.0, 2.5, 3.0]  # the warm-up, then the pilot's four batches
    problem = build_problem("toy")
    first_draw = np.random.default_rng(0).random(3)

    def simulate(k, sampler, target, rng):
        assert np.array_equal(rng.random(3), first_draw)  # a fresh stream of its own, seed 0
        clock[0] += factors[len(asked)] * expected * k / n
        asked.append(k)

    fake = types.SimpleNamespace(n_steps=100, target=problem.target, simulate=simulate)
    monkeypatch.setattr(experiment.time, "thread_time", lambda: clock[0])
    pilot = experiment.scene_pilot(fake)
    assert asked == [experiment.PROBE_PILOT] + [n] * experiment.PILOT_BATCHES
    assert [k for k, _ in pilot] == [n] * 4 and [s for _, s in pilot] == pytest.approx(
        [f * expected for f in factors[1:]]
    )
    assert cost.pilot_speed(cfg, pilot, 100) == pytest.approx(2.75, rel=1e-12)
    assert cost.pilot_speed(cfg, [], 100) == 1.0  # no pilot: the model's speed
    # a scene whose pilot runs twice as long against its run as the reference's (its declared probe part): 1.375
    monkeypatch.setitem(SCENARIO_COST_PARTS, "braking", {"probe": 2.0 * cost.COST.probe_share})
    assert cost.pilot_speed(cfg, pilot, 100) == pytest.approx(1.375, rel=1e-12)


def test_the_pilot_leaves_the_run_s_streams_as_they_were():
    """The same seed gives the same run, bit for bit, with the pilot drawn on its problem before it and without."""
    from pemviz.config import ExperimentConfig
    from pemviz.engine.experiment import Experiment, scene_pilot
    from pemviz.scenarios.problems import build_problem

    cfg = ExperimentConfig.of(scenario="toy", n_stages=2, n_per_stage=40, n_final=60, pretrain_rollouts=20, seed=3)
    alone = Experiment(cfg, problem=build_problem("toy")).run()
    problem = build_problem("toy")
    assert len(scene_pilot(problem)) == 4
    probed = Experiment(cfg, problem=problem).run()
    a, b = alone.final.estimate, probed.final.estimate
    assert (a.n, a.n_failures, a.log_mu_hat, a.ess) == (b.n, b.n_failures, b.log_mu_hat, b.ess)


def test_the_panels_cost_line_scales_by_the_load():
    from pemviz.app.form import run_cost
    from pemviz.config import ExperimentConfig

    cfg = ExperimentConfig.of(n_stages=2, n_per_stage=50, n_final=60, pretrain_rollouts=20)
    assert run_cost(cfg, slowdown=1.5).seconds == pytest.approx(1.5 * run_cost(cfg, slowdown=1.0).seconds)


def test_the_tasks_times_are_read_per_thread_with_the_session_and_the_nice(monkeypatch):
    files = {  # a name with a space and a parenthesis; nice is field 19 of stat
        "/proc/99/schedstat": "5 6 7",
        "/proc/11/stat": "11 (busy one) R 1 1 1 0 -1 0 0 0 0 0 0 0 0 0 20 0 1 0 5 0 0",
        "/proc/12/stat": "12 (nice) 10) R 1 1 1 0 -1 0 0 0 0 0 0 0 0 0 30 10 1 0 5 0 0",
        "/proc/11/task/11/schedstat": "100 20 3",
        "/proc/11/task/13/schedstat": "40 2 3",
        "/proc/12/task/12/schedstat": "7 0 1",
        "/proc/self/autogroup": "/autogroup-1 nice 0",
        "/proc/11/autogroup": "/autogroup-2 nice 3",
    }
    dirs = {"/proc": ["self", "11", "12", "99", "stat"], "/proc/11/task": ["11", "13"], "/proc/12/task": ["12"]}

    def read(path, **kw):
        if path not in files:
            raise OSError(path)
        return io.StringIO(files[path])

    def listdir(path):
        if path not in dirs:
            raise OSError(path)
        return dirs[path]

    monkeypatch.setattr(resources.os, "listdir", listdir)
    monkeypatch.setattr(resources.os, "getpid", lambda: 99)
    monkeypatch.setattr(resources.os, "getpriority", lambda which, who: 5)
    monkeypatch.setattr(resources, "open", read, raising=False)
    t = resources.tasks_now()
    assert t is not None and (t.group, t.group_nice, t.nice) == ("/autogroup-1", 0, 5)
    # the kernel thread (no autogroup) in the root group, ""; this process (99) not read
    assert t.tasks == {"11": ("/autogroup-2", 3, 0, 120), "13": ("/autogroup-2", 3, 0, 42), "12": ("", 0, 10, 7)}
    del files["/proc/99/schedstat"]  # no schedstats: nothing to read the load from
    assert resources.tasks_now() is None


def test_a_real_reading_leaves_this_process_out():
    import os

    t = resources.tasks_now()
    assert t is None or str(os.getpid()) not in t.tasks
