"""Executors: chunks of rollouts simulated elsewhere reproduce the serial run; ``--executor ray`` with 1 or 2
workers gives the serial rollouts and estimate, bit for bit, for the same seed."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import importlib.util
import io
import re

import numpy as np
import pytest
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.core.detectors import ConstantDetector, WindowDetector
from pemviz.core.problems import Problem
from pemviz.engine.events import RolloutsSampled, StageFinished
from pemviz.engine.executors import (
    ChunkUniforms,
    SerialExecutor,
    chunk_uniforms,
    gather_chunks,
    get_executor,
    simulate_chunk,
)
from pemviz.engine.experiment import Experiment
from pemviz.pem import load_pem
from pemviz.scenarios import simulate
from pemviz.scenarios.braking.problem import braking_problem
from pemviz.scenarios.toy import ToyBraking, ToyParams
from pemviz.scenarios.toy.problem import toy_problem


def test_t_draws_of_n_uniforms_are_the_rows_of_one_t_by_n_draw_and_chunks_are_its_columns():
    rows = np.stack([g.random(7) for g in [np.random.default_rng(11)] for _ in range(5)])
    block = np.random.default_rng(11).random((5, 7))
    np.testing.assert_array_equal(rows, block)
    state = np.random.default_rng(11).bit_generator.state
    for a, b in [(0, 7), (0, 3), (3, 4), (4, 7)]:
        np.testing.assert_array_equal(chunk_uniforms(state, 7, 5, a, b), block[:, a:b])


def test_simulate_with_pre_drawn_uniforms_reproduces_the_serial_rollouts_chunk_by_chunk():
    params = ToyParams(12, 6, 3, lambda d: 0.5 + 0.03 * d)
    target = WindowDetector(ConstantDetector(0.3), ConstantDetector(0.9), 8.0)
    sampler = ConstantDetector(0.6)
    serial = simulate(lambda: ToyBraking(params), 9, sampler, target, np.random.default_rng(4), params.steps)
    u = np.random.default_rng(4).random((params.steps, 9))
    parts = [
        simulate(lambda: ToyBraking(params), b - a, sampler, target, None, params.steps, uniforms=u[:, a:b])
        for a, b in [(0, 4), (4, 5), (5, 9)]
    ]
    for name in ("observations", "detected", "log_p", "log_q"):
        np.testing.assert_array_equal(np.concatenate([getattr(p, name) for p in parts]), getattr(serial, name))
    with pytest.raises(ValueError, match=r"uniforms must be float64 \[T, n K\] = \[11, 9\]"):
        simulate(lambda: ToyBraking(params), 9, sampler, target, None, params.steps, uniforms=u[:, :4])


@pytest.mark.parametrize("which", ["braking-batched", "braking-highway-env", "toy"])
def test_chunks_gathered_equal_the_serial_batch_and_leave_the_rng_where_it_would_be(which):
    if which == "toy":
        problem, n = toy_problem(ToyParams(10, 5, 3, 0.7)), 11
    else:
        problem, n = braking_problem(load_pem(), sim=which.split("-", 1)[1]), (11 if "batched" in which else 4)
    sampler = WindowDetector(ConstantDetector(0.5), problem.target, problem.window)
    rng_serial, rng_chunks = np.random.default_rng(9), np.random.default_rng(9)
    serial = SerialExecutor().simulate(problem, n, sampler, problem.target, rng_serial)
    state = rng_chunks.bit_generator.state
    results = [
        simulate_chunk(problem, n, a, b, sampler, problem.target, state)
        for a, b in ((0, n // 3), (n // 3, 2 * n // 3), (2 * n // 3, n))
    ]
    gathered = gather_chunks(problem, n, rng_chunks, results)
    for name in ("observations", "detected", "log_p", "log_q"):
        np.testing.assert_array_equal(getattr(gathered, name), getattr(serial, name))
    assert rng_chunks.random() == rng_serial.random()  # the next stage draws the same numbers


def test_a_simulator_that_does_not_draw_once_per_step_is_refused_with_a_clear_error():
    def two_draws(n, sampler, target, rng):
        rng.random(n)
        return toy_problem(ToyParams(10, 5, 3, 0.7)).simulate(n, sampler, target, rng)

    base = toy_problem(ToyParams(10, 5, 3, 0.7))
    odd = Problem("two-draws", two_draws, base.target, base.formula, signals={"d": "gap_m"})
    state = np.random.default_rng(0).bit_generator.state
    results = [simulate_chunk(odd, 6, a, b, base.target, base.target, state) for a, b in [(0, 3), (3, 6)]]
    steps = ToyParams(10, 5, 3, 0.7).steps
    with pytest.raises(RuntimeError, match=f"drew rng.random {steps + 1} times for {steps} steps"):
        gather_chunks(odd, 6, np.random.default_rng(0), results)
    with pytest.raises(RuntimeError, match=r"random\(5"):
        ChunkUniforms(state, 6, 0, 3).random(5)
    with pytest.raises(AttributeError, match="rng.integers"):
        ChunkUniforms(state, 6, 0, 3).integers(2)


def test_config_accepts_local_serial_and_ray_and_refuses_others():
    assert ExperimentConfig.of().execution.executor == "local"
    assert ExperimentConfig.of(executor="ray", ray_address="auto").execution.ray_address == "auto"
    with pytest.raises(ConfigError, match="executor = 'dask' is invalid: use one of local, serial, ray"):
        ExperimentConfig.of(executor="dask")
    with pytest.raises(ConfigError, match="ray_address"):
        ExperimentConfig.of(ray_address="auto")
    with pytest.raises(ValueError, match="unknown executor 'dask'"):
        get_executor("dask")


def test_run_command_passes_executor_and_ray_address_to_the_config():
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args

    args = build_parser().parse_args(["run", "--executor", "ray", "--ray-address", "ray://head:10001"])
    cfg = config_from_args(args)
    assert (cfg.execution.executor, cfg.execution.ray_address) == ("ray", "ray://head:10001")
    assert config_from_args(build_parser().parse_args(["run"])).execution.executor == "local"


def _run(config: ExperimentConfig, problem: Problem):
    batches, stages = [], []

    def listen(ev):
        if isinstance(ev, RolloutsSampled):
            batches.append(ev.batch)
        elif isinstance(ev, StageFinished):
            stages.append(ev.result)

    return Experiment(config, [listen], problem=problem).run(), batches, stages


ray_missing = pytest.mark.skipif(
    importlib.util.find_spec("ray") is None, reason="ray is not installed (pip install ray)"
)


@pytest.fixture(scope="module", params=[1, 2], ids=["1-worker", "2-workers"])
def ray_workers(request):
    """A local Ray cluster of 1 or 2 CPUs for the module's tests; ``--executor ray`` then uses it."""
    import ray
    from pemviz.engine.executors import close_executors

    ray.init(num_cpus=request.param, include_dashboard=False, log_to_driver=False)
    try:
        yield request.param
    finally:
        close_executors()
        ray.shutdown()


BLOCKS = ExperimentConfig.of(
    n_stages=2,
    n_per_stage=20,
    n_final=9000,
    pretrain_rollouts=20,
    ce_epochs=100,
    pretrain_epochs=200,
    seed=1,
    plain_fallback=0,
)
"""A small default-sampler run whose final batch spans two Array-RQMC blocks (8,192 + 808 rollouts); no plain Monte
Carlo after it (its stages are what is compared)."""


@functools.cache
def _serial_run(uniforms: str):
    return _run(BLOCKS.replace(uniforms=uniforms), braking_problem(dataclasses.replace(load_pem(), temperature=4.0)))


@ray_missing
@pytest.mark.parametrize("uniforms", ["array-rqmc", "iid"])
def test_ray_tasks_of_whole_blocks_give_the_serial_rollouts_and_estimate_bit_for_bit(ray_workers, uniforms):
    # A less confident PEM (logits / 4) so that K = 2 stages of N = 20 already see crashes.
    problem = braking_problem(dataclasses.replace(load_pem(), temperature=4.0))
    serial, serial_batches, serial_stages = _serial_run(uniforms)
    executor = get_executor("ray")
    assert (executor.cpus, executor.in_flight) == (ray_workers, 2 * ray_workers)
    remote, remote_batches, remote_stages = _run(BLOCKS.replace(uniforms=uniforms, executor="ray"), problem)
    assert [b.n for b in remote_batches] == [b.n for b in serial_batches] == [20, 20, 20, 9000]
    for a, b in zip(serial_batches, remote_batches, strict=False):
        for name in ("observations", "detected", "log_p", "log_q"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert [(repr(s.gamma), s.n_elites, s.estimate) for s in serial_stages] == [
        (repr(s.gamma), s.n_elites, s.estimate) for s in remote_stages
    ]
    assert serial.final.estimate == remote.final.estimate and serial.final.estimate.n_failures > 0


@ray_missing
def test_toy_blocks_on_ray_give_the_serial_batch_bit_for_bit(ray_workers):
    from pemviz.core.detectors import ArrayRQMC
    from pemviz.core.sampling import StateProposal

    problem = toy_problem(ToyParams(10, 5, 3, 0.7))
    proposal = ArrayRQMC(StateProposal((0, 1), (10.0, 1.0), (10.0, 0.0)))  # a torch network: asked block by block
    a = SerialExecutor().simulate(problem, 17_000, proposal, problem.target, np.random.default_rng(5))
    b = get_executor("ray").simulate(problem, 17_000, proposal, problem.target, np.random.default_rng(5))
    for name in ("observations", "detected", "log_p", "log_q"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


RUN_ARGS = (
    *("run", "--no-record", "--preset", "quick", "--k", "2", "--n", "30", "--n-final", "9000"),
    *("--plain-fallback", "0"),
)
"""A small default-sampler run whose final batch spans two blocks, so that ray runs it as tasks (no plain Monte
Carlo after it)."""


@functools.cache
def _final_lines(seed: int, executor: str) -> tuple[str, str]:
    """(the verdict line, mu_hat with its log) of ``pemviz run`` (:data:`RUN_ARGS`) on ``executor``."""
    from pemviz import cli

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli.main([*RUN_ARGS, "--seed", str(seed), "--executor", executor]) == 0
    lines = out.getvalue().splitlines()
    verdict = next(ln for ln in lines if ln.startswith("mu_hat = ") and "CI" in ln)
    log_line = next(ln for ln in lines if ln.startswith("mu_hat = ") and "(log mu_hat" in ln)
    return verdict, log_line.split(" from ")[0]


@ray_missing
@pytest.mark.parametrize("seed", [0, 3, 7])
def test_cli_run_on_ray_prints_the_serial_final_line(ray_workers, seed):
    serial = _final_lines(seed, "serial")
    assert serial[0].startswith("mu_hat = ") and "exact 1.984e-15" in serial[0]
    assert _final_lines.__wrapped__(seed, "ray") == serial


@ray_missing
def test_a_stage_streamed_on_ray_is_the_serial_stream_block_by_block_with_a_bounded_number_of_tasks(
    ray_workers, tmp_path
):
    import os

    import ray
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.engine.executors import RayExecutor, ray_block
    from pemviz.scenarios.problems import problem_for

    problem = problem_for(ExperimentConfig.of(scenario="crossing"))  # two pedestrians: K = 2 uniforms a rollout
    n, bound = 2 * 8192 + 500, 2
    serial_rng, ray_rng = np.random.default_rng(3), np.random.default_rng(3)
    serial = problem.simulate(n, problem.target, problem.target, serial_rng)
    executor = RayExecutor(in_flight=bound)  # the fixture's cluster

    def noted(path, *args):  # a block's task, noting the worker process that ran it
        with open(path, "a") as f:
            f.write(f"{os.getpid()}\n")
        return ray_block(*args)

    task, submitted = ray.remote(noted), []

    class Counted:  # the executor's task, its submissions counted
        @staticmethod
        def remote(*args):
            submitted.append(args[2:4])
            return task.remote(str(tmp_path / "pids"), *args)

    executor._task = Counted
    chunks, ahead = [], []
    for chunk in executor.stream(problem, n, problem.target, problem.target, ray_rng, keep_rows=False):
        ahead.append(len(submitted) - len(chunks))  # submitted and not handed out before this chunk, this one's too
        chunks.append(chunk)
    assert submitted == [(0, 8192), (8192, 16384), (16384, n)]  # a task a block, in order
    assert ahead == [2, 2, 1]  # never more than the bound in flight, the next submitted as one is taken
    assert [c.n for c in chunks] == [8192, 8192, 500]
    streamed = RolloutBatch.concatenate(chunks)
    for name in ("observations", "detected", "log_p", "log_q"):
        np.testing.assert_array_equal(getattr(streamed, name), getattr(serial, name))
    rows = np.array([0, 8191, 8192, n - 1])
    np.testing.assert_array_equal(streamed.select(rows).objects, serial.objects[rows])  # the rows replayed
    assert ray_rng.random() == serial_rng.random()  # the rng left where the serial stream leaves it
    pids = set((tmp_path / "pids").read_text().split())
    assert len(pids) == ray_workers  # every worker ran blocks


CROSSING_STREAMED = ("--scenario", "crossing", "--method", "mc", "--n", "9000", "--seed", "2", "--chunk", "4000")
"""Plain Monte Carlo on the crossing whose stage streams (--chunk 4000) in two blocks (8,192 + 808 rollouts)."""


@ray_missing
def test_cli_run_whose_stage_streams_on_ray_prints_the_serial_and_local_pool_s_run(ray_workers, monkeypatch):
    from pemviz import cli
    from pemviz.engine import resources

    monkeypatch.setattr(resources, "POOL_PAYS_S", 0.0)  # the local pool after the first block, whatever it cost

    def printed(*how: str) -> list[str]:
        out = io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
            assert cli.main(["run", "--no-record", *CROSSING_STREAMED, *how]) == 0
        lines = [ln for ln in out.getvalue().splitlines() if not re.search(r"\d (s|ms|min)\b|wall s", ln)]
        return [" ".join(ln.split()[:-1]) if ln.lstrip()[:1].isdigit() or "final " in ln else ln for ln in lines]

    serial = printed("--workers", "1")
    assert any(ln.startswith("mu_hat = ") and "reference" in ln for ln in serial)
    assert printed("--executor", "ray") == serial
    if ray_workers == 2:
        assert printed("--workers", "2") == serial and get_executor("local", workers=2).started


@ray_missing
def test_sigterm_during_a_ray_run_is_the_run_s_one_line_not_ray_s_stack_dump(tmp_path):
    """``ray.init`` installs Ray's own SIGTERM handling in the driver (its C++ core prints ``*** SIGTERM received``
    and a stack dump, and the process dies without the run's words); the executor puts the run's handler back, so
    SIGTERM mid-stage ends the run as Ctrl-C does: exit 143, one line saying no stage finished, no file written.
    (The signal is sent once a Ray worker runs a block (``ray.init`` has returned: during it, a few seconds, Ray's
    handling holds) while the run waits in ``ray.get``, which turns it into a plain ``KeyboardInterrupt``.)"""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path

    out = tmp_path / "r.parquet"
    args = ["--scenario", "crossing", "--method", "mc", "--n", "200000", "--executor", "ray", "--no-record"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "pemviz.cli", "run", *args, "--save-rollouts", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    deadline = time.monotonic() + 300

    def block_running() -> bool:  # a Ray worker runs one of the stage's blocks: ray.init has returned
        for pid in filter(str.isdigit, os.listdir("/proc")):
            with contextlib.suppress(OSError):
                if b"ray_block" in Path(f"/proc/{pid}/cmdline").read_bytes():
                    return True
        return False

    while not block_running() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    proc.send_signal(signal.SIGTERM)
    rest, _ = proc.communicate(timeout=120)
    text = rest
    assert proc.returncode == 143, text
    assert "interrupted (SIGTERM); 0 stage(s) finished" in text and "SIGTERM received" not in text, text
    assert "Traceback" not in text and not out.exists()
