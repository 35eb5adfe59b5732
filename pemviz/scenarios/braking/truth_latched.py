"""The latched-brake braking scenario's exact answer: its failure probability in closed form
(:func:`latched_log_failure_probability`: the first effective detection decides everything, a finite sum of
deterministic replays) and its value function V (:func:`latched_value`); and :data:`LogitFn`, the detector curve
every exact answer takes. Natural logs in float64."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.special import log_expit, logsumexp

# the latched path: the batched simulator's observations bit for bit
from pemviz.scenarios.braking.batched import replay
from pemviz.scenarios.braking.simulator import BrakingParams, braking_replay

LogitFn = Callable[[np.ndarray], np.ndarray]
"""``logit p(detect | gap_m)``: gaps in metres, any shape -> float64 of the same shape (e.g. ``PEM.logit_at_gap``)."""


@dataclass(frozen=True)
class LatchedTruth:
    """Exact p_fail of the latched-brake scenario and where it comes from.

    Attributes:
        log_p_fail: log p_fail (nats).
        first_step, last_step: the window of steps whose detection (the first one) still avoids the
            crash: p_fail = prod over this window of (1 - p_PEM(d_t)) when the crash set is exactly
            "no detection in the window" (``window_exact``).
        window_exact: True if the sum over first-detection steps reduces to that single product.
        crash_step: first step with d < 2 when nothing is ever detected (None if never)."""

    log_p_fail: float
    first_step: int
    last_step: int
    window_exact: bool
    crash_step: int | None

    @property
    def p_fail(self) -> float:
        return math.exp(self.log_p_fail)


@dataclass(frozen=True)
class _LatchedPath:
    """The all-miss path of the latched scenario: gaps [T] (m), crash step c (None: never), the effective steps E
    (gap < braking distance, before c) and crash_after [len(E)]: whether a first detection at that step still
    ends in a crash (the rest is deterministic)."""

    gaps: np.ndarray
    crash_step: int | None
    effective: list[int]
    crash_after: np.ndarray


def _latched_path(p: BrakingParams) -> _LatchedPath:
    T = p.n_steps
    all_miss = braking_replay(p, np.zeros((1, T), bool))[0]
    crashed = np.flatnonzero(all_miss < p.crash_gap_m)
    c = int(crashed[0]) if crashed.size else None
    end = c if c is not None else T - 1  # the last action (step T - 1) affects nothing
    eff = [t for t in range(end) if all_miss[t] < p.braking_distance_m]
    det = np.zeros((len(eff), T), bool)
    for k, t in enumerate(eff):
        det[k, t] = True
    crash_after = np.asarray((braking_replay(p, det) < p.crash_gap_m).any(axis=1)) if eff else np.zeros(0, bool)
    return _LatchedPath(all_miss, c, eff, crash_after)


def latched_log_failure_probability(logit_at_gap: LogitFn, params: BrakingParams | None = None) -> LatchedTruth:
    """Exact p_fail of the latched-brake braking scenario.

    Before the first effective detection the ego follows the all-miss path; after it the brake never releases. With
    ``E`` the effective steps of the all-miss path before its crash step c,

        p_fail = sum_{t in E} [prod_{s in E, s < t} (1 - p_s)] p_t crash(t) + prod_{s in E} (1 - p_s) [c exists],

    crash(t) the deterministic outcome of a first detection at step t; in log-space.

    Args:
        logit_at_gap: logit p_PEM(detect | gap) (e.g. ``pem.logit_at_gap``).
        params: braking parameters; ``latched_brake`` is forced to True."""
    p = BrakingParams(latched_brake=True) if params is None else dataclasses.replace(params, latched_brake=True)
    path = _latched_path(p)
    all_miss, c, eff, crash_after = path.gaps, path.crash_step, path.effective, path.crash_after
    if not eff:
        return LatchedTruth(0.0 if c is not None else -math.inf, -1, -1, True, c)
    logit = np.asarray(logit_at_gap(all_miss[eff]), dtype=np.float64)
    log_miss = log_expit(-logit)
    log_hit = log_expit(logit)
    log_prefix = np.concatenate([[0.0], np.cumsum(log_miss)])  # P(miss at all effective steps before k)
    terms = [log_prefix[k] + log_hit[k] for k in range(len(eff)) if crash_after[k]]
    if c is not None:
        terms.append(log_prefix[-1])
    log_p = float(logsumexp(terms)) if terms else -math.inf
    # the window: effective steps whose first detection avoids the crash
    safe = [t for t, cr in zip(eff, crash_after, strict=False) if not cr]
    first, last = (safe[0], safe[-1]) if safe else (-1, -1)
    window_exact = (
        c is not None
        and bool(safe)
        and all((not cr) == (first <= t <= last) for t, cr in zip(eff, crash_after, strict=False))
        and first == eff[0]
    )
    return LatchedTruth(float(log_p), first, last, bool(window_exact), c)


# -- exact value functions: the zero-variance sampler ------------------------------------------------------------
#
# V(s) = P(failure | s) gives the zero-variance importance sampler q*(a | s) = p(a | s) V(s'_a) / V(s) (L'Ecuyer,
# Mandjes & Tuffin, "Importance sampling in rare event simulation", in Rare Event Simulation using Monte Carlo
# Methods, 2009, Sec. 2.3; :class:`pemviz.estimators.optimal.ZeroVarianceDetector`). Each class below gives, for the
# observations a detector is asked about, log V of the state after a detection and after a miss (nats).


@dataclass(frozen=True)
class LatchedValue:
    """V of the latched-brake scenario along its all-miss path: a detection at effective step t latches the brake, so V
    = crash(t) in {0, 1} after it, and on the path ``V_t = p_t crash(t) + (1 - p_t) V_{t+1}`` at effective steps,
    ``V_{t+1}`` elsewhere, 1 from the path's crash step on; ``V_0`` is :func:`latched_log_failure_probability`. A
    state is on the path when its observation is within ``tolerance`` of the all-miss rollout's
    (:func:`latched_value` checks that q* read from the observation stays zero-variance one step after a detection).

    Attributes:
        observations: the all-miss rollout's observations, float64 [T, F] (gap m, ego speed m/s, lead speed m/s).
        log_v_detect, log_v_miss: log V after a detection / a miss at step t of the all-miss path, [T] (nats).
        log_v0: log V at the start (= log p_fail).
        tolerance: the largest difference per column that still counts as the same state."""

    observations: np.ndarray = field(repr=False)
    log_v_detect: np.ndarray = field(repr=False)
    log_v_miss: np.ndarray = field(repr=False)
    log_v0: float
    tolerance: float = 1e-9

    def path_step(self, obs: np.ndarray) -> np.ndarray:
        """The all-miss step whose observation each row equals (within ``tolerance``), int [N] (-1: off the path)."""
        obs = np.asarray(obs, dtype=np.float64)
        same = np.all(np.abs(obs[:, None, :] - self.observations[None, :, :]) <= self.tolerance, axis=2)  # [N, T]
        return np.where(same.any(axis=1), np.argmax(same, axis=1), -1)

    def log_value_next(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(log V after a detection, log V after a miss), float64 [N] each, for observations [N, F]; equal (0, 0)
        off the all-miss path, where the action changes nothing."""
        k = self.path_step(obs)
        on = k >= 0
        kk = np.maximum(k, 0)
        return np.where(on, self.log_v_detect[kk], 0.0), np.where(on, self.log_v_miss[kk], 0.0)


def latched_value(logit_at_gap: LogitFn, params: BrakingParams | None = None) -> LatchedValue:
    """:class:`LatchedValue` of the latched-brake scenario with ``logit_at_gap`` as the detector.

    Raises:
        ValueError: if two steps of the all-miss path look the same but have different V, or if a state one step
            after a detection that q* can draw looks like an all-miss state where q* differs from p (then the
            observation does not carry enough state for q*)."""
    p = BrakingParams(latched_brake=True) if params is None else dataclasses.replace(params, latched_brake=True)
    T = p.n_steps
    path = _latched_path(p)
    c = path.crash_step
    logit = np.asarray(logit_at_gap(path.gaps), dtype=np.float64)
    log_v = np.zeros(T + 1)  # V before the action of step t; V = 1 from the crash step on
    end = c if c is not None else T - 1
    log_v[end:] = 0.0 if c is not None else -math.inf
    crash_after = dict(zip(path.effective, path.crash_after, strict=False))
    log_v_detect = np.empty(T)
    for t in range(T - 1, -1, -1):
        if t >= end or t not in crash_after:
            log_v_detect[t] = log_v[t + 1] if t < end else log_v[t]
            log_v[t] = log_v[t + 1] if t < end else log_v[t]
            continue
        log_v_detect[t] = 0.0 if crash_after[t] else -math.inf
        if log_v_detect[t] == log_v[t + 1]:  # both actions lead to the same V (exactly, not p + (1 - p) rounded)
            log_v[t] = log_v[t + 1]
        else:
            log_v[t] = np.logaddexp(log_expit(logit[t]) + log_v_detect[t], log_expit(-logit[t]) + log_v[t + 1])
    log_v_miss = np.where(np.arange(T) < end, log_v[1:], log_v[:T])
    value = LatchedValue(replay(p, np.zeros((1, T), bool))[0], log_v_detect, log_v_miss, float(log_v[0]))
    same_v = (log_v_detect == log_v_miss) | (np.isneginf(log_v_detect) & np.isneginf(log_v_miss))
    k = value.path_step(value.observations)
    if np.any((log_v_detect != log_v_detect[k]) | (log_v_miss != log_v_miss[k])):
        raise ValueError("latched_value: two states of the all-miss path look alike but have different V")
    if p.actuation_lag_steps == 1:
        reachable = [t for t in path.effective if crash_after[t] and logit[t] > -np.inf]  # q*(detect at t) > 0
        if any(t + 1 < T and not same_v[t + 1] for t in reachable):
            raise ValueError(
                "latched_value: a state one step after a detection looks like an all-miss state where "
                "q* differs from p: the observation does not show the pending brake q* needs"
            )
    return value
