"""The rollout-level mixture of ``research/mixture_proposal.py`` against an exact answer: on five independent steps
that each miss with probability 0.2 (failure: all five missed, p = 0.2^5), each rollout's log weight equals
log p(x) - log(sum_c share_c q_c(x)) computed by hand from its misses, the weights average to 1 over all 32 patterns,
and the mixture's estimate is within four standard errors of p."""

from __future__ import annotations

import itertools
import math
from types import SimpleNamespace

import numpy as np
from scipy.special import expit, logsumexp

from conftest import REPO, load_script

study = load_script(REPO / "research" / "mixture_proposal.py")
P_EXACT = 0.2**5
MIX = study.Mixture(0.1, np.array([[-1.0, -2.0, 0.5, -1.5, -0.5], [-2.5, -0.2, -1.0, 0.3, -3.0]]), np.array([0.7, 0.3]))


def _hand_log_w(miss: np.ndarray) -> float:
    """log p(x) - log q_mix(x) of one pattern of misses [5], from the mixture's definition."""
    logit0 = math.log(0.8 / 0.2)
    det = ~miss
    log_p = float(np.sum(np.log(np.where(det, 0.8, 0.2))))
    terms = [math.log(0.1) + log_p]
    for share, beta in zip((0.9 * MIX.pi), MIX.beta, strict=True):
        q = expit(logit0 + beta)
        terms.append(math.log(share) + float(np.sum(np.log(np.where(det, q, 1.0 - q)))))
    return log_p - float(logsumexp(terms))


def test_weights_by_hand_and_unbiased() -> None:
    batch = study.draw(study.AllMissed(), MIX, 200_000, np.random.default_rng(3))
    some = np.random.default_rng(4).choice(200_000, 300, replace=False)
    hand = np.array([_hand_log_w(batch.miss[i]) for i in some])
    np.testing.assert_allclose(batch.log_w[some], hand, rtol=0, atol=1e-12)
    # the study's mixture density sums to 1 over the 32 patterns: its q_c(x) of every pattern at once
    patterns = np.array(list(itertools.product([False, True], repeat=5)))  # True: missed
    rows = (np.repeat(np.arange(32), 5), np.tile(np.eye(5), (32, 1)), np.full(160, math.log(4.0)), ~patterns.ravel())
    log_q = study.component_log_q(rows, MIX.beta, 32)
    log_pem = study.component_log_q(rows, np.zeros((1, 5)), 32)
    log_mix = logsumexp(np.hstack([log_pem, log_q]) + MIX.log_shares()[None, :], axis=1)
    assert abs(math.exp(logsumexp(log_mix)) - 1.0) < 1e-12
    np.testing.assert_allclose(log_pem[:, 0] - log_mix, [_hand_log_w(m) for m in patterns], rtol=0, atol=1e-12)
    y = np.where(batch.failed, np.exp(batch.log_w), 0.0)
    assert batch.failed.sum() > 1000  # the mixture makes the failure common (the PEM: 64 in 200,000)
    se = y.std() / math.sqrt(y.size)
    assert abs(y.mean() - P_EXACT) < 4 * se, (y.mean(), P_EXACT, se)
    assert se < 0.05 * P_EXACT


def test_cross_entropy_with_em_finds_the_failure() -> None:
    args = SimpleNamespace(n=1000, n_final=2000, stages=6, rho=0.1, alpha=0.1, l2=1e-2, em=3, init_window=1)
    r = study.run(study.AllMissed(), 2, 0, args)
    lo, hi = np.exp(r["e"].log_ci)
    assert lo <= P_EXACT <= hi, (lo, hi)
    assert abs(r["e"].mu_hat / P_EXACT - 1.0) < 0.3
