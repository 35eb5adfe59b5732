"""The cut-in scenario as a problem: its detector (the PEMs on each car's salient variables), its failure formula,
the samplers' treatment of cars the camera cannot see, and ``pemviz run --scenario cut-in``."""

from __future__ import annotations

import numpy as np
import pytest
from pemviz import stl
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.core.detectors import StageSamplers
from pemviz.pem import load_pem
from pemviz.pem.store import load_noise_pem
from pemviz.scenarios.cut_in.problem import cut_in_params, cut_in_problem
from pemviz.scenarios.cut_in.scenario import FAILURE_FORMULA, OBJECT_NAMES, OBSERVATION_NAMES, SALIENT_COLUMNS
from scipy.special import log_expit

from conftest import run_cli

VISIBLE = OBJECT_NAMES.index("visible")


@pytest.fixture(scope="module")
def problem():
    return cut_in_problem(load_pem(), cut_in_params("moderate"))


@pytest.fixture(scope="module")
def batch(problem):
    """200 rollouts under the PEMs themselves (plain Monte Carlo), seed 3."""
    return problem.simulate(200, problem.target, problem.target, np.random.default_rng(3))


def test_the_detector_is_the_pems_on_the_salient_columns_and_blind_to_unseen_cars(problem, batch):
    rows = batch.objects.reshape(-1, len(OBJECT_NAMES))
    seen = rows[:, VISIBLE] > 0.5
    assert seen.any() and (~seen).any()
    pem, noise = load_pem(), load_noise_pem("hetero-t")
    logit = problem.target.detect_logit(rows)
    # the same network, rows batched differently
    np.testing.assert_allclose(logit[seen], pem.logit(rows[seen][:, SALIENT_COLUMNS]), rtol=1e-9, atol=1e-12)
    assert np.all(logit[~seen] == -np.inf)
    errors = np.random.default_rng(0).standard_normal((seen.sum(), 2)) * 0.3
    features = noise.features(rows[seen][:, SALIENT_COLUMNS])
    np.testing.assert_allclose(
        problem.target.noise_log_prob(rows[seen], errors), noise.log_prob(features, errors), rtol=1e-9, atol=1e-12
    )


def test_under_the_pems_an_unseen_car_is_never_detected_and_the_weights_are_one(problem, batch):
    seen = batch.objects[..., VISIBLE] > 0.5
    assert not (batch.detected & ~seen).any()
    assert batch.noise.shape == batch.detected.shape + (2,)
    assert np.all(batch.noise[~batch.detected] == 0.0)
    np.testing.assert_array_equal(batch.log_p, batch.log_q)
    # log p of a step is the sum over its cars of log p(a | x) and, where detected, log p(errors | x)
    rows = batch.objects[0, 20]
    det = batch.detected[0, 20]
    logit = problem.target.detect_logit(rows)
    want = np.where(det, log_expit(logit), log_expit(-logit)).sum()
    if det.any():
        want += problem.target.noise_log_prob(rows[det], batch.noise[0, 20][det]).sum()
    assert batch.log_p[0, 20] == pytest.approx(want, rel=1e-12)


def test_a_proposal_cannot_detect_where_the_target_is_certain(problem, batch):
    class Eager:  # a proposal that detects every car with probability 1 - 4.5e-5
        def detect_logit(self, obs):
            return np.full(len(obs), 10.0)

    rows = batch.objects.reshape(-1, len(OBJECT_NAMES))
    samplers = StageSamplers(Eager(), problem.target, radius_m=problem.window)
    target, plain, _ = samplers.logits(rows)
    unseen = rows[:, VISIBLE] < 0.5
    assert np.all(plain[unseen] == -np.inf)
    near = ~unseen & (rows[:, 0] < problem.window)
    assert near.any() and np.all(plain[near] == 10.0)
    np.testing.assert_array_equal(plain[~near], target[~near])


def test_the_problem_formula_fails_exactly_where_the_scenarios_formula_does(problem, batch):
    signals = {name: batch.signal(name) for name in OBSERVATION_NAMES}
    theirs = stl.robustness(FAILURE_FORMULA, signals, semantics="classic")
    ours = problem.robustness(batch, "classic")
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-12)
    assert problem.failed(batch).tolist() == (np.asarray(theirs) < 0).tolist()


def test_the_cut_in_runs_on_its_twin_only():
    with pytest.raises(ConfigError, match="batched twin only"):
        ExperimentConfig.of(scenario="cut-in", sim="highway-env")


def test_pemviz_run_scenario_cut_in_estimates_and_says_so(tmp_path):
    proc = run_cli("run", "--scenario", "cut-in", "--method", "mc", "--n", "300", "--seed", "1", "--no-record")
    assert proc.returncode == 0, proc.stderr
    assert "mc on the cut-in scenario" in proc.stdout + proc.stderr
    assert "from 300 simulations" in proc.stdout


def test_save_rollouts_refuses_splitting_on_the_cut_in_before_it_runs(tmp_path):
    """A cut-in run's rollouts are saved (tests/files/test_rollout_roundtrip.py); splitting's have no weights to
    save."""
    out = tmp_path / "r.parquet"
    proc = run_cli("run", "--scenario", "cut-in", "--method", "ams", "--no-record", "--save-rollouts", str(out))
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "method ams estimates without importance weights" in proc.stderr
    assert "Traceback" not in proc.stderr and not out.exists() and not list(tmp_path.iterdir())


def test_a_cut_in_run_says_which_errors_decided_its_most_likely_failure(capsys):
    """A small cut-in run (two stages of 60, a final batch of 100) prints one why line naming the errors that decided
    its most likely failure; in this process (the console script's own path is the other tests' subject)."""
    from pemviz.cli import main

    argv = ["run", "--scenario", "cut-in", "--method", "adaptive", "--k", "2", "--n", "60", "--n-final", "100"]
    # --plain-fallback 0: the stages' most likely failure (a million plain cut-in rollouts after them: minutes)
    assert main([*argv, "--plain-fallback", "0", "--no-record"]) == 0
    out = capsys.readouterr().out
    why = [line for line in out.splitlines() if line.startswith("why: the most likely failure")]
    assert len(why) == 1 and "before the failure at step" in why[0]
    assert "decisive alone: car 0" in why[0] or "none of them alone decides it" in why[0]


class PerCall:
    """The cut-in detector asked the plain way: each head on a fresh writable copy of the rows (nothing is kept from
    one call to the next) and no ``noise_draw``, so that :func:`pemviz.core.detectors.draw_step` asks the noise head
    for the draw and for each density separately."""

    def __init__(self, detector):
        self.detector = detector
        self.noise_names = detector.noise_names
        self.noise_family, self.noise_df = detector.noise_family, detector.noise_df

    def detect_logit(self, rows):
        return self.detector.detect_logit(np.array(rows))

    def noise_from_uniforms(self, rows, u):
        return self.detector.noise_from_uniforms(np.array(rows), u)

    def noise_log_prob(self, rows, noise):
        return self.detector.noise_log_prob(np.array(rows), noise)


def test_the_heads_evaluated_once_per_step_give_the_per_call_rollouts_bit_for_bit(problem, monkeypatch):
    from pemviz.core.detectors import ArrayRQMC, ConstantDetector
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.pem.noise import NoisePEM

    asked = []
    noise_params = NoisePEM.noise_params
    monkeypatch.setattr(NoisePEM, "noise_params", lambda self, x: asked.append(len(x)) or noise_params(self, x))
    fields = ("detected", "noise", "observations", "object_rows", "log_p", "log_q")
    target = problem.target
    plain = PerCall(target)
    for sampler, plain_sampler in (
        (target, plain),
        (ArrayRQMC(target), ArrayRQMC(PerCall(target))),
        (ConstantDetector(0.7), ConstantDetector(0.7)),
    ):
        for chunk in (150, 64):
            asked.clear()
            fast = RolloutBatch.concatenate(
                list(problem.stream(150, sampler, target, np.random.default_rng(11), chunk_size=chunk))
            )
            once = len(asked)
            slow = RolloutBatch.concatenate(
                list(problem.stream(150, plain_sampler, plain, np.random.default_rng(11), chunk_size=chunk))
            )
            for f in fields:
                assert np.array_equal(getattr(fast, f), getattr(slow, f)), (sampler, chunk, f)
            chunks = -(-150 // chunk)
            assert once <= chunks * fast.n_steps  # the noise head once per step ...
            assert len(asked) - once >= 2 * once  # ... and two or three times per step asked per call
