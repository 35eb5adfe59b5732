"""The latched-brake braking scenario's exact answer: its failure probability in closed form
(:func:`latched_log_failure_probability`: the first effective detection decides everything, a finite sum of
deterministic replays); and :data:`LogitFn`, the detector curve every exact answer takes. Natural logs in float64."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import log_expit, logsumexp

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
