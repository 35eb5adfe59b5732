"""The failure population of an importance-sampling estimate: which failing rollouts carry its probability.

The share of p that failure i carries is its term of mu_hat = (1/N) sum_i 1[fail_i] w_i (pooled: w_i lambda_k N /
n_k) over the failures' sum, its self-normalised weight among the failures (Owen, "Monte Carlo theory, methods and
examples", 2013, Sec. 9.2); shares add up to 1. Failures that share their decisive events (a key the caller gives)
form groups whose shares add. No I/O, no scene; logs in nats, shares fractions of mu_hat."""

from __future__ import annotations

import math
from collections.abc import Hashable, Sequence
from dataclasses import dataclass

import numpy as np

from pemviz.core import libm


def pooling_shifts(stage_weights: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """log(lambda_k N / n_k) of each of K pooled stages (nats, float64 [K]): what a stage's log-weights gain when the
    estimate pools the stages with weights lambda_k (N = sum n_k; -inf for lambda_k = 0).

    Args:
        stage_weights: lambda_k >= 0, [K], summing to 1.
        sizes: n_k, the stages' rollouts, [K]."""
    n = np.asarray(sizes, dtype=np.float64)
    with np.errstate(divide="ignore"):
        return np.log(np.asarray(stage_weights, dtype=np.float64)) + math.log(n.sum()) - np.log(n)


@dataclass(frozen=True)
class FailureShares:
    """The failing rollouts of an estimate with the share of mu_hat each carries, largest share first.

    Attributes:
        stage: int [F] the stage that drew each failure.
        index: int [F] its rollout number in that stage.
        log_share: float64 [F] log of its share of mu_hat (nats, <= 0; the shares add up to 1), non-increasing.
        log_weight: float64 [F] its importance log-weight as the estimate counts it (nats, pooling constant
            included).
        log_p: float64 [F] log p_PEM of its events before the failure (nats; a log-likelihood with measurement
            errors)."""

    stage: np.ndarray
    index: np.ndarray
    log_share: np.ndarray
    log_weight: np.ndarray
    log_p: np.ndarray

    @property
    def n(self) -> int:
        """F, the failures."""
        return int(self.stage.size)

    def share(self) -> np.ndarray:
        """float64 [F] each failure's share of mu_hat (fractions adding up to 1; empty without failures)."""
        return libm.exp(self.log_share)

    def position(self, stage: int, index: int) -> int | None:
        """The rank (0 = the largest share) of rollout ``index`` of ``stage``, or None when it is not a failure of
        the estimate."""
        hit = np.flatnonzero((self.stage == stage) & (self.index == index))
        return int(hit[0]) if hit.size else None


def failure_shares(
    parts: Sequence[tuple[int, np.ndarray, np.ndarray, np.ndarray]], stage_weights: np.ndarray | None = None
) -> FailureShares:
    """The failures of an estimate pooled over K stages, each with its share of mu_hat.

    Args:
        parts: per stage k, (stage number, log-weights [n_k] as the estimate weighs them (nats), failed bool [n_k],
            log p before the failure [n_k] (nats)), in the order the estimate pools them.
        stage_weights: lambda_k >= 0, [K], summing to 1, as :func:`pemviz.estimators.pooling.pool` takes them; None:
            every rollout alike (lambda_k = n_k / N).
    Returns:
        The failures sorted by share, largest first (ties: the earlier stage, then the lower index).
    Raises:
        ValueError: arrays of one stage of unequal lengths, or ``stage_weights`` of another length than ``parts``."""
    if stage_weights is not None and len(stage_weights) != len(parts):
        raise ValueError(f"failure_shares: {len(stage_weights)} stage weights for {len(parts)} stages")
    sizes = np.array([np.size(lw) for _, lw, _, _ in parts], dtype=np.float64)
    shifts = np.zeros(len(parts)) if stage_weights is None else pooling_shifts(stage_weights, sizes)
    stage, index, log_w, log_p = [], [], [], []
    for k, (number, lw, failed, lp) in enumerate(parts):
        lw, failed, lp = np.asarray(lw, np.float64), np.asarray(failed, bool), np.asarray(lp, np.float64)
        if not lw.shape == failed.shape == lp.shape:
            raise ValueError(
                f"failure_shares: stage {number} has arrays of shapes {lw.shape}, {failed.shape}, "
                f"{lp.shape}; they must be equal"
            )
        shift = float(shifts[k])
        rows = np.flatnonzero(failed & np.isfinite(lw))
        stage.append(np.full(rows.size, number, dtype=np.int64))
        index.append(rows.astype(np.int64))
        log_w.append(lw[rows] + shift)
        log_p.append(lp[rows])
    s, i, w, p = (np.concatenate(a) if a else np.zeros(0) for a in (stage, index, log_w, log_p))
    s, i = s.astype(np.int64), i.astype(np.int64)
    order = np.lexsort((i, s, -w))  # the largest weight first; ties by stage, then index
    w = w[order]
    total = float(libm.logsumexp(w)) if w.size else 0.0
    return FailureShares(s[order], i[order], w - total, w, p[order])


@dataclass(frozen=True)
class FailureGroup:
    """Failures that share their decisive events.

    Attributes:
        key: the scene's key of the events (e.g. the last step at which one detection still saved the rollout).
        label: the key in words.
        count: its failures.
        share: the fraction of mu_hat its failures carry (the groups' shares add up to 1).
        first: the rank (in :class:`FailureShares` order) of its failure with the largest share."""

    key: Hashable
    label: str
    count: int
    share: float
    first: int


def failure_groups(shares: FailureShares, keys: Sequence[Hashable], labels: dict | None = None) -> list[FailureGroup]:
    """Groups of the failures by ``keys`` (one per failure, in ``shares`` order), the largest share first; each
    group's share is the exponentiated logsumexp of its members' log shares.

    Args:
        shares: the failures (:func:`failure_shares`).
        keys: [F] a hashable key per failure.
        labels: key -> words (default: ``str(key)``).
    Raises:
        ValueError: ``keys`` of another length than the failures."""
    if len(keys) != shares.n:
        raise ValueError(f"failure_groups: {len(keys)} keys for {shares.n} failures")
    if not len(keys):
        return []
    code_of = {k: i for i, k in enumerate(dict.fromkeys(keys))}  # each key's number, in the order of its first failure
    codes = np.fromiter(map(code_of.__getitem__, keys), dtype=np.intp, count=len(keys))
    by_code = np.split(np.argsort(codes, kind="stable"), np.cumsum(np.bincount(codes, minlength=len(code_of)))[:-1])
    groups = [
        FailureGroup(
            key,
            (labels or {}).get(key, str(key)),
            int(ranks.size),
            float(libm.exp(libm.logsumexp(shares.log_share[ranks]))),
            int(ranks[0]),
        )
        for key, ranks in zip(code_of, by_code, strict=True)
    ]
    return sorted(groups, key=lambda g: (-g.share, g.first))
