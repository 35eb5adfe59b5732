"""Pooling the stages of a run: the run's estimate over several stages' rollouts, each weighted by the proposal that
drew it (:func:`pool`, stage weights lambda_k: :func:`pool_stage_weights`, :func:`stage_weights_of`), and what is
pooled alike: the exceedance curve (:func:`severity_curve`), p under alternative PEMs (:func:`pem_spread`) and the
failures' shares (:func:`failure_population`). Re-exported by :mod:`pemviz.estimators.base`."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pemviz.core.estimate import Estimate, estimate
from pemviz.core.population import FailureShares, failure_shares, pooling_shifts
from pemviz.core.problems import Problem

if TYPE_CHECKING:
    from pemviz.core.reweight import PemSpread
    from pemviz.core.severity import SeverityCurve


def pool(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], stage_weights: np.ndarray | None = None) -> Estimate:
    """mu_hat = sum_k lambda_k mu_hat_k over K stages given as (log-weights, failed, log p before the failure),
    [n_k] each, computed as the mean over all N = sum n_k rollouts of 1[fail] w lambda_k N / n_k (nats, float64).

    Args:
        parts: the K stages' (log-weights float64 [n_k] in nats, failed bool [n_k], log p before the failure float64
            [n_k] in nats).
        stage_weights: lambda_k >= 0, [K], summing to 1; None: n_k / N (every rollout alike)."""
    own = np.concatenate([lw for lw, _, _ in parts])  # the lower bound bets on each rollout's own p/q (estimate)
    if stage_weights is not None:
        shift = pooling_shifts(stage_weights, np.array([lw.size for lw, _, _ in parts], dtype=np.float64))
        parts = [(lw + c, f, lp) for (lw, f, lp), c in zip(parts, shift, strict=False)]
    log_w, failed, log_p = (np.concatenate(a) for a in zip(*parts, strict=False))
    return estimate(log_w, failed, log_p, own)


def severity_curve(
    problem: Problem,
    estimator: object,
    final: Estimate,
    used: tuple[int, ...],
    pooling: tuple[str, tuple[float, ...]] | None,
    cap: tuple[str, str] | None = None,
) -> SeverityCurve | None:
    """The run's exceedance curve (:mod:`pemviz.core.severity`): ``final`` (the run's estimate) as its first point,
    then P(failure and min s < x) for each level x of ``problem.severity``, pooled over the stages ``used`` as the run's
    estimate is (``pooling``'s lambda_k, :func:`pool`; None: every rollout alike), each capped at ``cap`` (the sampler's
    best verdict, :meth:`pemviz.core.estimate.Estimate.at_most`).

    Returns:
        The curve, or None: no scale, or an estimator that keeps no per-stage rollouts (``stages``), e.g. AMS."""
    from pemviz.core.severity import SeverityCurve, SeverityPoint

    scale = problem.severity
    if scale is None:
        return None
    points = [SeverityPoint(scale.margin, final, problem.exact_log_p)]
    if not scale.levels:
        return SeverityCurve(scale, tuple(points))
    estimates = pooled_rows(estimator, used, pooling, "severity_arrays", cap)
    if estimates is None:
        return None
    for x, est in zip(scale.levels, estimates, strict=False):
        points.append(SeverityPoint(x, est, problem.severity_exact.get(x)))
    return SeverityCurve(scale, tuple(points))


def stage_weights_of(pooling: tuple[str, tuple[float, ...]] | None) -> np.ndarray | None:
    """lambda_k of a run's ``pooling`` (``FinalEstimate.pooling``) as :func:`pool` takes them; None for one stage or
    ``rollouts`` (every rollout alike)."""
    return None if pooling is None or pooling[0] == "rollouts" else np.asarray(pooling[1], dtype=np.float64)


def pooled_rows(
    estimator: object,
    used: tuple[int, ...],
    pooling: tuple[str, tuple[float, ...]] | None,
    arrays: str,
    cap: tuple[str, str] | None = None,
) -> list[Estimate] | None:
    """One estimate per row of the [R, N] arrays each used stage's :class:`~pemviz.estimators.base.StageRollouts`
    gives by its method ``arrays``, pooled over the stages ``used`` as the run's estimate is, each capped at
    ``cap``; None where the estimator keeps no such arrays."""
    stages = getattr(estimator, "stages", None)
    if not isinstance(stages, dict) or any(k not in stages for k in used):
        return None
    parts = [getattr(stages[k], arrays)() for k in used]
    if any(part is None for part in parts):
        return None
    lam = stage_weights_of(pooling)
    return [
        pool([(w[r], hit[r], lp[r]) for w, hit, lp in parts], lam).at_most(cap) for r in range(parts[0][0].shape[0])
    ]


def failure_population(
    estimator: object, used: tuple[int, ...], pooling: tuple[str, tuple[float, ...]] | None
) -> FailureShares | None:
    """The failures of the run's estimate with the share of mu_hat each carries (:mod:`pemviz.core.population`),
    pooled over the stages ``used`` as the estimate is (``pooling``'s lambda_k, :func:`pool`; None or ``rollouts``:
    every rollout alike); None where the estimator keeps no per-stage rollouts (``stages``), e.g. AMS."""
    stages = getattr(estimator, "stages", None)
    if not isinstance(stages, dict) or not used or any(k not in stages for k in used):
        return None
    return failure_shares([(k, *stages[k].arrays()) for k in used], stage_weights_of(pooling))


def pem_spread(
    problem: Problem,
    estimator: object,
    final: Estimate,
    used: tuple[int, ...],
    pooling: tuple[str, tuple[float, ...]] | None,
    cap: tuple[str, str] | None = None,
) -> PemSpread | None:
    """p under each of ``problem.alternatives`` from the run's own rollouts (:mod:`pemviz.core.reweight`), pooled as
    the run's estimate: the members of a PEM ensemble and the shifted PEMs; None without alternatives or where the
    estimator keeps no per-stage rollouts."""
    from pemviz.core.reweight import Alternative, PemSpread

    if not problem.alternatives:
        return None
    estimates = pooled_rows(estimator, used, pooling, "alternative_arrays", cap)
    if estimates is None:
        return None
    made = [Alternative(a.label, est, a.exact_log_p) for a, est in zip(problem.alternatives, estimates, strict=False)]
    members = tuple(m for m, a in zip(made, problem.alternatives, strict=False) if a.kind == "member")
    shifts = tuple(m for m, a in zip(made, problem.alternatives, strict=False) if a.kind == "shift")
    return PemSpread(final, members, shifts, problem.alternatives_source)


def pool_stage_weights(rule: str, sizes: list[int]) -> np.ndarray | None:
    """lambda_j of the j-th pooled stage (j = 1..K) of n_j rollouts under ``pool_weights`` ``rule``: ``quadratic``
    j^2 n_j / sum_i i^2 n_i, ``linear`` j n_j / sum_i i n_i, float64 [K]; None for ``rollouts`` (n_j / N, every rollout
    alike). Fixed by the stage sizes alone, before any pooled stage is drawn (Portier & Delyon, "Asymptotic optimality
    of adaptive importance sampling", NeurIPS 2018)."""
    if rule == "rollouts":
        return None
    power = 2 if rule == "quadratic" else 1
    lam = np.array([(j + 1) ** power * n for j, n in enumerate(sizes)], dtype=np.float64)
    return lam / lam.sum()
