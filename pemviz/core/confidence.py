"""Confidence intervals and lower confidence bounds of a failure probability, as natural logs: the exact interval of
plain Monte Carlo's failure count, the log-scale interval of an importance-sampling mean widened by the weights'
Pareto tail, and lower bounds that hold whatever that tail (testing by betting; Markov's inequality on independent
runs' estimates). :class:`pemviz.core.estimate.Estimate` reports them."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

CI_LEVEL = 0.95
"""Coverage of every interval pemviz reports for mu_hat."""


TAIL_SHAPES = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
"""Pareto tail shapes k of :data:`TAIL_QUANTILES`."""

TAIL_QUANTILES = (2.01, 2.04, 2.14, 2.29, 2.53, 2.90, 3.42, 4.32, 6.37, 10.74)
"""For each k of :data:`TAIL_SHAPES`: the 97.5 % quantile of -z, z = (log mu_hat - log mu) / (se / mu_hat) the
studentised log-mean of N terms 1[fail] w with w generalized-Pareto of shape k, the largest over N = 500, 2,000 and
8,000 (20,000 replications each; ``python research/crowd_coverage.py --table``). From k = 1/2 on the weights'
variance is infinite and z tends to a skewed law of its own, whatever N (Logan, Mallows, Rice & Shepp, "Limit
distributions of self-normalized sums", Ann. Probab. 1(5), 1973): a run that has not yet drawn the tail's large
weights is low with a small standard error, so mu lies far above a symmetric interval."""


def tail_multiplier(khat: float, n: int) -> float:
    """The multiplier of se / mu_hat above log mu_hat for a 97.5 % upper end (:func:`log_mean_interval`): the larger
    of Student's t_{n-1} quantile and :data:`TAIL_QUANTILES` interpolated at the Pareto k-hat of the terms' tail
    (clamped to :data:`TAIL_SHAPES`); t alone where k-hat is nan (not fitted).

    Raises:
        ValueError: n < 2."""
    from scipy.special import stdtrit  # the Student-t quantile, without scipy.stats' import

    if n < 2:
        raise ValueError(f"tail_multiplier: need n >= 2 terms, got {n}")
    t = float(stdtrit(n - 1, 0.5 + CI_LEVEL / 2.0))
    if math.isnan(khat):
        return t
    return max(t, float(np.interp(khat, TAIL_SHAPES, TAIL_QUANTILES)))


def log_mean_interval(log_y: np.ndarray, khat: float = math.nan) -> tuple[float, float, float]:
    """log of the mean of y >= 0 (given as logs, -inf for 0, [N]) and its log-scale interval, nats.

    The lower end is exp(log mean - t_{N-1} se / mean) with se the standard error of the mean: the delta-method
    interval on the log scale (Owen, "Monte Carlo theory, methods and examples", 2013, Ch. 2 and 9), which stays
    inside (0, inf). The upper end is exp(log mean + c se / mean) with c = :func:`tail_multiplier` of ``khat``, the
    Pareto k-hat of the y's tail (Vehtari et al., "Pareto Smoothed Importance Sampling", JMLR 25(72), 2024): an
    importance-sampling mean falls short of mu with a small se until the run draws the weights that carry mu
    (Chatterjee & Diaconis, "The sample size required in importance sampling", Ann. Appl. Probab. 28(2), 2018), so
    with a heavy tail a symmetric interval misses mu from below far more often than 2.5 % (:data:`TAIL_QUANTILES`);
    nan ``khat``: c = t_{N-1}. Computed in log space."""
    from scipy.special import logsumexp

    n = log_y.size
    log_mean = float(logsumexp(log_y)) - math.log(n)
    if log_mean == -math.inf or n < 2:
        return log_mean, -math.inf, 0.0 if n < 2 else -math.inf
    ratio = np.exp(log_y - log_mean)  # y_i / mean, finite
    rel_se = float(np.std(ratio, ddof=1)) / math.sqrt(n)  # se / mean
    t = tail_multiplier(math.nan, n)
    return log_mean, log_mean - t * rel_se, log_mean + tail_multiplier(khat, n) * rel_se


def clopper_pearson(n_failures: int, n: int, level: float = CI_LEVEL) -> tuple[float, float]:
    """The exact (Clopper-Pearson) interval (lo, hi) at confidence ``level`` of a failure probability from
    ``n_failures`` = k failures in ``n`` rollouts drawn from the target: the beta quantiles ``B^-1(a/2; k, n - k + 1)``
    and ``B^-1(1 - a/2; k + 1, n - k)``, a = 1 - level (Clopper & Pearson, Biometrika 26(4), 1934), by
    ``scipy.special.betaincinv``: what ``scipy.stats.binomtest(...).proportion_ci(method="exact")`` computes, to its
    root finder's 1e-7, without importing scipy.stats (0.8 s).

    Raises:
        ValueError: ``n`` < 1, ``n_failures`` outside 0..n, or ``level`` outside (0, 1)."""
    from scipy.special import betaincinv

    k, n = int(n_failures), int(n)
    if n < 1 or not 0 <= k <= n or not 0.0 < level < 1.0:
        raise ValueError(
            f"clopper_pearson: need n >= 1, 0 <= failures <= n and a level in (0, 1), got {k} of {n} at " f"{level}"
        )
    a = 1.0 - level
    lo = 0.0 if k == 0 else float(betaincinv(k, n - k + 1, a / 2.0))
    hi = 1.0 if k == n else float(betaincinv(k + 1, n - k, 1.0 - a / 2.0))
    return lo, hi


def markov_lower_bound(log_estimates: np.ndarray, alpha: float = 1.0 - CI_LEVEL) -> float:
    """A lower confidence bound of p at level 1 - ``alpha``, log (nats), from n independent runs of unbiased
    non-negative estimators of p, their logs ``log_estimates`` float64 [n]: (log alpha + sum of the logs) / n. It
    holds whatever the weights' tail: E[prod X_i] = p^n, so P(prod X_i >= t) <= p^n / t (Markov's inequality). -inf
    when a run gave 0 or there is none; no such upper bound exists.

    Raises:
        ValueError: alpha outside (0, 1)."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"markov_lower_bound: alpha must be in (0, 1), got {alpha}")
    logs = np.asarray(log_estimates, dtype=np.float64)
    if logs.size == 0 or np.any(np.isneginf(logs)):
        return -math.inf
    return float((math.log(alpha) + math.fsum(logs.tolist())) / logs.size)


BET_FRACTIONS = 2.0 ** -np.arange(1, 31)
"""The betting fractions lambda_j = 2^-j, j = 1..30, of :func:`betting_lower_bound`, fixed before any rollout is
drawn: a run of n rollouts is best served by lambda ~ 1/n, so the grid serves runs of 2 to 10^9 rollouts."""

BET_BIN_NATS = 0.01
"""nats: :class:`BettingEvidence` rounds each log term down to a multiple of this before counting equal ones; a
smaller term only lowers the wealth, so the bound stays valid (and at most 1 % lower)."""


@dataclass(frozen=True, eq=False)
class BettingEvidence:
    """What :func:`betting_lower_bound` needs of a run's N terms X_i = 1[fail_i] w_i, kept small: the distinct values
    of log X_i > -inf rounded down to :data:`BET_BIN_NATS` (``log_x`` float64 [U], nats), how many terms have each
    (``counts`` int64 [U]), and N (``n``).

    Built by :meth:`of`; the wealth of a fraction lambda does not depend on the terms' order, so the counts suffice."""

    log_x: np.ndarray
    counts: np.ndarray
    n: int

    @classmethod
    def of(cls, log_terms: np.ndarray) -> BettingEvidence:
        """From the log terms log X_i float64 [N] (nats; -inf for X_i = 0, a rollout that did not fail)."""
        log_terms = np.asarray(log_terms, dtype=np.float64)
        finite = log_terms[np.isfinite(log_terms)]
        binned = np.floor(finite / BET_BIN_NATS) * BET_BIN_NATS
        values, counts = np.unique(binned, return_counts=True)
        return cls(values, counts.astype(np.int64), int(log_terms.size))

    def log_wealth(self, log_m: float) -> float:
        """log K(m) (nats) of the mixture of bettors against "E X <= m": K(m) = (1/J) sum_j prod_i (1 - lambda_j +
        lambda_j X_i / m) over :data:`BET_FRACTIONS`, in log space; non-increasing in m."""
        from scipy.special import logsumexp

        lam = BET_FRACTIONS
        log1m, loglam = np.log1p(-lam), np.log(lam)
        zeros = self.n - int(self.counts.sum())
        per = zeros * log1m
        if self.log_x.size:
            per = per + np.logaddexp(log1m[:, None], loglam[:, None] + (self.log_x - log_m)[None, :]) @ self.counts
        return float(logsumexp(per)) - math.log(lam.size)

    def lower_bound(self, alpha: float = 1.0 - CI_LEVEL) -> float:
        """The smallest m whose wealth stays below 1 / ``alpha`` (:func:`betting_lower_bound`), natural log, to 1e-6
        nats (rounded down); -inf with no positive term."""
        if self.log_x.size == 0:
            return -math.inf
        target = -math.log(alpha)
        hi = float(self.log_x.max())  # every factor <= 1 at m >= max X: K(hi) <= 1 < 1 / alpha
        lo = hi - 64.0
        while self.log_wealth(lo) < target:
            lo -= 64.0
        while hi - lo > 1e-6:
            mid = 0.5 * (lo + hi)
            if self.log_wealth(mid) >= target:
                lo = mid
            else:
                hi = mid
        return lo


def betting_lower_bound(log_terms: np.ndarray, alpha: float = 1.0 - CI_LEVEL) -> float:
    """A lower confidence bound of p at level 1 - ``alpha`` from a run's terms X_i = 1[fail_i] w_i, given as logs
    ``log_terms`` float64 [N] (nats, -inf for 0), that holds however heavy the weights' tail: it needs only X_i >= 0
    and E[X_i | the rollouts before i] = p, which exact importance weights give under any proposal.

    Testing by betting (Waudby-Smith & Ramdas, "Estimating means of bounded random variables by betting", JRSS B
    86(1), 2024, Sec. 4, for X >= 0): for each fraction lambda_j in :data:`BET_FRACTIONS`, K_j(m) = prod_i (1 -
    lambda_j + lambda_j X_i / m) is a non-negative martingale at m = p, and so is their mean K(m); by Ville's
    inequality {m : K(m) < 1 / alpha} holds p with probability >= 1 - alpha at every n at once. K is non-increasing
    in m, so the bound is found by bisection on log m. No such upper bound exists.

    Raises:
        ValueError: ``alpha`` outside (0, 1)."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"betting_lower_bound: alpha must be in (0, 1), got {alpha}")
    return BettingEvidence.of(log_terms).lower_bound(alpha)
