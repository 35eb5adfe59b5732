"""What a state-dependent proposal does to a feature: the feature that moved q(detect) most away from the PEM, and
q(detect) against the PEM's p(detect) over it, per bin of the rows a stage drew.

:func:`feature_effects` measures, for every column of the rows with their features, how far the shift ``s = logit
q(detect) - logit p_PEM(detect)`` changes across one standard deviation of that column (a centred finite difference:
cf. the sigma-normalised derivatives of Saltelli et al., "Global Sensitivity Analysis: The Primer", Wiley 2008, ch.
1). :func:`feature_curve` bins the rows by the column with the largest effect: per bin the mean q(detect) and
p_PEM(detect). :func:`stage_feature_curve` is that for a stage's rollouts, their features replayed. No I/O."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.special import log_expit

from pemviz.core.detectors import reads_state
from pemviz.core.features import with_state

if TYPE_CHECKING:  # annotations only
    from pemviz.core.features import FeaturesFn
    from pemviz.core.rollouts import RolloutBatch

N_BINS = 20
"""Bins of a feature curve: quantile bins of the feature over the rows (a bin per value for a feature of at most this
many values, e.g. a tracker's confirmed flag)."""

MAX_EFFECT_ROWS = 2_000
"""At most this many rows (evenly spaced) are perturbed to rank the features: 2 C evaluations of the proposal and the
PEM each, C the columns (a network's cost is per row)."""

MAX_ROLLOUTS = 200
"""At most this many of a stage's rollouts (evenly spaced) have their features replayed for its curve: about one more
simulation of each (:attr:`pemviz.core.problems.Problem.features`)."""

Q_SERIES, PEM_SERIES = "q(detect)", "PEM p(detect)"
"""The two series of a feature curve as the recording and the panel name them."""

EFFECT_FLOOR = 1e-6
"""Nats: a column whose effect (:func:`feature_effects`) is below this moves nothing (the rounding of logit q - logit
p where the proposal adds a constant to the PEM's logit is ~1e-15)."""


@dataclass(frozen=True)
class FeatureCurve:
    """q(detect) of a proposal and p(detect) of the PEM over the feature that moved q most (:func:`feature_curve`).

    Attributes:
        name: the feature's name (a column of :attr:`names`), e.g. ``object misses``.
        column: its column in the rows.
        names: the C names of the rows' columns.
        effects: float64 [C] each column's effect (nats, :func:`feature_effects`); 0 for a constant column.
        x: float64 [B] the mean of the feature in each bin (its unit), increasing.
        q_detect, p_detect: float64 [B] the mean q(detect) and p_PEM(detect) of the bin's rows.
        n_rows: int [B] the rows in each bin (none empty)."""

    name: str
    column: int
    names: tuple[str, ...]
    effects: np.ndarray
    x: np.ndarray
    q_detect: np.ndarray
    p_detect: np.ndarray
    n_rows: np.ndarray

    @property
    def effect(self) -> float:
        """The chosen feature's effect (nats)."""
        return float(self.effects[self.column])


def evenly_spaced(n: int, most: int) -> np.ndarray:
    """At most ``most`` of the indices 0..n-1, evenly spaced and increasing, int64 [min(n, most)] (all of them where
    there are no more); ``n`` = 0 gives none."""
    return np.unique(np.linspace(0, n - 1, min(n, most)).round().astype(np.int64))


def feature_effects(proposal: Any, target: Any, rows: np.ndarray, own_columns: int) -> np.ndarray:
    """How far each column moves the proposal's log-odds shift from the PEM over ``rows``, float64 [C] (nats): with
    ``s(x) = logit q(detect | x) - logit p(detect | x[:own_columns])``, column j's effect is the mean of ``|s(x +
    sd_j e_j / 2) - s(x - sd_j e_j / 2)|`` over at most :data:`MAX_EFFECT_ROWS` rows (non-finite ones left out; 0
    for a constant column).

    Args:
        proposal: a detector over the rows with their features (``detect_logit(rows [N, C]) -> float64 [N]``).
        target: the PEM, asked about the rows' own columns.
        rows: float64 [N, C] object rows with their state features after their own ``own_columns`` columns.
        own_columns: the rows' own columns (what the PEM reads), 1 <= own_columns <= C.
    Raises:
        ValueError: rows not 2-D, or ``own_columns`` outside 1..C."""
    x = np.asarray(rows, dtype=np.float64)
    if x.ndim != 2 or not 1 <= own_columns <= x.shape[1]:
        raise ValueError(f"feature_effects: rows [N, C] with 1 <= own_columns <= C, got {x.shape} and {own_columns}")
    x = x[evenly_spaced(x.shape[0], MAX_EFFECT_ROWS)] if x.shape[0] > MAX_EFFECT_ROWS else x
    sd = x.std(axis=0) if x.shape[0] else np.zeros(x.shape[1])

    def shift(at: np.ndarray) -> np.ndarray:
        q = np.asarray(proposal.detect_logit(at), dtype=np.float64)
        p = np.asarray(target.detect_logit(np.ascontiguousarray(at[:, :own_columns])), dtype=np.float64)
        with np.errstate(invalid="ignore"):
            return q - p

    out = np.zeros(x.shape[1])
    for j in np.flatnonzero(sd > 0):
        up, down = x.copy(), x.copy()
        up[:, j] += sd[j] / 2.0
        down[:, j] -= sd[j] / 2.0
        with np.errstate(invalid="ignore"):
            d = shift(up) - shift(down)
        d = d[np.isfinite(d)]
        out[j] = float(np.abs(d).mean()) if d.size else 0.0
    return out


def _bins(values: np.ndarray, n_bins: int) -> np.ndarray:
    """Each value's bin, int [N] in 0..B-1: one per distinct value where there are at most ``n_bins``, else quantile
    bins (edges at the 0, 1/n_bins, ..., 1 quantiles, repeated ones merged; the largest value in the last bin)."""
    distinct = np.unique(values)
    if distinct.size <= n_bins:
        return np.searchsorted(distinct, values)
    edges = np.unique(np.quantile(values, np.linspace(0.0, 1.0, n_bins + 1)))
    return np.clip(np.searchsorted(edges, values, side="right") - 1, 0, edges.size - 2)


def feature_curve(
    proposal: Any,
    target: Any,
    rows: np.ndarray,
    names: Sequence[str],
    own_columns: int,
    n_bins: int = N_BINS,
) -> FeatureCurve | None:
    """q(detect) against the PEM's p(detect) over the feature that moved q most from the PEM (module docstring).

    Args:
        proposal: the sampler's proposal, as :func:`feature_effects`.
        target: the PEM, as :func:`feature_effects`.
        own_columns: as :func:`feature_effects`.
        rows: float64 [N, C] the object rows a stage drew with their state features; rows with a non-finite value or
            PEM logit are left out.
        names: the C columns' names.
        n_bins: at most this many bins (:func:`_bins`), >= 1.
    Returns:
        the :class:`FeatureCurve`, or None: no row left, or no effect above :data:`EFFECT_FLOOR`.
    Raises:
        ValueError: ``names`` not one per column, ``n_bins`` < 1, or as :func:`feature_effects`."""
    x = np.asarray(rows, dtype=np.float64)
    if x.ndim != 2 or len(names) != x.shape[1] or n_bins < 1:
        raise ValueError(
            f"feature_curve: rows [N, C] with C names and n_bins >= 1, got {x.shape}, {len(names)} names, {n_bins}"
        )
    x = x[np.all(np.isfinite(x), axis=1)]
    p_logit = np.asarray(target.detect_logit(np.ascontiguousarray(x[:, :own_columns])), dtype=np.float64)
    x, p_logit = x[np.isfinite(p_logit)], p_logit[np.isfinite(p_logit)]
    if x.shape[0] == 0:
        return None
    effects = feature_effects(proposal, target, x, own_columns)
    if not np.any(effects >= EFFECT_FLOOR):
        return None
    j = int(np.argmax(effects))
    q = np.exp(log_expit(np.asarray(proposal.detect_logit(x), dtype=np.float64)))
    p = np.exp(log_expit(p_logit))
    b = _bins(x[:, j], n_bins)
    n = np.bincount(b)
    kept = n > 0
    x_mean, q_mean, p_mean = (np.bincount(b, weights=v)[kept] / n[kept] for v in (x[:, j], q, p))
    return FeatureCurve(str(names[j]), j, tuple(str(s) for s in names), effects, x_mean, q_mean, p_mean, n[kept])


def state_proposal_of(sampler: object) -> object | None:
    """The proposal that reads the state features inside a stage's sampler (itself, or a
    :class:`pemviz.core.detectors.StageSamplers` view's ``proposal``), None: the sampler reads none (e.g. the PEM of a
    pretraining stage)."""
    inner = getattr(getattr(sampler, "samplers", None), "proposal", sampler)
    return inner if reads_state(inner) else None


def stage_feature_curve(
    batch: RolloutBatch,
    sampler: object,
    target: Any,
    features: FeaturesFn | None,
    max_rollouts: int = MAX_ROLLOUTS,
) -> FeatureCurve | None:
    """:func:`feature_curve` of the proposal that drew ``batch`` (call it before an estimator refits in place) over
    the object rows of at most ``max_rollouts`` of its rollouts, their features replayed by ``features``
    (:attr:`pemviz.core.problems.Problem.features`); None: the sampler reads no state, no features, or
    :func:`feature_curve`'s None."""
    proposal = state_proposal_of(sampler)
    if proposal is None or features is None or batch.n == 0:
        return None
    keep = evenly_spaced(batch.n, max_rollouts)
    part = batch.select(keep) if keep.size < batch.n else batch
    replayed = features(part, None)
    if replayed is None:
        return None
    own = part.object_rows.shape[-1]
    full = with_state(part, replayed)
    rows = full.object_rows
    return feature_curve(proposal, target, rows.reshape(-1, rows.shape[-1]), full.row_names, own)
