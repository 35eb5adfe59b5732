"""A mixture stage's component densities come out of the simulation that drew its rollouts (ScoredTarget), and
equal a second pass over the rollouts (the fallback for remote executors)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.core.detectors import ConstantDetector, StageSamplers, WindowDetector
from pemviz.core.scored_target import ScoredTarget, by_rollout
from pemviz.engine.experiment import Experiment
from pemviz.estimators.cross_entropy import DefensiveDetector
from pemviz.scenarios import simulate
from pemviz.scenarios.problems import build_problem
from pemviz.scenarios.toy import ToyBraking, ToyParams

T = 6


class GapLogit:
    """A detector whose logit is the gap itself (distinct values per row, so a mix-up of rows shows)."""

    calls = 0

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        GapLogit.calls += 1
        return np.asarray(obs)[:, 0] / 10.0 - 2.0


def test_scored_target_answers_as_the_target_and_hands_over_the_extras_logits_chunk_by_chunk():
    target, extra = ConstantDetector(0.3), GapLogit()
    scored = ScoredTarget(target, (extra,))
    rng = np.random.default_rng(1)
    batches = [
        simulate(lambda: ToyBraking(ToyParams(20, 10, 5, 0.5)), n, ConstantDetector(0.5), scored, rng, T)
        for n in (3, 2)
    ]  # two chunks of rollouts, stepped one after the other
    for b in batches:  # the target's log-probabilities: log 0.3 where detected, log 0.7 where missed
        np.testing.assert_allclose(b.log_p, np.where(b.detected[..., 0], math.log(0.3), math.log(0.7)), rtol=1e-14)
    groups = scored.take(5, T)
    assert [(row, block.shape) for row, block in groups] == [(0, (2, T, 3)), (3, (2, T, 2))]  # [K + 1, T, r]
    kept, target_logit = by_rollout(groups, 5)
    assert kept.shape == (1, 5, T, 1)  # [K, n, T, M]: one object per step
    obs = np.concatenate([b.observations for b in batches])
    np.testing.assert_array_equal(kept[0, ..., 0], obs[:, :, 0] / 10.0 - 2.0)  # rollout by rollout, step by step
    np.testing.assert_array_equal(
        target_logit, np.full((5, T, 1), ConstantDetector(0.3).detect_logit(np.zeros((1, 1)))[0])
    )
    assert scored.take(1, T) is None  # nothing left


def test_scored_target_refuses_asks_that_do_not_make_whole_rollouts():
    scored = ScoredTarget(ConstantDetector(0.3), (GapLogit(),))
    simulate(
        lambda: ToyBraking(ToyParams(20, 10, 5, 0.5)), 3, ConstantDetector(0.5), scored, np.random.default_rng(0), T
    )
    assert scored.take(4, T) is None  # 3 rollouts were drawn, not 4
    assert scored.take(3, T) is None  # and the unusable asks were dropped


class Counting:
    """A detector that counts the rows it was asked about (a proposal network costs per row)."""

    def __init__(self, detector) -> None:
        self.detector, self.calls, self.rows = detector, 0, 0

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        self.calls, self.rows = self.calls + 1, self.rows + len(obs)
        return self.detector.detect_logit(obs)


def test_stage_samplers_evaluate_each_detector_once_per_step_and_the_proposal_only_inside_the_window():
    # gaps 1, 3, 6, 9, 12 m: the proposal draws in [2, 10) m (above the decided 2 m, below the 10 m window), the target
    # elsewhere; the plain sampler is the old WindowDetector around the proposal, the defensive one around the defensive
    # mixture, value for value
    proposal, target = Counting(GapLogit()), Counting(ConstantDetector(0.9))
    samplers = StageSamplers(proposal, target, radius_m=10.0, floor_m=2.0, eps=0.2)
    obs = np.array([[1.0], [3.0], [6.0], [9.0], [12.0]])
    for detector in (samplers.defensive, samplers.target, samplers.plain, samplers.defensive):
        detector.detect_logit(obs.copy())  # equal values, other arrays: one evaluation
    assert (proposal.calls, proposal.rows, target.calls, target.rows) == (1, 3, 1, 5)
    np.testing.assert_array_equal(samplers.target.detect_logit(obs), ConstantDetector(0.9).detect_logit(obs))
    np.testing.assert_array_equal(
        samplers.plain.detect_logit(obs), WindowDetector(GapLogit(), ConstantDetector(0.9), 10.0, 2.0).detect_logit(obs)
    )
    np.testing.assert_array_equal(
        samplers.defensive.detect_logit(obs),
        WindowDetector(DefensiveDetector(GapLogit(), 0.2), ConstantDetector(0.9), 10.0, 2.0).detect_logit(obs),
    )
    with pytest.raises(ValueError, match="read-only"):
        samplers.plain.detect_logit(obs)[0] = 1.0  # the kept answer cannot be changed through a caller
    samplers.forget()  # the proposal was fitted: asked again
    samplers.plain.detect_logit(obs)
    samplers.plain.detect_logit(obs[:4])  # other observations: asked again
    assert (proposal.calls, target.calls) == (3, 3)
    assert samplers.describe(2) == "(1 - 0.2) proposal + 0.2 x 50 % within 10 m, target beyond"
    no_eps = StageSamplers(proposal, target)  # no defensive share: the defensive sampler is the plain one
    assert no_eps.defensive is no_eps.plain and no_eps.describe(2) == "proposal"


def kept_and_asked_again(cfg: ExperimentConfig, monkeypatch) -> tuple:
    """The final estimates of a braking run from the logits kept while simulating, then of the same run with every
    component's densities recomputed from the rollouts (``ScoredTarget.take`` hands nothing over); both have failures
    and the same estimate and ESS."""
    kept = Experiment(cfg, problem=build_problem("main")).run().final.estimate
    monkeypatch.setattr(ScoredTarget, "take", lambda self, n, n_steps, n_objects=1, skip=None: None)
    again = Experiment(cfg, problem=build_problem("main")).run().final.estimate
    assert kept.n_failures == again.n_failures > 0
    assert kept.log_mu_hat == again.log_mu_hat and kept.ess == again.ess
    return kept, again


def test_a_run_weighs_its_mixture_as_a_second_pass_over_the_rollouts_would(monkeypatch):
    """The default sampler's mixture weights from the logits kept while simulating, against the weights recomputed
    from the rollouts (the path Ray tasks take): asked about the same rows, step by step and block by block, the
    network gives the same bits, so the runs are the same run (the contract that serial and Ray runs agree)."""
    cfg = ExperimentConfig.of(n_stages=4, n_per_stage=80, n_final=200, ce_epochs=60, pretrain_epochs=60, seed=3)
    kept, _ = kept_and_asked_again(cfg, monkeypatch)
    assert math.exp(kept.log_mu_hat) == pytest.approx(1.984e-15, rel=0.5)  # and near the exact answer


def test_streamed_chunks_take_their_own_components_densities_as_drawn(monkeypatch):
    """Streamed in chunks of one component each, a chunk's own component's densities are its log q as drawn, not
    computed again: the run equals the one that recomputes every component's densities from the rollouts."""
    from pemviz.estimators.ce_mixture import MixtureWeights

    cfg = ExperimentConfig.of(
        n_stages=4,
        n_per_stage=200,
        n_final=300,
        ce_epochs=60,
        pretrain_epochs=60,
        seed=3,
        uniforms="iid",
        chunk_rollouts=40,
    )
    drawn_by = MixtureWeights._drawn_by
    owners: list[int | None] = []
    monkeypatch.setattr(MixtureWeights, "_drawn_by", lambda self, *a: owners.append(drawn_by(self, *a)) or owners[-1])
    kept_and_asked_again(cfg, monkeypatch)
    assert {0, 1, None} <= set(owners)  # the plain and the defensive proposal's chunks, and the target's
