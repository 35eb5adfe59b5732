"""A mixture stage's component densities come out of the simulation that drew its rollouts (ScoredTarget), and
equal a second pass over the rollouts (the fallback for remote executors)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pemviz.config import ExperimentConfig
from pemviz.detectors import ConstantDetector, LastAnswer, ScoredTarget
from pemviz.engine import Experiment
from pemviz.problems import build_problem
from pemviz.scenarios import simulate
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
    batches = [simulate(lambda: ToyBraking(ToyParams(20, 10, 5, 0.5)), n, ConstantDetector(0.5), scored, rng, T)
               for n in (3, 2)]  # two chunks of rollouts, stepped one after the other
    for b in batches:  # the target's log-probabilities: log 0.3 where detected, log 0.7 where missed
        np.testing.assert_allclose(b.log_p, np.where(b.detected, math.log(0.3), math.log(0.7)), rtol=1e-14)
    kept = scored.take(5, T)
    assert kept.shape == (1, 5, T)
    obs = np.concatenate([b.observations for b in batches])
    np.testing.assert_array_equal(kept[0], obs[:, :, 0] / 10.0 - 2.0)  # rollout by rollout, step by step
    assert scored.take(1, T) is None  # nothing left


def test_scored_target_refuses_asks_that_do_not_make_whole_rollouts():
    scored = ScoredTarget(ConstantDetector(0.3), (GapLogit(),))
    simulate(lambda: ToyBraking(ToyParams(20, 10, 5, 0.5)), 3, ConstantDetector(0.5), scored,
             np.random.default_rng(0), T)  # fmt: skip
    assert scored.take(4, T) is None  # 3 rollouts were drawn, not 4
    assert scored.take(3, T) is None  # and the unusable asks were dropped


def test_last_answer_asks_again_only_for_other_observations_or_after_forget():
    GapLogit.calls = 0
    memo = LastAnswer(GapLogit())
    obs = np.array([[3.0], [7.0]])
    first = memo.detect_logit(obs)
    np.testing.assert_array_equal(memo.detect_logit(obs.copy()), first)  # equal values: the same answer
    assert GapLogit.calls == 1
    memo.detect_logit(np.array([[3.0], [7.5]]))
    memo.forget()
    memo.detect_logit(np.array([[3.0], [7.5]]))
    assert GapLogit.calls == 3


def test_a_run_weighs_its_mixture_as_a_second_pass_over_the_rollouts_would(monkeypatch):
    """The default sampler's mixture weights from the logits kept while simulating, against the weights recomputed
    from the rollouts (the path Ray tasks take): asked about the same rows, step by step and block by block, the
    network gives the same bits, so the runs are the same run (the contract that serial and Ray runs agree)."""
    cfg = ExperimentConfig(n_stages=4, n_per_stage=80, n_final=200, ce_epochs=60, pretrain_epochs=60, seed=3)
    kept = Experiment(cfg, problem=build_problem("main")).run().final.estimate
    monkeypatch.setattr(ScoredTarget, "take", lambda self, n, n_steps: None)
    again = Experiment(cfg, problem=build_problem("main")).run().final.estimate
    assert kept.n_failures == again.n_failures > 0
    assert kept.log_mu_hat == again.log_mu_hat and kept.ess == again.ess
    assert math.exp(kept.log_mu_hat) == pytest.approx(1.984e-15, rel=0.5)  # and near the exact answer
