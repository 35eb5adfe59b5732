"""Executors: chunks of rollouts simulated elsewhere reproduce the serial run; ``--executor ray`` gives the
serial estimate for the same seed."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest

from pemviz.config import ConfigError, ExperimentConfig
from pemviz.detectors import ConstantDetector, WindowDetector
from pemviz.engine import Experiment, RolloutsSampled, StageFinished
from pemviz.executors import (
    ChunkUniforms,
    SerialExecutor,
    chunk_bounds,
    chunk_uniforms,
    gather_chunks,
    get_executor,
    simulate_chunk,
)
from pemviz.pem import load_pem
from pemviz.problems import Problem, braking_problem
from pemviz.scenarios import simulate
from pemviz.scenarios.toy import ToyBraking, ToyParams, toy_problem


def test_t_draws_of_n_uniforms_are_the_rows_of_one_t_by_n_draw_and_chunks_are_its_columns():
    rows = np.stack([g.random(7) for g in [np.random.default_rng(11)] for _ in range(5)])
    block = np.random.default_rng(11).random((5, 7))
    np.testing.assert_array_equal(rows, block)
    state = np.random.default_rng(11).bit_generator.state
    for a, b in [(0, 7), (0, 3), (3, 4), (4, 7)]:
        np.testing.assert_array_equal(chunk_uniforms(state, 7, 5, a, b), block[:, a:b])


def test_chunk_bounds_cover_the_rollouts_in_order():
    assert chunk_bounds(20, 2) == [(0, 10), (10, 20)]
    assert chunk_bounds(3, 8) == [(0, 1), (1, 2), (2, 3)]
    bounds = chunk_bounds(20000, 2, max_chunk=8192)
    assert len(bounds) == 3 and bounds[0][0] == 0 and bounds[-1][1] == 20000
    assert all(b0[1] == b1[0] for b0, b1 in zip(bounds, bounds[1:]))
    with pytest.raises(ValueError, match="n, n_chunks"):
        chunk_bounds(0, 2)


def test_simulate_with_pre_drawn_uniforms_reproduces_the_serial_rollouts_chunk_by_chunk():
    params = ToyParams(12, 6, 3, lambda d: 0.5 + 0.03 * d)
    target = WindowDetector(ConstantDetector(0.3), ConstantDetector(0.9), 8.0)
    sampler = ConstantDetector(0.6)
    serial = simulate(lambda: ToyBraking(params), 9, sampler, target, np.random.default_rng(4), params.steps)
    u = np.random.default_rng(4).random((params.steps, 9))
    parts = [simulate(lambda: ToyBraking(params), b - a, sampler, target, None, params.steps, uniforms=u[:, a:b])
             for a, b in [(0, 4), (4, 5), (5, 9)]]  # fmt: skip
    for name in ("observations", "detected", "log_p", "log_q"):
        np.testing.assert_array_equal(np.concatenate([getattr(p, name) for p in parts]), getattr(serial, name))
    with pytest.raises(ValueError, match=r"uniforms must be float64 \[T, n\]"):
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
    results = [simulate_chunk(problem, n, a, b, sampler, problem.target, state) for a, b in chunk_bounds(n, 3)]
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


def test_config_accepts_serial_and_ray_and_refuses_others():
    assert ExperimentConfig().executor == "serial"
    assert ExperimentConfig(executor="ray", ray_address="auto").ray_address == "auto"
    with pytest.raises(ConfigError, match="executor = 'dask' is invalid: use one of serial, ray"):
        ExperimentConfig(executor="dask")
    with pytest.raises(ConfigError, match="ray_address"):
        ExperimentConfig(ray_address="auto")
    with pytest.raises(ValueError, match="unknown executor 'dask'"):
        get_executor("dask")


def test_run_command_passes_executor_and_ray_address_to_the_config():
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args

    args = build_parser().parse_args(["run", "--executor", "ray", "--ray-address", "ray://head:10001"])
    cfg = config_from_args(args)
    assert (cfg.executor, cfg.ray_address) == ("ray", "ray://head:10001")
    assert config_from_args(build_parser().parse_args(["run"])).executor == "serial"


def _run(config: ExperimentConfig, problem: Problem):
    batches, stages = [], []

    def listen(ev):
        if isinstance(ev, RolloutsSampled):
            batches.append(ev.batch)
        elif isinstance(ev, StageFinished):
            stages.append(ev.result)

    return Experiment(config, [listen], problem=problem).run(), batches, stages


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="ray is not installed (pip install ray)")
def test_ray_executor_with_two_local_workers_gives_the_serial_estimate_for_the_same_seed():
    import ray

    from pemviz.executors import close_executors

    # A less confident PEM (logits / 4) so that K = 2 stages of N = 20 already see crashes.
    problem = braking_problem(load_pem().with_temperature(4.0))
    # i.i.d. uniforms: with Array-RQMC each task couples its own chunk's rollouts (module docstring)
    config = ExperimentConfig(n_stages=2, n_per_stage=20, n_final=20, pretrain_rollouts=20, ce_epochs=100,
                              pretrain_epochs=200, seed=1, uniforms="iid")  # fmt: skip
    serial, serial_batches, serial_stages = _run(config, problem)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        executor = get_executor("ray")
        assert executor.n_chunks == 2
        remote, remote_batches, remote_stages = _run(config.replace(executor="ray"), problem)
    finally:
        close_executors()
        ray.shutdown()
    assert len(remote_batches) == len(serial_batches) == 4  # pretraining, 2 CE stages, final batch
    for a, b in zip(serial_batches, remote_batches):
        np.testing.assert_array_equal(a.detected, b.detected)
        np.testing.assert_array_equal(a.observations, b.observations)
        np.testing.assert_allclose(b.log_q, a.log_q, rtol=0, atol=1e-13)  # torch: last bit per chunk size
    for a, b in zip(serial_stages, remote_stages):
        assert a.estimate.n_failures == b.estimate.n_failures
        assert a.gamma == b.gamma or (math.isnan(a.gamma) and math.isnan(b.gamma))
    s, r = serial.final.estimate, remote.final.estimate
    assert s.n_failures == r.n_failures > 0
    assert abs(r.log_mu_hat - s.log_mu_hat) <= 1e-12  # mu_hat equal to 1e-12 relative
    assert r.ess == pytest.approx(s.ess, rel=1e-9)
