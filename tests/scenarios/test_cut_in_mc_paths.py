"""The cut-in's plain Monte Carlo, one path: the rollouts ``pemviz run --scenario cut-in --method mc`` draws (the
registered problem's ``stream``, which ``benchmarks/cut_in_mc.py`` also counts) against a plain loop written here from
the scene's documentation, both driven by one stream of uniforms, rollout by rollout.

The loop (docs/cut-in.md, :mod:`pemviz.scenarios.cut_in.scenario`): each step, every car's 11 KITTI salient variables
encoded with the detection PEM's statistics; a car is detected iff it is visible and ``u <= p_PEM(detect)``; a
detected car's range and lateral errors are ``loc + scale t^-1_df(u)`` of the noise PEM (Student-t quantiles from
scipy's ``stdtrit``, not pemviz's table); the rollout fails when the classic robustness of
:data:`~pemviz.scenarios.cut_in.scenario.FAILURE_FORMULA` (the scene's two ``G`` conjuncts, not the problem's one
safety formula) is negative. The uniforms are the engine's serial stream: one ``rng.random(N M 3)`` a step, rollout
by rollout, car by car, (detection, range error, lateral error)."""

from __future__ import annotations

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.pem.encoding import encode_salient
from pemviz.scenarios.cut_in.batched import BatchedCutIn
from pemviz.scenarios.cut_in.scenario import FAILURE_FORMULA, OBJECT_NAMES, SALIENT_COLUMNS, CutInParams
from pemviz.scenarios.registry import problem_for
from pemviz.stl import robustness
from scipy.special import expit, stdtrit


def plain_loop(problem, params: CutInParams, n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(failed bool [n], detected bool [n, T, M], errors float64 [n, T, M, 2]) of the plain loop above."""
    detector = problem.target
    pem, noise = detector.detect, detector.noise
    m, n_steps = params.n_objects, params.n_steps
    rng = np.random.default_rng(seed)
    sim = BatchedCutIn(params, n)
    obs = np.empty((n_steps, n, len(sim.observation_names)))
    detected = np.zeros((n, n_steps, m), bool)
    errors = np.zeros((n, n_steps, m, 2))
    visible = OBJECT_NAMES.index("visible")
    for t in range(n_steps):
        u = rng.random(n * m * 3).reshape(n * m, 3)
        sim.observation(out=obs[t])
        rows = np.array(sim.objects()).reshape(n * m, -1)
        raw = rows[:, SALIENT_COLUMNS]
        p_detect = expit(pem.logit_features(encode_salient(raw, pem.norm)))
        d = (rows[:, visible] > 0.5) & (u[:, 0] <= p_detect)
        loc, log_scale = noise.noise_params(encode_salient(raw, noise.norm))
        e = np.where(d[:, None], loc + np.exp(log_scale) * stdtrit(noise.df[None, :], u[:, 1:]), 0.0)
        detected[:, t], errors[:, t] = d.reshape(n, m), e.reshape(n, m, 2)
        sim.step(d.reshape(n, m), e.reshape(n, m, 2))
    signals = {name: obs[:, :, k].T for k, name in enumerate(sim.observation_names)}
    return np.asarray(robustness(FAILURE_FORMULA, signals)) < 0.0, detected, errors


@pytest.mark.parametrize(
    ("params", "n", "seed", "failures_at_least"),
    [
        # the default scene (about 8e-5: no failure expected) on 3,000 rollouts, every draw compared; with the 7,000
        # at 19.8 m: the failure indicator of 10,000 shared rollouts
        ((), 3_000, 7, 0),
        ((("cut_in_gap_m", 19.8),), 7_000, 3, 100),  # 19.8 m, where about 2 % fail: the failure event compared
    ],
)
def test_the_engines_rollouts_are_the_documented_scenes(
    params: tuple[tuple[str, float], ...], n: int, seed: int, failures_at_least: int
) -> None:
    problem = problem_for(ExperimentConfig.of(scenario="cut-in", scenario_params=params))
    target = problem.target
    batches = list(problem.stream(n, target, target, np.random.default_rng(seed), keep_rows=False))
    engine_failed = np.concatenate([problem.failed(b) for b in batches])
    engine_detected = np.concatenate([b.detected for b in batches])
    engine_errors = np.concatenate([b.noise for b in batches])
    failed, detected, errors = plain_loop(problem, CutInParams(**dict(params)), n, seed)
    assert engine_failed.shape == (n,)
    assert int(failed.sum()) >= failures_at_least
    np.testing.assert_array_equal(engine_detected, detected)
    np.testing.assert_allclose(engine_errors, errors, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(engine_failed, failed)
