"""Splitting ranked by a score learned on a pilot's state features (research/learned_score.py): unbiased on a toy
with an exact answer, a path functional that only falls, fitted on the pilot's streams alone."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pemviz.estimators.ams import run_ams
from pemviz.scenarios.problems import build_problem

from conftest import REPO, load_script

study = load_script(REPO / "research" / "learned_score.py")
Z_SCALE, LearnedScore, design = study.Z_SCALE, study.LearnedScore, study.design


def test_learned_score_ams_is_unbiased_on_the_toy():
    """toy (10, 5, 3, 0.9), p = 1e-3 exactly: the mean of p_hat / p over 300 seeds of N = 100, k = 10, each with its
    own pilot (measured 1.02 +- 0.033), within 3 standard errors of 1, the standard error small
    enough that a 50 % bias would show; and the run is not the robustness's (the score changes the particles kept)."""
    pb = build_problem("toy-1e-3")
    x = np.array(
        [
            math.exp(run_ams(pb, 100, 10, seed=s, score=LearnedScore(pb, s)).estimate().log_mu_hat - pb.exact_log_p)
            for s in range(300)
        ]
    )
    se = x.std(ddof=1) / math.sqrt(x.size)
    assert abs(x.mean() - 1.0) <= 3.0 * se and se < 0.15, f"mean p_hat / p = {x.mean():.3f} +- {se:.3f}"
    a, b = run_ams(pb, 100, 10, seed=3, score=LearnedScore(pb, 3)), run_ams(pb, 100, 10, seed=3)
    assert a.estimate().log_mu_hat != b.estimate().log_mu_hat


def test_the_score_falls_along_a_path_as_the_fitted_log_odds_rise():
    """The score at step t is exp(-max_{t' <= t} z(t') / Z_SCALE), z the fitted log-odds of the step's row: it never
    rises along a rollout, and it moves (the fit separates the toy's states: misses in a row raise the odds)."""
    pb = build_problem("toy-1e-3")
    score = LearnedScore(pb, 0)
    assert score.model is not None and 0 < score.pilot_failures < score.pilot_rollouts
    batch = pb.simulate(200, pb.target, pb.target, np.random.default_rng(5))
    g = score.graded(batch)
    assert np.all(np.diff(g, axis=1) <= 0.0) and np.all(g > 0.0)
    assert pb.features is not None
    z = score.log_odds(design(pb, batch, pb.features(batch, None)))
    np.testing.assert_allclose(g, np.exp(-np.maximum.accumulate(z, axis=1) / Z_SCALE), rtol=1e-12)
    assert np.unique(g[:, -1]).size > 2


def test_the_pilot_draws_from_its_own_streams_and_is_counted():
    """The same seed fits the same score (bit for bit); another seed another; the pilot's simulated steps and its
    replays are in the score's steps (more than its rollouts' own steps), so in the run's rollout-equivalents."""
    pb = build_problem("toy-1e-3")
    a, b, c = (LearnedScore(pb, s) for s in (4, 4, 5))
    coef = [s.model[1].coef_ for s in (a, b, c)]  # type: ignore[index]
    np.testing.assert_array_equal(coef[0], coef[1])
    assert not np.array_equal(coef[0], coef[2])
    t = pb.simulate(1, pb.target, pb.target, np.random.default_rng(0)).n_steps
    assert a.steps > a.pilot_rollouts * t
    r = run_ams(pb, 100, 10, seed=4, score=LearnedScore(pb, 4))
    assert r.n_simulations >= -(-(r.steps + a.steps) // t)


def test_learned_score_without_state_features_gives_one_line():
    with pytest.raises(ValueError, match=r"^the learned score needs a scenario that reports its state features; "):
        LearnedScore(build_problem("latched"), 0)
