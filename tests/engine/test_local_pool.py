"""The ``local`` executor (the default): a batch's or a streamed stage's blocks simulated by worker processes give the
rollouts and the printed run of one process, bit for bit; the pool starts only for batches of several blocks; its
workers are the usable cores."""

from __future__ import annotations

import contextlib
import functools
import io
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pemviz.engine.resources as resources
import pytest
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.engine.executors import SerialExecutor, close_executors, get_executor
from pemviz.engine.pool import LocalExecutor
from pemviz.engine.resources import usable_cpus


@pytest.fixture(scope="module", autouse=True)
def _pool_closed_after_the_module():
    yield
    close_executors()


def test_usable_cpus_are_the_affinity_mask_capped_by_the_cgroup_quota(tmp_path):
    mask = len(os.sched_getaffinity(0))
    quota = tmp_path / "cpu.max"
    assert usable_cpus(tmp_path / "absent") == mask
    quota.write_text("max 100000\n")
    assert usable_cpus(quota) == mask
    quota.write_text("50000 100000\n")  # half a core: one worker
    assert usable_cpus(quota) == 1
    quota.write_text(f"{100000 * mask + 1} 100000\n")  # a share of one more core than the mask: the mask
    assert usable_cpus(quota) == mask


def test_the_default_executor_is_local_with_every_usable_core_and_one_worker_is_the_serial_path():
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args

    cfg = config_from_args(build_parser().parse_args(["run"]))
    assert (cfg.execution.executor, cfg.execution.workers) == ("local", None)
    assert config_from_args(build_parser().parse_args(["run", "--workers", "3"])).execution.workers == 3
    assert isinstance(get_executor("local", workers=1), SerialExecutor)
    assert get_executor("local", workers=2).workers == 2
    default = get_executor("local")
    assert default.workers == usable_cpus()
    with pytest.raises(ConfigError, match="workers"):
        ExperimentConfig.of(workers=0)
    with pytest.raises(ConfigError, match="give it only with executor = 'local'"):
        ExperimentConfig.of(executor="serial", workers=2)


def test_a_batch_goes_to_the_pool_only_from_two_blocks_that_pay_for_its_start():
    ex = LocalExecutor(2)
    rng = np.random.default_rng(0)
    assert not ex.eligible(2100, rng)  # braking's default stages and final batch
    assert not ex.eligible(8192, rng)
    assert ex.eligible(8193, rng)
    assert not ex.eligible(10**6, np.random.Generator(np.random.MT19937(0)))
    assert not LocalExecutor(1).eligible(10**6, rng)
    assert not ex._pays(10, 1.9) and ex._pays(10, 2.0)  # 20 CPU seconds left: resources.POOL_PAYS_S


def test_the_first_time_estimate_divides_a_pooled_batch_s_simulation_by_what_the_workers_add():
    from pemviz.core.rng import RQMC_BLOCK
    from pemviz.engine.cost import COST, stage_cost
    from pemviz.engine.resources import POOL_BLOCK, Competition, LoadReading, pool_workers

    assert POOL_BLOCK == RQMC_BLOCK
    one = ExperimentConfig.of(method="mc", workers=1)
    two = ExperimentConfig.of(method="mc", workers=2)
    assert [pool_workers(two.execution, n, s) for n, s in ((2100, 99.0), (8192, 99.0), (8193, 19.9), (8193, 20.0))] == [
        1,
        1,
        1,
        2,
    ]
    assert pool_workers(ExperimentConfig.of(executor="serial").execution, 10**6, 99.0) == 1
    assert pool_workers(ExperimentConfig.of().execution, 10**6, 99.0) == usable_cpus()
    idle = LoadReading(2)
    a, b = (stage_cost(cfg, "final", 10**6, model="plain", load=idle) for cfg in (one, two))
    # idle on 2 CPUs two workers get through the CPU seconds twice as fast, each rollout costing COST.pool_share
    # (1.13: the hand-off, the run's process collecting): 1.77 times one process's speed (1.74-1.79 measured at rest)
    assert b.simulate_s == pytest.approx(a.simulate_s * COST.pool_share / 2, rel=1e-12) and b.after_s == a.after_s
    assert a.simulate_s / b.simulate_s == pytest.approx(1.77, abs=0.01)
    # beside two other busy sessions the run's session gets two thirds of a CPU with one thread or two: no gain,
    # and the pool's share costs more (0.91-1.06 times one worker's speed measured at load)
    busy = LoadReading(2, Competition(((1.0, 1.0), (1.0, 1.0))))
    slow = stage_cost(two, "final", 10**6, model="plain", load=busy)
    assert a.simulate_s / slow.simulate_s == pytest.approx(1 / COST.pool_share, rel=1e-12)
    assert stage_cost(one, "final", 10**6, model="plain", load=busy) == a  # one process: the caller's slowdown only
    small = [stage_cost(cfg, "final", 2100, model="plain").simulate_s for cfg in (one, two)]
    assert small[0] == small[1]
    # a batch whose model seconds are under the pool's 20 s, on a machine that runs it 2 times slower: pooled
    mid = 500_000  # 13.7 model seconds of braking's plain rollouts
    base = stage_cost(one, "final", mid, model="plain").simulate_s
    assert base < 20.0 <= 2.0 * base
    assert stage_cost(two, "final", mid, model="plain").simulate_s == base
    slow = stage_cost(two, "final", mid, model="plain", speed=2.0, load=idle).simulate_s
    assert slow == pytest.approx(base * COST.pool_share / 2, rel=1e-12)  # the model's seconds, the pool's share


def test_pooled_blocks_and_streamed_chunks_are_the_serial_rollouts_and_leave_the_rng_where_it_would_be(monkeypatch):
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.scenarios.problems import problem_for

    monkeypatch.setattr(resources, "POOL_PAYS_S", 0.0)  # the pool after the first block, whatever it cost
    problem = problem_for(ExperimentConfig.of(scenario="crossing"))  # two pedestrians: K = 2 uniforms a rollout
    n, ex = 8192 + 500, get_executor("local", workers=2)
    serial_rng, pooled_rng = np.random.default_rng(3), np.random.default_rng(3)
    a = problem.simulate(n, problem.target, problem.target, serial_rng)
    b = ex.simulate(problem, n, problem.target, problem.target, pooled_rng)
    chunks = list(ex.stream(problem, n, problem.target, problem.target, np.random.default_rng(3), chunk_size=3000))
    assert [c.n for c in chunks] == [3000, 3000, 2192, 500]  # block by block, then at most chunk_size
    streamed = RolloutBatch.concatenate(chunks)
    for name in ("observations", "detected", "log_p", "log_q"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        np.testing.assert_array_equal(getattr(a, name), getattr(streamed, name))
    assert serial_rng.random() == pooled_rng.random()
    assert ex.started
    folder = ex._folder  # the blocks came through shared-memory files (pemviz.engine.handoff), each removed once read
    assert folder is None or os.listdir(folder) == []
    ex.close()
    assert folder is None or not os.path.exists(folder)


@functools.cache
def _printed(args: tuple[str, ...], workers: int, pays_s: float) -> tuple[list[str], bool]:
    """The lines ``pemviz run ARGS --workers W`` prints that do not say a time, and whether a pool started."""
    from pemviz import cli

    saved, resources.POOL_PAYS_S = resources.POOL_PAYS_S, pays_s
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
            assert cli.main(["run", "--no-record", *args, "--workers", str(workers)]) == 0
    finally:
        resources.POOL_PAYS_S = saved
    ex = get_executor("local", workers=workers)
    started = bool(getattr(ex, "started", False))
    timed = re.compile(r"\d (s|ms|min)\b|wall s")
    lines = [ln for ln in out.getvalue().splitlines() if not timed.search(ln)]
    return [" ".join(ln.split()[:-1]) if ln.lstrip()[:1].isdigit() or "final " in ln else ln for ln in lines], started


CROSSING_MC = ("--scenario", "crossing", "--method", "mc", "--n", "9000", "--seed", "2")
"""Plain Monte Carlo on the two-pedestrian crossing, two blocks (8,192 + 808 rollouts)."""


@pytest.mark.parametrize("chunk", [None, "4000"], ids=["one-batch", "streamed"])
def test_crossing_plain_monte_carlo_prints_the_same_run_with_one_and_two_workers(chunk):
    args = CROSSING_MC if chunk is None else (*CROSSING_MC, "--chunk", chunk)  # --chunk 4000: the stage streams
    one, _ = _printed(args, 1, 0.0)
    two, started = _printed(args, 2, 0.0)
    assert started
    assert any(ln.startswith("mu_hat = ") and "reference" in ln for ln in one)
    assert one == two


def test_a_braking_run_whose_final_stage_streams_prints_the_same_run_with_one_and_two_workers():
    # the default sampler; --chunk 4000 streams its final stage of 9,000 (two blocks, 8,192 + 808: the pool), the
    # path a final stage above STREAM_ABOVE (20,000) takes in chunks of its own
    args = ("--n-final", "9000", "--chunk", "4000", "--seed", "1")
    one, _ = _printed(args, 1, 0.0)
    two, started = _printed(args, 2, 0.0)  # the pool for the blocks after the first, whatever they cost
    assert started and one == two
    assert any(ln.startswith("mu_hat = ") and "exact 1.984e-15" in ln for ln in one)


def test_the_braking_default_run_never_starts_the_pool():
    close_executors()  # a fresh executor: whatever an earlier test started
    two, started = _printed(("--seed", "0"), 2, resources.POOL_PAYS_S)  # pemviz run: braking, 2,100 rollouts
    # two workers whose pool never starts print one worker's run: the CE stages of the streamed braking run above
    # (2,100 rollouts each, below two blocks) take that path, and its printed lines compare one worker with two
    assert not started
    assert any("exact 4.670e-19" in ln for ln in two)


def test_validate_runs_its_seeds_on_every_core_and_they_give_one_process_records():
    from pemviz.cli import build_parser
    from pemviz.studies.validation import methods_for, run_jobs, study_jobs

    assert build_parser().parse_args(["validate"]).jobs is None  # None: every usable core
    sizes = {"n_stages": 4, "ce_epochs": 150, "pretrain_epochs": 300}
    jobs = study_jobs(["toy-1e-3"], methods_for(["paper"], ["mc"], sizes), 2)  # 2 methods x 2 seeds
    one, two = run_jobs(jobs, 1), run_jobs(jobs, 2)
    assert [(r.method, r.seed) for r in two] == [(j.method, j.seed) for j in jobs]
    assert [(r.log_mu_hat, r.n_failures, r.n) for r in one] == [(r.log_mu_hat, r.n_failures, r.n) for r in two]
    assert sum(r.n_failures for r in one) > 0


def _ignores_sigint(pid: int) -> bool:
    """Whether process ``pid`` ignores SIGINT (its ``SigIgn`` mask in /proc): a worker past its start, whose
    initializer ignores it (a Ctrl-C while a worker still imports is the case this test does not cover)."""
    try:
        line = next(x for x in Path(f"/proc/{pid}/status").read_text().splitlines() if x.startswith("SigIgn:"))
    except (OSError, StopIteration):
        return False
    return bool(int(line.split()[1], 16) >> (signal.SIGINT - 1) & 1)


def _workers_of(pid: int) -> list[int]:
    """The local executor's worker processes (``LokyProcess``) whose parent is ``pid``."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            if entry.name.isdigit() and ppid == pid and b"LokyProcess" in (entry / "cmdline").read_bytes():
                found.append(int(entry.name))
        except (OSError, ValueError, IndexError):
            continue
    return found


@pytest.mark.parametrize("how", ["SIGINT", "SIGTERM"])
def test_ctrl_c_and_sigterm_end_the_run_and_its_workers(how):
    cmd = [sys.executable, "-m", "pemviz.cli", "run", "--no-record", "--method", "mc", "--n", "5000000"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        workers: list[int] = []
        for _ in range(1200):  # until the pool's workers are up (a few seconds), at most about 2 minutes
            workers = _workers_of(proc.pid)
            if (len(workers) == usable_cpus() and all(map(_ignores_sigint, workers))) or proc.poll() is not None:
                break
            time.sleep(0.1)
        assert len(workers) == usable_cpus() > 1, "the run did not start its workers"
        if how == "SIGINT":  # Ctrl-C in a terminal: the whole foreground group
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == (130 if how == "SIGINT" else 143)
    assert f"interrupted ({'Ctrl-C' if how == 'SIGINT' else 'SIGTERM'}); 0 stage(s) finished" in err
    assert "Traceback" not in err and "leaked" not in err
    assert [pid for pid in workers if Path(f"/proc/{pid}").exists()] == []


def test_workers_find_a_module_of_ones_own_put_on_the_import_path_after_the_pool_started(tmp_path, monkeypatch):
    """A long-lived process (the panel) imports a scenario of one's own from a folder it adds to ``sys.path`` after
    its pool's workers started: the pool's new tasks run on workers that find that module (pickled by reference)."""
    import importlib

    from pemviz.engine.pool import LocalExecutor

    first = LocalExecutor(2)
    assert first._executor().submit(abs, -3).result(timeout=120) == 3  # workers up, on the old import path
    (tmp_path / "pool_probe_mod.py").write_text("def answer():\n    return 42\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    probe = importlib.import_module("pool_probe_mod")
    try:
        assert LocalExecutor(2)._executor().submit(probe.answer).result(timeout=120) == 42
    finally:
        sys.modules.pop("pool_probe_mod", None)
