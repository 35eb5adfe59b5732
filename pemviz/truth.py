"""Exact failure probabilities: closed forms and dynamic programming (spec section 6).

Three problems with a known answer judge the sampler:

1. the toy 1-D braking model: ``p_fail = prod_{d=safe}^{braking} (1 - p(d))`` in closed form
   (:func:`toy_log_failure_probability`);
2. the latched-brake braking scenario: the first effective detection decides everything, so p_fail is a
   finite sum over the step of the first detection, each term computed from the deterministic simulator
   (:func:`latched_log_failure_probability`);
3. the main (non-latched) braking scenario: backward dynamic programming over the scenario's state
   ``(gap, ego speed, PID integral, pending brake)`` on a grid with multilinear interpolation, refined
   until the answer moves by less than 2 % (:func:`braking_dp`, :func:`braking_dp_refine`), and checked
   by importance sampling with the DP's own zero-variance proposal (:func:`braking_dp_check`).

The braking dynamics here (:func:`braking_step`) are the scenario's (``ego_acceleration`` of
:mod:`pemviz.scenarios.braking` plus the explicit-Euler update of highway-env's ``Vehicle.step``), written
on the gap instead of positions; they replay highway-env rollouts to ~1e-12 m (tested).

All probabilities are returned as natural logs (nats) in float64. The DP adds and multiplies
non-negative numbers only (no cancellation), so it runs in linear space: its values stay far above
float64's smallest normal number (checked; an error is raised otherwise).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from pemviz.detectors import log_sigmoid
from pemviz.scenarios.braking import BrakingParams, ControllerState, ego_acceleration
from pemviz.scenarios.toy import ToyParams

LogitFn = Callable[[np.ndarray], np.ndarray]
"""``logit p(detect | gap_m)``: gaps in metres, any shape -> float64 of the same shape (e.g. ``PEM.logit_at_gap``)."""


# -- 1. toy ---------------------------------------------------------------------------------------------
def toy_log_failure_probability(params: ToyParams) -> float:
    """log p_fail of the toy model, exact: ``sum_{d=safe}^{braking} log(1 - p(d))`` (nats).

    The car fails iff every detection at the distances ``braking .. safe`` (each visited once while
    moving) misses. For constant p: ``(braking - safe + 1) log(1 - p)``; (100, 50, 30, 0.9) gives
    log(1e-21). Source: spec section 6 (authors' ``adaptiveImportanceSampler.py``).
    """
    d = np.arange(params.safe, params.braking + 1, dtype=np.float64)
    logit = params.detect_logit(d)
    return float(np.sum(log_sigmoid(-logit)))


# -- braking dynamics on the gap --------------------------------------------------------------------------
def lead_speeds(params: BrakingParams) -> np.ndarray:
    """Lead speed at steps 0..T (m/s), float64 [T + 1], accumulated exactly as highway-env does
    (``speed += acceleration * dt`` with the scenario's per-step lead acceleration)."""
    acc = params.lead_accel_mps2
    v = np.empty(params.n_steps + 1)
    v[0] = params.lead_speed_profile_mps[0]
    for t in range(params.n_steps):
        v[t + 1] = v[t] + acc[t] * params.dt_s
    return v


def braking_step(
    params: BrakingParams,
    lead_speed_mps: float,
    gap_m: np.ndarray,
    speed_mps: np.ndarray,
    integral: np.ndarray,
    pending: np.ndarray,
    detected: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One step of the braking scenario for many states at once.

    Args:
        lead_speed_mps: the lead's speed at this step (m/s).
        gap_m, speed_mps, integral, pending: state [...] at this step: gap (m), ego speed (m/s), PID
            integral (km/h s), emergency-brake command of the previous step (bool).
        detected: bool [...], the detector's output at this step.
    Returns:
        the state at the next step (same shapes): gap' = gap + (v_lead - v) dt; v' = max(v + a dt, 0).
    Source: :func:`pemviz.scenarios.braking.ego_acceleration` and highway-env ``Vehicle.step``.
    """
    shape = np.shape(gap_m)
    g = np.asarray(gap_m, dtype=np.float64).ravel()
    v = np.asarray(speed_mps, dtype=np.float64).ravel()
    ctrl = ControllerState(np.asarray(integral, dtype=np.float64).ravel(), np.asarray(pending, dtype=bool).ravel())
    a = np.broadcast_to(np.asarray(detected, dtype=bool), shape).ravel()
    accel, ctrl2 = ego_acceleration(params, a, g, v, ctrl)
    dt = params.dt_s
    g2 = g + (lead_speed_mps - v) * dt
    v2 = np.maximum(v + accel * dt, 0.0)
    return g2.reshape(shape), v2.reshape(shape), ctrl2.integral_kmh_s.reshape(shape), ctrl2.pending_brake.reshape(shape)


def braking_replay(params: BrakingParams, detected: np.ndarray) -> np.ndarray:
    """Gaps of rollouts with given detection sequences, float64 [N, T] (metres), deterministic.

    Args:
        detected: bool [N, T] (or [N, <T]: missing steps count as misses).
    """
    detected = np.atleast_2d(np.asarray(detected, dtype=bool))
    n, T = detected.shape[0], params.n_steps
    vl = lead_speeds(params)
    g = np.full(n, params.gap0_m)
    v = np.full(n, params.ego_speed0_mps)
    i = np.zeros(n)
    b = np.zeros(n, dtype=bool)
    out = np.empty((n, T))
    for t in range(T):
        out[:, t] = g
        a = detected[:, t] if t < detected.shape[1] else np.zeros(n, dtype=bool)
        g, v, i, b = braking_step(params, vl[t], g, v, i, b, a)
    return out


@dataclass(frozen=True)
class BrakingStart:
    """The scenario's state at the first step where a detection can matter (gap < braking distance).

    Every step before ``step`` has gap >= the braking distance, where both detector outputs lead to the
    same next state: the prefix is deterministic.
    """

    step: int
    gap_m: float
    speed_mps: float
    integral: float
    pending: bool


def branching_start(params: BrakingParams) -> BrakingStart:
    """Run the deterministic prefix until the gap first drops below the braking distance.

    Raises:
        ValueError: if that never happens within the episode (nothing random: p_fail is 0 or 1).
    """
    vl = lead_speeds(params)
    g, v, i, b = (np.array([params.gap0_m]), np.array([params.ego_speed0_mps]), np.zeros(1), np.zeros(1, bool))
    for t in range(params.n_steps):
        if g[0] < params.braking_distance_m:
            return BrakingStart(t, float(g[0]), float(v[0]), float(i[0]), bool(b[0]))
        g, v, i, b = braking_step(params, vl[t], g, v, i, b, np.zeros(1, bool))
    raise ValueError("branching_start: the gap never drops below the braking distance; p_fail is 0 or 1")


# -- 2. latched brake -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LatchedTruth:
    """Exact p_fail of the latched-brake scenario and where it comes from.

    Attributes:
        log_p_fail: log p_fail (nats).
        first_step, last_step: the window of steps whose detection (the first one) still avoids the
            crash: p_fail = prod over this window of (1 - p_PEM(d_t)) when the crash set is exactly
            "no detection in the window" (``window_exact``).
        window_exact: True if the sum over first-detection steps reduces to that single product.
        crash_step: first step with d < 2 when nothing is ever detected (None if never).
    """

    log_p_fail: float
    first_step: int
    last_step: int
    window_exact: bool
    crash_step: int | None

    @property
    def p_fail(self) -> float:
        return math.exp(self.log_p_fail)


def latched_log_failure_probability(logit_at_gap: LogitFn, params: BrakingParams | None = None) -> LatchedTruth:
    """Exact p_fail of the latched-brake braking scenario (spec section 6).

    Before the first effective detection (one at gap < braking distance) the ego follows the all-miss
    path; after it the brake never releases and the rest is deterministic. So, with ``E`` the effective
    steps of the all-miss path before its crash step c,

        p_fail = sum_{t in E} [prod_{s in E, s < t} (1 - p_s)] p_t crash(t) + prod_{s in E} (1 - p_s) [c exists]

    where crash(t) is the deterministic outcome of a first detection at step t; every term is evaluated in
    log-space.

    Args:
        logit_at_gap: logit p_PEM(detect | gap) (e.g. ``pem.logit_at_gap``).
        params: braking parameters; ``latched_brake`` is forced to True.
    """
    p = BrakingParams(latched_brake=True) if params is None else _replace(params, latched_brake=True)
    T = p.n_steps
    all_miss = braking_replay(p, np.zeros((1, T), bool))[0]
    crashed = np.flatnonzero(all_miss < p.crash_gap_m)
    c = int(crashed[0]) if crashed.size else None
    end = c if c is not None else T - 1  # the last action (step T - 1) affects nothing
    eff = [t for t in range(end) if all_miss[t] < p.braking_distance_m]
    if not eff:
        return LatchedTruth(0.0 if c is not None else -math.inf, -1, -1, True, c)
    det = np.zeros((len(eff), T), bool)
    for k, t in enumerate(eff):
        det[k, t] = True
    crash_after = (braking_replay(p, det) < p.crash_gap_m).any(axis=1)
    logit = np.asarray(logit_at_gap(all_miss[eff]), dtype=np.float64)
    log_miss = log_sigmoid(-logit)
    log_hit = log_sigmoid(logit)
    log_prefix = np.concatenate([[0.0], np.cumsum(log_miss)])  # P(miss at all effective steps before k)
    terms = [log_prefix[k] + log_hit[k] for k in range(len(eff)) if crash_after[k]]
    if c is not None:
        terms.append(log_prefix[-1])
    log_p = _logsumexp(np.array(terms)) if terms else -math.inf
    # the window: effective steps whose first detection avoids the crash
    safe = [t for t, cr in zip(eff, crash_after) if not cr]
    first, last = (safe[0], safe[-1]) if safe else (-1, -1)
    window_exact = c is not None and bool(safe) and all(
        (not cr) == (first <= t <= last) for t, cr in zip(eff, crash_after)
    ) and first == eff[0]
    return LatchedTruth(float(log_p), first, last, bool(window_exact), c)


# -- 3. main scenario: dynamic programming ------------------------------------------------------------------
@dataclass(frozen=True)
class Grid:
    """Grid of the DP over (gap, ego speed, PID integral); the pending-brake flag is exact (2 slices).

    Attributes:
        n_gap, n_speed, n_integral: points per axis (uniform spacing, >= 2 each).
    """

    n_gap: int
    n_speed: int
    n_integral: int

    def __post_init__(self) -> None:
        if min(self.n_gap, self.n_speed, self.n_integral) < 2:
            raise ValueError(f"Grid: every axis needs >= 2 points, got {self}")

    @property
    def n_nodes(self) -> int:
        return 2 * self.n_gap * self.n_speed * self.n_integral

    def __str__(self) -> str:
        return f"{self.n_gap}x{self.n_speed}x{self.n_integral}x2"


DEFAULT_REFINEMENT: tuple[Grid, ...] = (
    Grid(101, 101, 4),
    Grid(201, 201, 6),
    Grid(401, 401, 8),
    Grid(801, 801, 12),
)
"""The grids of :func:`braking_dp_refine`, coarse to fine."""


@dataclass(frozen=True)
class DPResult:
    """The DP's answer on one grid.

    Attributes:
        log_p_fail: log p_fail at the scenario's start (nats).
        grid: the grid used; ``axes`` its (gap, speed, integral) coordinates.
        start: the branching start state (where the DP is evaluated).
        wall_s: seconds it took.
        values: V at the start step on the grid [2, G, S, I] (kept for the zero-variance check when
            ``keep_values``), else None.
    """

    log_p_fail: float
    grid: Grid
    axes: tuple[np.ndarray, np.ndarray, np.ndarray]
    start: BrakingStart
    wall_s: float
    values: tuple[np.ndarray, ...] | None = field(default=None, repr=False)

    @property
    def p_fail(self) -> float:
        return math.exp(self.log_p_fail)


def _replace(params: BrakingParams, **changes) -> BrakingParams:
    import dataclasses

    return dataclasses.replace(params, **changes)


def _logsumexp(x: np.ndarray) -> float:
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0:
        return -math.inf
    m = float(np.max(x))
    if m == -math.inf:
        return -math.inf
    return m + math.log(float(np.sum(np.exp(x - m))))


def _axes(params: BrakingParams, start: BrakingStart, grid: Grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axis coordinates covering every state reachable after ``start`` (gap, speed, integral)."""
    vl = lead_speeds(params)
    dt = params.dt_s
    gap_hi = start.gap_m + dt * float(np.sum(vl[start.step :]))  # the ego never reverses
    speed_hi = max(start.speed_mps, params.target_speed_kmh / 3.6) + 0.5
    if not 0.0 <= params.integral_leak < 1.0:
        raise ValueError(f"braking_dp: needs a leaky PID integral (0 <= integral_leak < 1), got {params.integral_leak}")
    k = dt / (1.0 - params.integral_leak)
    i_lo = min(start.integral, (params.target_speed_kmh - 3.6 * speed_hi) * k)
    i_hi = max(start.integral, params.target_speed_kmh * k)
    return (
        np.linspace(params.crash_gap_m, gap_hi, grid.n_gap),
        np.linspace(0.0, speed_hi, grid.n_speed),
        np.linspace(i_lo, i_hi, grid.n_integral),
    )


class _Interpolator:
    """Multilinear interpolation of V [2, G, S, I] at points (pending, gap, speed, integral); clamps to the box."""

    def __init__(self, axes: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        self.lo = np.array([a[0] for a in axes])
        self.step = np.array([a[1] - a[0] for a in axes])
        self.n = np.array([a.size for a in axes])
        self.strides = np.array([self.n[1] * self.n[2], self.n[2], 1])
        self.slice_size = int(np.prod(self.n))

    def __call__(self, values_flat: np.ndarray, pending: np.ndarray, coords: Sequence[np.ndarray]) -> np.ndarray:
        base = pending.astype(np.int64) * self.slice_size
        weights = []
        for k, x in enumerate(coords):
            u = (x - self.lo[k]) / self.step[k]
            i0 = np.clip(np.floor(u), 0, self.n[k] - 2).astype(np.int64)
            f = np.clip(u - i0, 0.0, 1.0)
            base = base + i0 * self.strides[k]
            weights.append(f)
        out = np.zeros(base.shape)
        for corner in range(8):
            idx = base.copy()
            w = np.ones(base.shape)
            for k in range(3):
                if corner >> k & 1:
                    idx += self.strides[k]
                    w *= weights[k]
                else:
                    w *= 1.0 - weights[k]
            out += w * values_flat[idx]
        return out


def braking_dp(
    logit_at_gap: LogitFn,
    params: BrakingParams | None = None,
    grid: Grid = Grid(401, 401, 8),
    *,
    keep_values: bool = False,
    chunk: int = 1 << 20,
) -> DPResult:
    """p_fail of the braking scenario by backward dynamic programming over its state (spec section 6).

    V_t(s) = P(some step t' >= t has gap < 2 | state s at step t), with V_{T-1}(s) = 1[gap < 2] and

        V_t(s) = p(d) V_{t+1}(f(s, detect)) + (1 - p(d)) V_{t+1}(f(s, miss)),   V = 1 once gap < 2,

    where f is :func:`braking_step` and p(d) = sigmoid(logit_at_gap(d)). V is stored on ``grid`` (gap from
    2 m to the largest reachable gap, speed 0 .. max speed + 0.5 m/s, integral over its reachable range;
    the pending flag exactly) and read between nodes by multilinear interpolation; next states with gap
    < 2 are exact failures (V = 1), not interpolated. The DP starts at the first step where the gap is
    below the braking distance (:func:`branching_start`); the prefix before it is deterministic. Works
    for ``latched_brake`` too (then it can be checked against :func:`latched_log_failure_probability`).

    Cost: 2 x nodes x (T - start) interpolations; 401x401x8 takes ~1 min on one core.

    Args:
        logit_at_gap: logit p_PEM(detect | gap).
        params: the scenario (default :class:`BrakingParams`).
        grid: points per axis.
        keep_values: keep V for every step (for :func:`braking_dp_check`; memory 16 x nodes x steps bytes).
        chunk: nodes per vectorised block (memory bound).
    Returns:
        :class:`DPResult`.
    Raises:
        ValueError: on a non-leaky integral, or if V underflows float64's normal range.
    """
    t_start = time.perf_counter()
    p = params or BrakingParams()
    start = branching_start(p)
    axes = _axes(p, start, grid)
    interp = _Interpolator(axes)
    vl = lead_speeds(p)
    G, S, I = (a.size for a in axes)
    gg, ss, ii = np.meshgrid(*axes, indexing="ij")
    gg, ss, ii = gg.ravel(), ss.ravel(), ii.ravel()
    logit = np.asarray(logit_at_gap(axes[0]), dtype=np.float64)
    p_hit = np.exp(log_sigmoid(logit))[np.repeat(np.arange(G), S * I)]
    n_slice = G * S * I
    V = np.zeros(2 * n_slice)  # V_{T-1} on the grid: every node has gap >= 2
    kept: list[np.ndarray] = []
    for t in range(p.n_steps - 2, start.step - 1, -1):
        V_new = np.empty_like(V)
        for b in (0, 1):
            pend = np.full(min(chunk, n_slice), bool(b))
            for lo in range(0, n_slice, chunk):
                hi = min(lo + chunk, n_slice)
                sl = slice(lo, hi)
                val = []
                for a in (False, True):
                    g2, v2, i2, b2 = braking_step(p, vl[t], gg[sl], ss[sl], ii[sl], pend[: hi - lo], np.array(a))
                    inside = interp(V, b2, (g2, v2, i2))
                    val.append(np.where(g2 < p.crash_gap_m, 1.0, inside))
                V_new[b * n_slice + lo : b * n_slice + hi] = p_hit[sl] * val[1] + (1.0 - p_hit[sl]) * val[0]
        V = V_new
        if keep_values:
            kept.append(V.reshape(2, G, S, I).copy())
    positive = V[V > 0]
    if positive.size and positive.min() < 1e-290:
        raise ValueError("braking_dp: value function underflows float64; the problem needs a log-space DP")
    v_start = interp(V, np.array([start.pending]), (np.array([start.gap_m]), np.array([start.speed_mps]),
                                                     np.array([start.integral])))[0]  # fmt: skip
    log_p = math.log(v_start) if v_start > 0 else -math.inf
    values = tuple(reversed(kept)) if keep_values else None
    return DPResult(log_p, grid, axes, start, time.perf_counter() - t_start, values)


@dataclass(frozen=True)
class Refinement:
    """The DP on successively finer grids.

    Attributes:
        results: one :class:`DPResult` per grid, coarse to fine.
        rel_changes: |p_k - p_{k-1}| / p_k for k >= 1 (nan for the first).
        tolerance: the target relative change.
    """

    results: tuple[DPResult, ...]
    rel_changes: tuple[float, ...]
    tolerance: float

    @property
    def converged(self) -> bool:
        return len(self.rel_changes) > 1 and self.rel_changes[-1] < self.tolerance

    @property
    def final(self) -> DPResult:
        return self.results[-1]

    def table(self) -> str:
        """The refinement table as Markdown."""
        from pemviz.sampling import format_probability

        rows = ["| grid (gap x speed x integral x pending) | nodes | p_fail | rel. change | wall s |",
                "|---|---:|---:|---:|---:|"]  # fmt: skip
        for r, ch in zip(self.results, self.rel_changes):
            change = "-" if math.isnan(ch) else f"{ch:.2%}"
            rows.append(
                f"| {r.grid} | {r.grid.n_nodes:,} | {format_probability(r.log_p_fail, 4)} | {change} | {r.wall_s:.1f} |"
            )
        return "\n".join(rows)


def braking_dp_refine(
    logit_at_gap: LogitFn,
    params: BrakingParams | None = None,
    grids: Sequence[Grid] = DEFAULT_REFINEMENT,
    *,
    tolerance: float = 0.02,
    stop_when_converged: bool = False,
    on_result: Callable[[DPResult], None] | None = None,
) -> Refinement:
    """Run :func:`braking_dp` on each grid (coarse to fine) and report the relative changes.

    Args:
        tolerance: convergence target for the last relative change (spec: 2 %).
        stop_when_converged: stop at the first grid whose change is below ``tolerance``.
        on_result: called with each grid's result as soon as it is ready (progress output).
    """
    results: list[DPResult] = []
    changes: list[float] = []
    for g in grids:
        r = braking_dp(logit_at_gap, params, g)
        if results:
            prev = results[-1].p_fail
            changes.append(abs(r.p_fail - prev) / r.p_fail if r.p_fail > 0 else math.inf)
        else:
            changes.append(math.nan)
        results.append(r)
        if on_result is not None:
            on_result(r)
        if stop_when_converged and len(changes) > 1 and changes[-1] < tolerance:
            break
    return Refinement(tuple(results), tuple(changes), tolerance)
