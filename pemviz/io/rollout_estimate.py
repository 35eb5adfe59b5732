"""Failure-probability estimates from logged rollouts (``pemviz estimate``): log p and log q from the file's columns or
recomputed, and mu_hat formed as the engine does (:func:`estimate_rollouts`; Innes & Ramamoorthy 2022, eq. 6)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, cast

import numpy as np

from pemviz.core.detectors import ConstantDetector, Detector, PEMDetector, WindowDetector, action_log_prob
from pemviz.core.estimate import Estimate, estimate
from pemviz.core.problems import LookAheadFn, Problem
from pemviz.core.rollouts import RolloutBatch
from pemviz.core.weights import CONVENTIONS, MeanWeight, mean_weight
from pemviz.estimators.base import SeenFailures, log_p_before_failure, log_weight, look_ahead_weights
from pemviz.estimators.pooling import pool
from pemviz.io.rollout_format import (
    SALIENT_COLUMNS,
    SAMPLERS,
    RolloutFormatError,
    RolloutMeta,
    json_float,
    parse_formula,
)
from pemviz.io.rollout_table import RolloutData, braking_salient
from pemviz.methods import MIXED_METHOD, NAIVE_METHOD
from pemviz.settings import METRICS

REESTIMATE_RTOL = 1e-9
"""A rollout file re-estimates to its run's mu_hat within this relative error, and prints the run's rows and verdict:
the file's weights are summed in another grouping than the run's, so their float64 sums agree to the last bits only
(seen: 1.5e-11 at 2,100 rollouts, 1.5e-10 at 10^5 rollouts streamed in chunks)."""


def _one_object(data: RolloutData) -> None:
    """Refuse to recompute log-probabilities of a file of several objects or with errors (its rows are not in it)."""
    if data.n_objects > 1 or data.noise is not None:
        raise ValueError(
            f"{data.path or 'rollouts'}: {data.n_objects} object(s) a step with errors "
            f"{list(data.noise_names)}: log p and log q are the file's own columns, not recomputed"
        )


def detector_log_prob(data: RolloutData, detector: Detector) -> np.ndarray:
    """``log p(a_t | s_t)`` of the logged actions under a detector, float64 [N, T] (nats), asked one step of all N
    rollouts at a time, as :func:`pemviz.core.lockstep.simulate` asks.

    Raises:
        ValueError: a file of several objects or with measurement errors (their rows are not in it)."""
    _one_object(data)
    out = np.empty((data.n, data.n_steps))
    for t in range(data.n_steps):
        out[:, t] = action_log_prob(detector.detect_logit(data.observations[:, t]), data.detected[:, t, 0])
    return out


def pem_log_prob(data: RolloutData, pem: Any) -> np.ndarray:
    """``log p_PEM(a_t | s_t)`` of the logged actions, float64 [N, T] (nats), from the file's salient-variable
    columns (:meth:`pemviz.pem.PEM.logit`), or from the gap (:meth:`pemviz.pem.PEM.logit_at_gap`) when it has none
    or they are exactly the braking gap's mapping.

    Raises:
        ValueError: a file of several objects or with measurement errors (their rows are not in it)."""
    _one_object(data)
    gap = data.signal("gap_m")
    if data.salient is None or np.array_equal(data.salient, braking_salient(gap)):
        return detector_log_prob(data, PEMDetector(pem))
    logit = pem.logit(data.salient.reshape(-1, len(SALIENT_COLUMNS))).reshape(data.n, data.n_steps)
    return action_log_prob(logit, data.detected[..., 0])


def sampler_detector(name: str, pem: Any, window_m: float = 10.0) -> Detector:
    """The detector a named baseline sampled with: ``pem``, ``naive50`` (50 % everywhere), ``mixed50``
    (50 % inside ``window_m``, the PEM outside; the baselines of Innes & Ramamoorthy 2022).

    Raises:
        ValueError: an unknown name."""
    target = PEMDetector(pem)
    if name == "pem":
        return target
    if name == NAIVE_METHOD:
        return ConstantDetector(0.5)
    if name == MIXED_METHOD:
        return WindowDetector(ConstantDetector(0.5), target, window_m)
    raise ValueError(f"unknown sampler {name!r}; use a proposal checkpoint or one of {', '.join(SAMPLERS)}")


@dataclass(frozen=True)
class StageRow:
    """One stage's estimate from a file's rollouts of that stage (``stage`` None: the file has no stage column)."""

    stage: int | None
    kind: str
    estimate: Estimate


@dataclass(frozen=True)
class RolloutEstimate:
    """The failure-probability estimate from logged rollouts.

    Attributes:
        estimate: mu_hat, failures, NLL, ESS, interval, k-hat, verdict (:class:`pemviz.core.estimate.Estimate`): pooled
            over :attr:`pooled` with the sidecar's stage weights, or over every rollout alike.
        robustness: float64 [N] under ``metric``.
        failed: bool [N].
        log_weight: float64 [N] importance log-weights under :attr:`weights` (nats), before any stage weight.
        metric: the robustness semantics.
        failure: ``crash`` (classic robustness < 0) or ``metric`` (robustness under ``metric`` < 0).
        weights: the convention used, one of :data:`pemviz.core.weights.CONVENTIONS`.
        stages: one row per stage in the file (one row with stage None without a stage column).
        pooled: the stages the estimate pools with the sidecar's rule (empty: every rollout alike).
        rule: the sidecar's pooling rule (``every rollout alike`` without one).
        check: the mean importance weight over all N rollouts (:func:`pemviz.core.weights.mean_weight`)."""

    estimate: Estimate
    robustness: np.ndarray
    failed: np.ndarray
    log_weight: np.ndarray
    metric: str
    failure: str
    weights: str = "to-failure"
    stages: tuple[StageRow, ...] = ()
    pooled: tuple[int, ...] = ()
    rule: str = "every rollout alike"
    check: MeanWeight | None = None


def _no_simulator(n: int, sampler: Detector, target: Detector, rng: np.random.Generator) -> RolloutBatch:
    raise ValueError("a rollout file's problem has no simulator: its rollouts are given")


def file_problem(meta: RolloutMeta, name: str = "rollout file") -> Problem:
    """The :class:`~pemviz.core.problems.Problem` a rollout file poses: the sidecar's formula, signals and signal
    ranges, with the engine's robustness and failure, and no simulator or target.

    Raises:
        RolloutFormatError: the sidecar's formula is not valid STL."""
    formula = parse_formula(meta.formula, lambda why: RolloutFormatError(f"{name}: {why}"))
    return Problem(
        name,
        _no_simulator,
        cast(Detector, None),  # no target detector: the logged log-probabilities stand for it
        formula,
        signals=dict(meta.signals),  # type: ignore[arg-type]
        signal_ranges=dict(meta.signal_ranges),
    )


def estimate_rollouts(
    data: RolloutData,
    log_p: np.ndarray,
    log_q: np.ndarray,
    *,
    metric: str = "classic",
    failure: str = "crash",
    weights: str = "to-failure",
    log_p_seen: float | str | None = None,
    verdict_cap: tuple[str, str] | None = None,
    look_ahead: LookAheadFn | None = None,
) -> RolloutEstimate:
    """mu_hat from logged rollouts (Innes & Ramamoorthy 2022, eq. 6), per stage and pooled as the sidecar says, through
    the engine's code: ``log w_i = sum_{t < k_i} log p - log q`` with k_i = T - 1 (``"full"``) or the failure step
    (``"to-failure"``; :mod:`pemviz.core.weights`).
    Args:
        data: the rollout file read (:func:`pemviz.io.rollouts.read_rollouts`).
        log_p: float64 [N, T] each action's log-probability under the PEM (nats).
        log_q: float64 [N, T] each action's log-probability under the sampler (nats).
        metric: the robustness semantics that ranks the rollouts (:data:`pemviz.settings.METRICS`).
        failure: ``crash`` (classic robustness < 0) or ``metric`` (robustness under ``metric`` < 0).
        weights: one of :data:`pemviz.core.weights.CONVENTIONS`; ``to-failure`` falls back to ``full`` for a formula
            not ``G[a,b](state predicate)`` or with ``failure="metric"``.
        log_p_seen: the probability of the failures the run drew (nats, the sidecar's; ``"-inf"`` read as that
            number), with the file's own failures the bound below which the verdict is unreliable
            (:meth:`pemviz.core.estimate.Estimate.below_seen`).
        verdict_cap: the best verdict the run's sampler let it claim (the sidecar's;
            :meth:`pemviz.core.estimate.Estimate.at_most`).
        look_ahead: the run's problem's look-ahead, weighed as the run weighed it
            (:func:`pemviz.estimators.base.look_ahead_weights`).
    Raises:
        ValueError: an unknown metric, failure mode or convention, arrays of the wrong shape, or a formula the
            file's signals cannot evaluate (a RolloutFormatError naming the file)."""
    _check_choices(metric, failure, weights)
    shape = (data.n, data.n_steps)
    log_p_seen = json_float(log_p_seen)  # a sidecar writes -inf as text
    log_p, log_q = np.asarray(log_p, np.float64), np.asarray(log_q, np.float64)
    if log_p.shape != shape or log_q.shape != shape:
        raise ValueError(f"log_p and log_q must have shape {shape}, got {log_p.shape}, {log_q.shape}")
    where = str(data.path or "rollouts")
    assert data.meta is not None  # a rollout file's data has its sidecar
    problem = file_problem(data.meta, where)
    batch = data.to_batch(log_p, log_q)
    try:
        rho = {m: problem.robustness(batch, m) for m in {"classic", metric}}
    except ValueError as exc:
        raise RolloutFormatError(f"{where}: formula {data.meta.formula!r}: {exc}") from None
    failed = problem.failed(batch, rho["classic"]) if failure == "crash" else rho[metric] < 0.0
    if failure != "crash":
        weights = "full"
    with np.errstate(over="ignore", invalid="ignore"):  # the same weights and NLL steps as the engine's
        try:
            log_w = log_weight(problem, batch, until_failure=weights == "to-failure")
        except ValueError:  # not G[a,b](state predicate): the first T - 1 steps
            log_w, weights = batch.log_weight(), "full"
        log_p_total = log_p_before_failure(problem, batch)
    _check_finite(data, where, log_w, log_p_total, log_p, log_q)
    checked = log_w  # the weights whose mean should be 1
    if look_ahead is not None and failure == "crash":
        weighed = look_ahead_weights(replace(problem, look_ahead=look_ahead), batch)
        assert weighed is not None  # the problem has a look-ahead
        log_w, failed, checked = weighed
    est, rows, pooled, rule = _pooled(data, log_w, failed, log_p_total)
    if failure == "crash" and not data.meta.odd_parameters:  # the failures the run drew (no bound over an ODD)
        seen = SeenFailures()
        seen.add(problem, batch, failed)
        est = est.below_seen(max((b for b in (seen.log_p, log_p_seen) if b is not None), default=None))
    est = est.at_most(verdict_cap)
    return RolloutEstimate(
        est,
        rho[metric],
        failed,
        log_w,
        metric,
        failure,
        weights,
        rows,
        pooled,
        rule,
        _mean_weight(checked, _stage_bounds(data)),
    )


def _check_choices(metric: str, failure: str, weights: str) -> None:
    """:func:`estimate_rollouts`' metric, failure event and weight convention, each one of those known.

    Raises:
        ValueError: an unknown one."""
    if metric not in METRICS:
        raise ValueError(f"unknown metric {metric!r}; use one of {', '.join(METRICS)}")
    if failure not in ("crash", "metric"):
        raise ValueError(f"unknown failure event {failure!r}; use crash or metric")
    if weights not in CONVENTIONS:
        raise ValueError(f"unknown weight convention {weights!r}; use one of {', '.join(CONVENTIONS)}")


def _check_finite(
    data: RolloutData, where: str, log_w: np.ndarray, log_p_total: np.ndarray, log_p: np.ndarray, log_q: np.ndarray
) -> None:
    """Every rollout's log-weight and log p sum finite or -inf (an action the PEM cannot take: weight 0, as in the
    run).

    Raises:
        RolloutFormatError: one beyond float64, naming the rollout."""
    k = data.n_steps - 1
    for name, x in (("importance log-weight sum(log_p - log_q)", log_w), ("sum of log_p", log_p_total)):
        bad = np.isnan(x) | (x == np.inf)  # -inf: an action the PEM cannot take, weight 0 (as in the run)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            assert data.rollout_ids is not None  # a rollout file's data has its ids
            raise RolloutFormatError(
                f"{where}: rollout {data.rollout_ids[i]}: the {name} over its {k} steps is beyond "
                f"float64 (+-1.8e308 nats; log_p down to {log_p[i, :k].min():.3g}, log_q down to "
                f"{log_q[i, :k].min():.3g}): no estimate can be formed from these log-probabilities"
            )


def _stage_bounds(data: RolloutData) -> np.ndarray | None:
    """Each rollout's stage's largest possible weight (the sidecar's ``max_weight``; NaN: not known), or None
    without stages."""
    if data.stage is None or data.meta is None or not data.meta.stages:
        return None
    b = {s["stage"]: s["max_weight"] for s in data.meta.stages}
    return np.array([math.nan if b.get(int(k)) is None else b[int(k)] for k in data.stage])


def _mean_weight(log_w: np.ndarray, bound: np.ndarray | None) -> MeanWeight:
    """:func:`pemviz.core.weights.mean_weight` of log-weights [N] (nats), where every weight may be 0 (log w = -inf:
    each rollout took an action the PEM cannot take): then the mean is 0 with standard error 0."""
    if np.max(log_w) > -np.inf:
        return mean_weight(log_w, bound)
    return replace(mean_weight(np.zeros_like(log_w), bound), log_mean=-math.inf, se=0.0)


def _pooled(
    data: RolloutData, log_w: np.ndarray, failed: np.ndarray, log_p: np.ndarray
) -> tuple[Estimate, tuple[StageRow, ...], tuple[int, ...], str]:
    """(the estimate, the per-stage rows, the pooled stages, the rule) of :func:`estimate_rollouts`."""
    if data.stage is None:
        whole = estimate(log_w, failed, log_p)
        stage = (data.meta.provenance or {}).get("stage") if data.meta else None
        kind = str((data.meta.provenance or {}).get("kind", "")) if data.meta else ""
        return whole, (StageRow(stage if isinstance(stage, int) else None, kind, whole),), (), "every rollout alike"
    assert data.meta is not None  # a stage column comes with its sidecar
    rows = []
    for k in np.unique(data.stage).tolist():
        m = data.stage == k
        info = data.meta.stage_info(k) or {}
        rows.append(StageRow(k, str(info.get("kind", "")), estimate(log_w[m], failed[m], log_p[m])))
    pooling = data.meta.pooling
    if pooling is None:
        return estimate(log_w, failed, log_p), tuple(rows), (), "every rollout alike"
    parts = [(log_w[data.stage == k], failed[data.stage == k], log_p[data.stage == k]) for k in pooling["stages"]]
    if len(parts) == 1:
        est = estimate(*parts[0])
    else:  # the run's arithmetic: no stage weights for "rollouts", its lambda_k otherwise
        est = pool(parts, None if pooling["rule"] == "rollouts" else np.asarray(pooling["stage_weights"]))
    return est, tuple(rows), tuple(pooling["stages"]), pooling["rule"] or "given"
