"""What a sampler really did: q(detect) over the states its rollouts visited, per bin of the first observation column
(the window's, e.g. the braking scenario's gap), beside the PEM's.

A reference-state curve of a state proposal (:meth:`pemviz.core.sampling.StateProposal.curve`) can sit near 1 while
the sampler misses in the states it reaches. Here q is read back from each rollout's ``log_q`` at the states of a
stage's rollouts, for any sampler: per bin the mean and quantiles of q(detect) and of the log-odds of a miss (nats),
and the same for the PEM from ``log_p``. Marginalising over the visited states is how Rubinstein & Kroese ("The
Cross-Entropy Method", Springer 2004, Ch. 3) compare a fitted density with the optimal one. No I/O."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.special import expit

from pemviz.core.detectors import reads_state
from pemviz.core.features import with_state

if TYPE_CHECKING:  # annotations only
    from pemviz.core.detectors import Detector
    from pemviz.core.features import FeaturesFn
    from pemviz.core.rollouts import RolloutBatch

QUANTILES = (0.1, 0.9)
"""The lower and upper quantile of a bin's spread."""

N_BINS = 26
"""Bins of a view over a proposal's curve grid (:func:`bins_over`): e.g. 0.5 m wide over the braking scenario's
grid 0-13 m."""

LOG_ODDS_SPAN_NATS = 12.0
"""A log-odds chart shows at most -12..12 nats (odds of 1:160,000); values beyond are drawn at the edge."""


def bins_over(grid: np.ndarray, n_bins: int = N_BINS) -> np.ndarray:
    """``n_bins`` equal bins over the span of a problem's curve grid
    (:attr:`pemviz.core.problems.Problem.curve_grid`), float64 [n_bins + 1] edges in the grid's unit (the first
    observation column's, e.g. metres).

    Raises:
        ValueError: a grid without a positive span, or ``n_bins`` < 1."""
    g = np.asarray(grid, dtype=np.float64)
    lo, hi = (float(g.min()), float(g.max())) if g.size else (math.nan, math.nan)
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo) or n_bins < 1:
        raise ValueError(
            f"bins_over: need a grid with a positive finite span and n_bins >= 1, got [{lo}, {hi}], " f"{n_bins}"
        )
    return np.linspace(lo, hi, n_bins + 1)


def log1mexp(log_x: np.ndarray) -> np.ndarray:
    """log(1 - exp(a)) for a <= 0, accurate near both ends (Maechler, "Accurately Computing log(1 - exp(-|a|))",
    the R project, 2012): ``log(-expm1(a))`` above -log 2, ``log1p(-exp(a))`` below. -inf at a = 0."""
    a = np.asarray(log_x, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.where(a > -math.log(2.0), np.log(-np.expm1(np.minimum(a, 0.0))), np.log1p(-np.exp(a)))


def prob_detect(log_p_action: np.ndarray, detected: np.ndarray) -> np.ndarray:
    """p(detect) from the log-probability of the action taken, float64 of the inputs' shape: exp(log p) if
    detected, else 1 - exp(log p) (``-expm1``, exact for small probabilities)."""
    lp = np.asarray(log_p_action, dtype=np.float64)
    return np.where(np.asarray(detected, bool), np.exp(lp), -np.expm1(lp))


def object_detect_probabilities(
    batch: RolloutBatch,
    i: int,
    sampler: Detector | None,
    target: Detector | None,
    features: FeaturesFn | None = None,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Each object's p(detect) under ``target`` and q(detect) under ``sampler`` along rollout ``i`` of a batch of
    several objects, float64 (p [T, M], q [T, M]), from the detectors' logits at its object rows (0 where out of
    sight); None for one object a step or without both detectors. Call it while ``sampler`` is the one that drew the
    batch; a state-reading detector gets the rows with the features replayed by ``features``, None where they cannot
    be.

    Raises:
        ValueError: ``i`` outside the batch."""
    if not 0 <= int(i) < batch.n:
        raise ValueError(f"object_detect_probabilities: rollout {i} outside a batch of {batch.n}")
    if batch.objects is None or batch.n_objects < 2 or sampler is None or target is None:
        return None
    rows = np.array(batch.object_rows[int(i)], dtype=np.float64)  # [T, M, G], a copy no detector keeps a view of
    wide = rows
    if reads_state(sampler) or reads_state(target):
        one = batch.select(np.array([int(i)]))
        replayed = features(one, None) if features is not None else None
        if replayed is None:  # a detector that reads the state, and no features to ask it with
            return None
        wide = np.array(with_state(one, replayed).object_rows[0], dtype=np.float64)

    def detect(detector: Detector) -> np.ndarray:
        at = wide if reads_state(detector) else rows
        logit = np.asarray(detector.detect_logit(at.reshape(-1, at.shape[-1])), dtype=np.float64)
        return expit(logit).reshape(rows.shape[:2])

    return detect(target), detect(sampler)


def miss_log_odds(log_p_action: np.ndarray, detected: np.ndarray) -> np.ndarray:
    """log p(miss) - log p(detect) (nats) from the log-probability of the action taken, float64 of the inputs'
    shape: positive where a miss is the likelier outcome."""
    lp = np.asarray(log_p_action, dtype=np.float64)
    other = log1mexp(lp)
    with np.errstate(invalid="ignore"):
        return np.where(np.asarray(detected, bool), other - lp, lp - other)


@dataclass(frozen=True)
class ProposalView:
    """q(detect) of the sampler and p(detect) of the PEM over one batch's visited states, per gap bin.

    Attributes:
        edges_m: float64 [B + 1] the bins' edges (metres), bin b holding edges[b] <= gap < edges[b + 1].
        centres_m: float64 [B] the bins' centres (metres).
        n_states: int [B] visited states (rollouts x steps) in each bin.
        q_mean, q_lo, q_hi: float64 [B] mean and :data:`QUANTILES` of q(detect) (nan: empty).
        p_mean, p_lo, p_hi: float64 [B] the same of p_PEM(detect).
        q_log_odds, q_log_odds_lo, q_log_odds_hi: float64 [B] median and :data:`QUANTILES` of log q(miss) /
            q(detect) (nats).
        p_log_odds, p_log_odds_lo, p_log_odds_hi: float64 [B] the same of the PEM.
        window_m: the gap below which the window means are taken (metres).
        q_miss_window, p_miss_window: the mean q(miss) and p_PEM(miss) over the states below ``window_m`` (nan:
            none)."""

    edges_m: np.ndarray
    centres_m: np.ndarray
    n_states: np.ndarray
    q_mean: np.ndarray
    q_lo: np.ndarray
    q_hi: np.ndarray
    p_mean: np.ndarray
    p_lo: np.ndarray
    p_hi: np.ndarray
    q_log_odds: np.ndarray
    q_log_odds_lo: np.ndarray
    q_log_odds_hi: np.ndarray
    p_log_odds: np.ndarray
    p_log_odds_lo: np.ndarray
    p_log_odds_hi: np.ndarray
    window_m: float
    q_miss_window: float
    p_miss_window: float


def _bin_order(bins: np.ndarray, n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """``(order, bounds)``: the states [S] sorted by their bin (``bins`` [S] in 0..n_bins-1; stable: within a bin in
    their own order) and where each bin starts and ends in that order (int [n_bins + 1]), for :func:`_by_bin`."""
    order = np.argsort(bins, kind="stable")
    return order, np.searchsorted(bins[order], np.arange(n_bins + 1))


def _by_bin(
    values: np.ndarray, sorted_bins: tuple[np.ndarray, np.ndarray], n_bins: int, median: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centre, lo, hi) of ``values`` [S] per bin in 0..n_bins-1 (``sorted_bins``: :func:`_bin_order` of the states'
    bins): the mean (or median) and :data:`QUANTILES`."""
    out = np.full((3, n_bins), np.nan)
    order, bounds = sorted_bins
    for b in range(n_bins):
        v = values[order[bounds[b] : bounds[b + 1]]]
        v = v[~np.isnan(v)]
        if v.size:
            lo, mid, hi = np.quantile(v, (QUANTILES[0], 0.5, QUANTILES[1]))
            out[:, b] = (mid if median else v.mean(), lo, hi)
    return out[0], out[1], out[2]


def proposal_view(
    inputs: np.ndarray,
    detected: np.ndarray,
    log_q: np.ndarray,
    log_p: np.ndarray,
    edges_m: np.ndarray,
    window_m: float = 10.0,
) -> ProposalView:
    """The sampler's and the PEM's detection probabilities over the states a batch of rollouts visited, by the first
    observation column (the proposal's input).

    Args:
        inputs: float64 [N, T] the first observation column at each visited state (the edges' unit, e.g. metres).
        detected: bool [N, T] the action taken there.
        log_q: float64 [N, T] log q(action) under the detector that drew the rollout (nats).
        log_p: float64 [N, T] log p_PEM(action) (nats).
        edges_m: float64 [B + 1] increasing bin edges (e.g. metres); states outside them count in no bin.
        window_m: the input below which the mean miss probabilities are also taken over all states (the problem's
            window, in the same unit).
    Raises:
        ValueError: arrays of different shapes, or edges not increasing with at least one bin."""
    gap = np.asarray(inputs, dtype=np.float64).ravel()
    d = np.asarray(detected, dtype=bool).ravel()
    lq, lp = np.asarray(log_q, dtype=np.float64).ravel(), np.asarray(log_p, dtype=np.float64).ravel()
    edges = np.asarray(edges_m, dtype=np.float64)
    shape = np.shape(inputs)
    if not (np.shape(detected) == np.shape(log_q) == np.shape(log_p) == shape):
        raise ValueError(
            f"proposal_view: inputs, detected, log_q and log_p need one shape [N, T], got {shape}, "
            f"{np.shape(detected)}, {np.shape(log_q)}, {np.shape(log_p)}"
        )
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError(f"proposal_view: edges_m must be increasing with at least 2 entries, got {edges_m!r}")
    n_bins = edges.size - 1
    b = np.searchsorted(edges, gap, side="right") - 1
    inside = (b >= 0) & (b < n_bins)
    b, q_det, p_det = b[inside], prob_detect(lq, d)[inside], prob_detect(lp, d)[inside]
    q_lo_odds, p_lo_odds = miss_log_odds(lq, d)[inside], miss_log_odds(lp, d)[inside]
    window = gap < window_m
    sorted_bins = _bin_order(b, n_bins)  # once for the four series
    return ProposalView(
        edges,
        (edges[:-1] + edges[1:]) / 2.0,
        np.bincount(b, minlength=n_bins),
        *_by_bin(q_det, sorted_bins, n_bins, median=False),
        *_by_bin(p_det, sorted_bins, n_bins, median=False),
        *_by_bin(q_lo_odds, sorted_bins, n_bins, median=True),
        *_by_bin(p_lo_odds, sorted_bins, n_bins, median=True),
        float(window_m),
        float(prob_detect(lq, ~d)[window].mean()) if window.any() else math.nan,
        float(prob_detect(lp, ~d)[window].mean()) if window.any() else math.nan,
    )


def batch_proposal_view(batch, edges_m: np.ndarray, window_m: float = 10.0) -> ProposalView | None:
    """:func:`proposal_view` of a :class:`pemviz.core.rollouts.RolloutBatch` by its first observation column (None: its
    rollouts perceive several objects, whose densities the batch holds only per step)."""
    if batch.n_objects != 1:
        return None
    return proposal_view(
        batch.observations[:, :, 0], batch.detected[..., 0], batch.log_q, batch.log_p, edges_m, window_m
    )
