"""The look-ahead's ties broken by pessimistic continuations (research/cut_in_ams_ties.py): the draws miss exactly
the planned steps, the tie-break moves the score by less than TIE_BREAK and separates tied states, and splitting
ranked by it is unbiased on a toy with an exact answer."""

from __future__ import annotations

import math

import numpy as np
from pemviz.estimators.ams import run_ams
from pemviz.estimators.lookahead_score import LookAheadScore
from pemviz.scenarios.problems import build_problem

from conftest import REPO, load_script

study = load_script(REPO / "research" / "cut_in_ams_ties.py")


def test_missing_uniforms_miss_the_planned_steps_of_each_rollout():
    """Rollouts starting at steps 0, 2 and 5 with m = 2, two objects of 1 + 2 uniforms: the detection uniforms are just
    below 1 at steps [at, at + 2) of each rollout and 0.5 elsewhere; the error uniforms are always 0.5."""
    draws = study.MissingUniforms(np.array([0, 2, 5]), 2, 3)
    for t in range(8):
        u = draws.random(3 * 2 * 3).reshape(3, 2, 3)
        missed = np.array([0 <= t < 2, 2 <= t < 4, 5 <= t < 7])
        assert np.all((u[:, :, 0] > 0.99) == missed[:, None]) and np.all(u[:, :, 0][~missed] == 0.5)
        assert np.all(u[:, :, 1:] == 0.5)


def test_the_tie_break_moves_the_score_less_than_its_bound_and_separates_ties():
    """On the toy the nominal look-ahead takes 2 values over 50 rollouts' scored steps (measured), the tie-broken one
    more; each score moves up by 0 < delta < TIE_BREAK, and the pessimistic continuations' steps are counted."""
    pb = build_problem("toy-1e-3")
    batch = pb.simulate(50, pb.target, pb.target, np.random.default_rng(0))
    first = np.full(50, -1)
    nominal, broken = LookAheadScore(pb), study.TieBrokenLookAhead(pb, (1, 2))
    g0, g1 = nominal.score(batch, first), broken.score(batch, first)
    scored = np.isfinite(g0)
    assert np.array_equal(scored, np.isfinite(g1))
    delta = g1[scored] - g0[scored]
    assert np.all((delta > 0.0) & (delta < study.TIE_BREAK))
    assert np.unique(g0[scored]).size == 2 and np.unique(g1[scored]).size > 2
    assert broken.steps == 3 * nominal.steps


def test_splitting_on_the_tie_broken_look_ahead_is_unbiased_on_the_toy():
    """toy (10, 5, 3, 0.9), p = 1e-3 exactly: the mean of p_hat / p over 300 seeds of N = 100, k = 10 (measured
    0.81 +- 0.09 over seeds 0-19) within 3 standard errors of 1, the standard error small enough that a 50 % bias
    would show."""
    pb = build_problem("toy-1e-3")
    x = []
    for s in range(300):
        e = run_ams(pb, 100, 10, seed=s, score=study.TieBrokenLookAhead(pb, (1, 2))).estimate()
        x.append(math.exp(e.log_mu_hat - pb.exact_log_p) if e.n_failures else 0.0)
    ratios = np.array(x)
    se = ratios.std(ddof=1) / math.sqrt(ratios.size)
    assert abs(ratios.mean() - 1.0) <= 3.0 * se and se < 0.15, f"mean p_hat / p = {ratios.mean():.3f} +- {se:.3f}"
