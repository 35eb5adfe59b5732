"""Diagnostics of importance weights from log-weights: the effective sample size and the Pareto k-hat of their tail.
pemviz's own rather than ``arviz.psislw``'s, whose tail size and relative efficiency would move k-hat and every
verdict."""

from __future__ import annotations

import math

import numpy as np
from scipy.special import softmax


def effective_sample_size(log_weights: np.ndarray) -> float:
    """Kish's effective sample size (sum w)^2 / sum w^2 of weights given as natural logs, float64 [S] (S >= 1),
    computed relative to the largest (Kong, Liu & Wong, JASA 89(425), 1994; Owen 2013, Sec. 9.3): in [1, S]; 0 when
    every weight is 0; nan when a weight is nan or +inf."""
    lw = np.asarray(log_weights, dtype=np.float64)
    if lw.size and np.all(lw == -np.inf):
        return 0.0
    rel = np.exp(lw - lw.max())  # weights relative to the largest: finite whatever the scale of the logs
    return float(rel.sum() ** 2 / np.square(rel).sum())


def pareto_khat(log_values: np.ndarray) -> float:
    """Pareto k-hat of the upper tail of a sample of non-negative values given as natural logs, [S].

    The generalized Pareto distribution (:func:`fit_generalized_pareto`) is fitted to the exceedances of the M =
    min(S / 5, 3 sqrt(S)) largest values over the next one (Vehtari et al., "Pareto Smoothed Importance Sampling",
    JMLR 2024, Sec. 3); -inf values (zeros) may be present, and the tail is then taken from the positive values
    alone. Exceedances within 1e-9 (relative) are ties. Returns 0 for a flat or discrete tail (fewer than 5 distinct
    exceedances) and nan for fewer than 25 positive values."""
    lv = np.asarray(log_values, dtype=np.float64)
    m = int(min(lv.size / 5.0, 3.0 * math.sqrt(lv.size)))
    if m < lv.size:  # only the M + 1 largest are needed, sorted: a partition, then a sort of those
        lv = np.sort(np.partition(lv, lv.size - m - 1)[lv.size - m - 1 :])
    if m >= lv.size or not np.isfinite(lv[lv.size - m - 1]):
        lv = np.sort(np.asarray(log_values, dtype=np.float64))
        lv = lv[np.isfinite(lv)]
        m = int(min(lv.size / 5.0, 3.0 * math.sqrt(lv.size)))
    if m < 5:
        return math.nan
    top = lv[-1]
    tail = np.exp(lv[lv.size - m :] - top) - math.exp(lv[lv.size - m - 1] - top)  # scale-free exceedances
    tail = tail[tail > 1e-9]  # ties with the cutoff carry no tail information (and break the fit's quartile)
    if tail.size < 5 or np.unique(np.round(tail / 1e-9)).size < 5:  # a few repeated values: a bounded tail
        return 0.0
    k, _ = fit_generalized_pareto(tail)
    return k


def fit_generalized_pareto(x: np.ndarray) -> tuple[float, float]:
    """(k, sigma) of a generalized Pareto distribution fitted to positive exceedances ``x``, float64 [M], by the
    empirical Bayes estimate of Zhang & Stephens, "A new and efficient estimation method for the generalized Pareto
    distribution", Technometrics 51(3), 2009, with the weakly informative prior on k of Vehtari et al. (JMLR 2024):
    ``pyro.ops.stats.fit_generalized_pareto`` (the tests' oracle) in numpy, the candidates' weights as a softmax.

    Raises:
        ValueError: ``x`` not 1-D with at least one value."""
    x = np.sort(np.asarray(x, dtype=np.float64))
    if x.ndim != 1 or x.size < 1:
        raise ValueError(f"fit_generalized_pareto: x must be 1-D with at least one value, got shape {x.shape}")
    n = x.size
    m = 30 + int(math.sqrt(n))
    b = 1.0 - math.sqrt(m) / np.sqrt(np.arange(1, m + 1, dtype=np.float64) - 0.5)  # candidate b = k / sigma
    b /= 3.0 * x[int(n / 4 - 0.5)]
    b += 1.0 / x[-1]
    ks = np.log1p(-b[:, None] * x).mean(axis=1)
    profile = n * (np.log(-b / ks) - (ks + 1.0))  # the profile log-likelihood of each candidate
    weights = softmax(profile)  # each candidate's posterior weight, 1 / sum_j exp(L_j - L_i), in log space
    keep = weights > 1e-30
    weights, b = weights[keep] / weights[keep].sum(), b[keep]
    b_hat = float((b * weights).sum())
    k = float(np.log1p(-b_hat * x).mean())
    sigma = -k / b_hat
    return k * n / (n + 10.0) + 5.0 / (n + 10.0), sigma
