"""Exact failure probabilities: closed forms and exact enumeration.

Three problems with a known answer judge the sampler:

1. the toy 1-D braking model: ``p_fail = prod_{d=safe}^{braking} (1 - p(d))`` in closed form
   (:func:`pemviz.scenarios.toy.toy_log_failure_probability`, beside the toy);
2. the latched-brake braking scenario: the first effective detection decides everything, so p_fail is a
   finite sum over the step of the first detection, each term from the deterministic simulator
   (:func:`latched_log_failure_probability`);
3. the main (non-latched) braking scenario: the only randomness is the detector and the dynamics are
   deterministic, so p_fail is a sum over detection sequences. :func:`braking_exact` follows every
   sequence exactly from the first step inside the braking distance (no grid, no merging) and drops a
   sequence only when a rigorous bound on all it could still contribute is below a threshold; the bound is
   a dynamic program on a (gap, speed) grid of the least number of misses that can still lead to a crash
   (:func:`miss_bound`). The result is a bracket [enumerated, enumerated + dropped bound], refined by
   lowering the threshold until it is narrower than the tolerance (:func:`braking_truth`).

Why not a grid DP of the value function with interpolation: V is a sum of step functions of the state and
interpolation smears its jumps; on the latched problem it stays 45 % off on a 401 x 401 grid while moving
by 50 % from 201 x 201 (``benchmarks/truth_braking.py`` prints both tables).

The braking dynamics are the scenario's own, written on the gap instead of positions
(:func:`pemviz.scenarios.braking.braking_step`). Probabilities are natural logs (nats) in float64 and sums are
log-sum-exps.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np
from scipy.special import expit, log_expit, logsumexp

from pemviz.core.estimate import format_probability
from pemviz.scenarios.batched import replay  # the latched path: the batched simulator's observations bit for bit
from pemviz.scenarios.braking import BrakingParams, braking_replay, braking_step, lead_speeds

LogitFn = Callable[[np.ndarray], np.ndarray]
"""``logit p(detect | gap_m)``: gaps in metres, any shape -> float64 of the same shape (e.g. ``PEM.logit_at_gap``)."""


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
    crash_after = (braking_replay(p, det) < p.crash_gap_m).any(axis=1) if eff else np.zeros(0, bool)
    return _LatchedPath(all_miss, c, eff, crash_after)


def latched_log_failure_probability(logit_at_gap: LogitFn, params: BrakingParams | None = None) -> LatchedTruth:
    """Exact p_fail of the latched-brake braking scenario.

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
    safe = [t for t, cr in zip(eff, crash_after) if not cr]
    first, last = (safe[0], safe[-1]) if safe else (-1, -1)
    window_exact = c is not None and bool(safe) and all(
        (not cr) == (first <= t <= last) for t, cr in zip(eff, crash_after)
    ) and first == eff[0]
    return LatchedTruth(float(log_p), first, last, bool(window_exact), c)


# -- exact value functions: the zero-variance sampler ------------------------------------------------------------
#
# V(s) = P(failure | s) gives the zero-variance importance sampler q*(a | s) = p(a | s) V(s'_a) / V(s) (L'Ecuyer,
# Mandjes & Tuffin, "Importance sampling in rare event simulation", in Rare Event Simulation using Monte Carlo
# Methods, 2009, Sec. 2.3; :class:`pemviz.estimators.optimal.ZeroVarianceDetector`). Each class below gives, for the
# observations a detector is asked about, log V of the state after a detection and after a miss (nats).


@dataclass(frozen=True)
class LatchedValue:
    """V of the latched-brake scenario along its all-miss path.

    Before the first effective detection the ego follows the all-miss path; a detection at effective step t
    latches the brake, after which everything is deterministic: V = crash(t) in {0, 1} from then on, so the action
    matters only on the all-miss path. There ``V_t = p_t crash(t) + (1 - p_t) V_{t+1}`` at effective steps and
    ``V_t = V_{t+1}`` elsewhere, with ``V = 1`` from the crash step of the all-miss path on (0 at the last step
    when it never crashes); ``V_0`` is :func:`latched_log_failure_probability`.

    A state is recognised as on the all-miss path by its observation: within ``tolerance`` of the all-miss
    rollout's observation at some step (every column; the batched simulator replays it bit for bit). Off the
    path both actions give the same V. One step after a detection the observation is still the all-miss one
    (the brake acts one step late, and the observation does not show a pending brake); :func:`latched_value`
    checks that q* = p there wherever a rollout can reach such a state, so that q* read from the observation is
    still the zero-variance sampler.

    Attributes:
        observations: the all-miss rollout's observations, float64 [T, F] (gap m, ego speed m/s, lead speed m/s).
        log_v_detect, log_v_miss: log V after a detection / a miss at step t of the all-miss path, [T] (nats).
        log_v0: log V at the start (= log p_fail).
        tolerance: the largest difference per column that still counts as the same state.
    """

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
            observation does not carry enough state for q*).
    """
    p = BrakingParams(latched_brake=True) if params is None else dataclasses.replace(params, latched_brake=True)
    T = p.n_steps
    path = _latched_path(p)
    c = path.crash_step
    logit = np.asarray(logit_at_gap(path.gaps), dtype=np.float64)
    log_v = np.zeros(T + 1)  # V before the action of step t; V = 1 from the crash step on
    end = c if c is not None else T - 1
    log_v[end:] = 0.0 if c is not None else -math.inf
    crash_after = dict(zip(path.effective, path.crash_after))
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
            raise ValueError("latched_value: a state one step after a detection looks like an all-miss state where "
                             "q* differs from p: the observation does not show the pending brake q* needs")  # fmt: skip
    return value


# -- 3. main scenario: exact enumeration with a rigorous bound ---------------------------------------------------
#
# A grid DP with interpolation smears V, a sum of step functions of the state, across its jumps: on the
# latched variant (exact answer known) it was 40 % off on an 801 x 801 grid while moving by only 9 % from
# 401 x 401 (benchmarks/truth_braking.py). Here instead every detection sequence is followed exactly (no
# grid, no merging), and a sequence is dropped only when an upper bound on everything it can still contribute
# is negligible. The bound comes from a DP over a (gap, speed) grid of the least number of misses that can
# still lead to a crash, which rounds states in the safe direction and so stays a valid lower bound.


def _relaxed_step(params: BrakingParams, lead_speed_mps: float, gap_m, speed_mps, pending, detected):
    """:func:`braking_step` of a controller that is never gentler: the PID integral at its largest
    reachable value (the most throttle) and no PID brake (which, above 7.5 m/s, makes the true next speed
    fall as the speed rises). Its next speed is at least the true one from the same gap and speed, whatever
    the integral, and it is monotone: next gap non-increasing and next speed non-decreasing in the speed
    (checked in tests/test_truth.py). So a state that is no safer (gap no larger, speed no smaller) stays
    no safer under the same action, which is what :class:`MissBound` rests on.
    """
    relaxed = dataclasses.replace(params, max_pid_brake=0.0)
    i_max = np.full(np.shape(gap_m), params.target_speed_kmh * params.dt_s / (1.0 - params.integral_leak))
    g2, v2, _, b2 = braking_step(relaxed, lead_speed_mps, gap_m, speed_mps, i_max, pending, detected)
    return g2, v2, b2


@dataclass(frozen=True)
class MissBound:
    """A lower bound on the number of misses (detections at gap < braking distance that fail) still needed
    to crash, from (step, gap, speed, pending); ``NO_CRASH`` when no crash can happen any more.

    Attributes:
        gap_axis, speed_axis: the grid (metres, m/s), uniform.
        table: int32 [T, 2, G, S]: the bound at grid nodes per step and pending flag.
    """

    gap_axis: np.ndarray
    speed_axis: np.ndarray
    table: np.ndarray = field(repr=False)

    NO_CRASH = 1 << 20

    def __call__(self, step: int, gap_m: np.ndarray, speed_mps: np.ndarray, pending: np.ndarray) -> np.ndarray:
        """The bound for states at ``step``, int [N]: read at the grid node with the next smaller gap and
        the next larger speed (a state at least as dangerous), so it never exceeds the true number.

        Raises:
            ValueError: if a speed lies above the grid (the bound would not be valid).
        """
        g0, dg = self.gap_axis[0], self.gap_axis[1] - self.gap_axis[0]
        dv = self.speed_axis[1] - self.speed_axis[0]
        if np.any(speed_mps > self.speed_axis[-1]):
            top = float(np.max(speed_mps))
            raise ValueError(f"MissBound: speed {top:.3f} m/s above the grid's {self.speed_axis[-1]:.3f} m/s")
        gi = np.clip(np.floor((gap_m - g0) / dg + 1e-9).astype(np.int64), 0, self.gap_axis.size - 1)
        vi = np.clip(np.ceil(speed_mps / dv - 1e-9).astype(np.int64), 0, self.speed_axis.size - 1)
        out = self.table[step, np.asarray(pending, dtype=np.int64), gi, vi].astype(np.int64)
        return np.where(gap_m < g0, 0, out)


MISS_BOUND_MIN_GAP_M = 1.0
"""The smallest crash gap (metres) for which :func:`miss_bound` is checked: at 0.5 m and 0 m the failures of a
targeted run (``pemviz run --margin 0.5``) pass states where the ego is already braking hard and stops within a
step, and there the relaxed controller is not monotone in the speed, so the table is too high (85 and 466 of the
rollout-steps of seed 0's final failures); at 1 m, 1.5 m and 2 m none of 2,542 failures violates it
(``tests/test_severity.py`` checks 1 m)."""


def miss_bound(params: BrakingParams, start: BrakingStart, n_grid: int = 401) -> MissBound:
    """Backward DP of the least number of misses to a crash on a (gap, speed) grid (see :class:`MissBound`).

    m_{T-1} = NO_CRASH (no step left to observe a crash); m_t(node) = min over the action of
    [1 if a miss] + (0 if the next gap < 2 else m_{t+1}(next state rounded to the more dangerous node)),
    under :func:`_relaxed_step`. By induction it is at most the true least number from any state it bounds.

    Raises:
        ValueError: if the gap can come back to the braking distance after ``start`` (then missing is not
            always a cost and the order argument fails), or ``n_grid`` < 2.
    """
    if n_grid < 2:
        raise ValueError(f"miss_bound: n_grid must be >= 2, got {n_grid}")
    if params.crash_gap_m < MISS_BOUND_MIN_GAP_M:
        raise ValueError(
            f"miss_bound: crash gap {params.crash_gap_m:g} m is below {MISS_BOUND_MIN_GAP_M:g} m, where the bound is "
            "not a bound (sampled failures at 0.5 m and 0 m need fewer misses than it says)"
        )
    vl = lead_speeds(params)
    T, dt = params.n_steps, params.dt_s
    gap_hi = start.gap_m + dt * float(np.sum(vl[start.step :]))  # the ego never reverses
    if gap_hi >= params.braking_distance_m:
        raise ValueError(
            f"miss_bound: the gap can return to {gap_hi:.2f} m >= the braking distance after step {start.step}; "
            "the exact enumeration needs the lead to stay stopped once the ego is inside the braking distance"
        )
    speed_hi = max(start.speed_mps, params.target_speed_kmh / 3.6) + 1.5
    gap_axis = np.linspace(params.crash_gap_m, gap_hi, n_grid)
    speed_axis = np.linspace(0.0, speed_hi, n_grid)
    gg, vv = (a.ravel() for a in np.meshgrid(gap_axis, speed_axis, indexing="ij"))
    table = np.full((T, 2, n_grid, n_grid), MissBound.NO_CRASH, dtype=np.int32)
    bound = MissBound(gap_axis, speed_axis, table)
    for t in range(T - 2, start.step - 1, -1):
        for b in (0, 1):
            best = np.full(gg.size, MissBound.NO_CRASH, dtype=np.int64)
            for detected, cost in ((True, 0), (False, 1)):
                g2, v2, b2 = _relaxed_step(params, vl[t], gg, vv, np.full(gg.size, bool(b)), np.array(detected))
                m = np.where(g2 < params.crash_gap_m, 0, bound(t + 1, g2, v2, b2)) + cost
                best = np.minimum(best, m)
            table[t, b] = np.minimum(best, MissBound.NO_CRASH).reshape(n_grid, n_grid)
    return bound


def _log_binomial_tail(n_max: int, q: float) -> np.ndarray:
    """log P(Binomial(n, q) >= m), float64 [n_max + 1, n_max + 2] (row n, column m; -inf where m > n)."""
    from scipy.stats import binom  # scipy.stats takes ~0.5 s to import: only when a truth is computed

    out = np.full((n_max + 1, n_max + 2), -np.inf)
    for n in range(n_max + 1):
        out[n, 0] = 0.0
        m = np.arange(1, n + 1)
        out[n, 1 : n + 1] = binom.logsf(m - 1, n, q)
    return out


@dataclass(frozen=True)
class ExactResult:
    """p_fail of the braking scenario bracketed by exact enumeration.

    Attributes:
        log_p_fail: log of the probability of every enumerated crashing detection sequence (nats): a lower
            bound on p_fail, exact up to float64 rounding.
        log_pruned_bound: log of an upper bound on what the dropped sequences could add (nats).
        log_prune: a sequence is dropped when its bound is below exp(log_prune).
        min_misses: the bound on misses needed to crash at the start (a crash needs at least this many).
        max_paths: largest number of live sequences at one step.
        n_crash_paths: crashing sequences enumerated.
        start: where the branching starts; wall_s: seconds taken.
    """

    log_p_fail: float
    log_pruned_bound: float
    log_prune: float
    min_misses: int
    max_paths: int
    n_crash_paths: int
    start: BrakingStart
    wall_s: float

    @property
    def p_fail(self) -> float:
        return math.exp(self.log_p_fail)

    @property
    def log_p_fail_upper(self) -> float:
        return float(np.logaddexp(self.log_p_fail, self.log_pruned_bound))

    @property
    def relative_width(self) -> float:
        """(upper - lower) / lower: the most the answer can still move."""
        return math.exp(self.log_pruned_bound - self.log_p_fail) if self.log_p_fail > -math.inf else math.inf


def braking_exact(
    logit_at_gap: LogitFn,
    params: BrakingParams | None = None,
    *,
    log_prune: float = -54.0,
    bound_grid: int = 401,
    bound: MissBound | None = None,
    max_paths: int = 20_000_000,
) -> ExactResult:
    """p_fail of the braking scenario (latched or not) by enumerating detection sequences.

    From the branching start (:func:`branching_start`) every live sequence is split into its miss and its
    detection (probabilities 1 - p and p, p = sigmoid(logit_at_gap(gap)), in log-space) and stepped exactly
    with :func:`braking_step`; a sequence whose next gap is below the crash gap adds its probability to
    p_fail and ends. A live sequence of log-probability L at step t is dropped when
    ``L + log P(Binomial(n_left, q_max) >= m) < log_prune``, where m is the :class:`MissBound` of its
    state, n_left the actions still to come and q_max the largest miss probability inside the braking
    distance; that quantity bounds every crash it could still lead to, and the bounds of all dropped
    sequences add up to ``log_pruned_bound``. No state is merged or rounded.

    Args:
        logit_at_gap: logit p_PEM(detect | gap) (e.g. ``pem.logit_at_gap``).
        params: the scenario (default :class:`BrakingParams`).
        log_prune: drop threshold (nats); lower = tighter bracket, more sequences.
        bound_grid: points per axis of the miss-bound grid; ``bound`` reuses one already computed.
        max_paths: refuse to go on beyond this many live sequences (memory).
    Returns:
        :class:`ExactResult`: p_fail in [exp(log_p_fail), exp(log_p_fail_upper)].
    Raises:
        ValueError: see :func:`miss_bound`; RuntimeError: beyond ``max_paths`` live sequences.
    """
    t_start = time.perf_counter()
    p = params or BrakingParams()
    start = branching_start(p)
    bound = bound or miss_bound(p, start, bound_grid)
    vl = lead_speeds(p)
    T = p.n_steps
    gap_probe = np.linspace(p.crash_gap_m, p.braking_distance_m, 20001)
    q_max = float(np.max(expit(-np.asarray(logit_at_gap(gap_probe), dtype=np.float64))))
    log_tail = _log_binomial_tail(T, q_max)
    g, v = np.array([start.gap_m]), np.array([start.speed_mps])
    i, b = np.array([start.integral]), np.array([start.pending])
    lp = np.zeros(1)
    crash_terms: list[np.ndarray] = []
    pruned_terms: list[np.ndarray] = []
    max_live = 1
    for t in range(start.step, T - 1):
        logit = np.asarray(logit_at_gap(g), dtype=np.float64)
        inside = g < p.braking_distance_m
        n = g.size
        lp2 = np.concatenate([lp + np.where(inside, log_expit(-logit), 0.0), lp + log_expit(logit)])
        live = np.concatenate([np.ones(n, bool), inside])  # outside the braking distance: one outcome
        detected = np.concatenate([np.zeros(n, bool), np.ones(n, bool)])[live]
        g, v, i, b = braking_step(p, vl[t], np.tile(g, 2)[live], np.tile(v, 2)[live], np.tile(i, 2)[live],
                                  np.tile(b, 2)[live], detected)  # fmt: skip
        lp = lp2[live]
        crash = g < p.crash_gap_m
        crash_terms.append(lp[crash])
        g, v, i, b, lp = g[~crash], v[~crash], i[~crash], b[~crash], lp[~crash]
        m = bound(t + 1, g, v, b)
        n_left = (T - 1) - (t + 1)
        ub = lp + np.where(m >= MissBound.NO_CRASH, -np.inf, log_tail[n_left, np.minimum(m, T + 1)])
        drop = ub < log_prune
        pruned_terms.append(ub[drop])
        keep = ~drop
        g, v, i, b, lp = g[keep], v[keep], i[keep], b[keep], lp[keep]
        max_live = max(max_live, g.size)
        if g.size > max_paths:
            raise RuntimeError(
                f"braking_exact: {g.size:,} live sequences at step {t + 1} exceed max_paths = {max_paths:,}; "
                f"raise log_prune (now {log_prune})"
            )
        if g.size == 0:
            break
    crashes = np.concatenate(crash_terms) if crash_terms else np.zeros(0)
    pruned = np.concatenate(pruned_terms) if pruned_terms else np.zeros(0)
    m0 = int(bound(start.step, np.array([start.gap_m]), np.array([start.speed_mps]), np.array([start.pending]))[0])
    return ExactResult(
        float(logsumexp(crashes)), float(logsumexp(pruned)), float(log_prune), m0, int(max_live), int(crashes.size), start,
        time.perf_counter() - t_start,
    )  # fmt: skip


@dataclass(frozen=True)
class Refinement:
    """:func:`braking_exact` at decreasing drop thresholds until the bracket is narrow enough.

    Attributes:
        results: one :class:`ExactResult` per threshold, in the order run.
        tolerance: the target relative width (upper - lower) / lower.
    """

    results: tuple[ExactResult, ...]
    tolerance: float

    @property
    def final(self) -> ExactResult:
        return self.results[-1]

    @property
    def converged(self) -> bool:
        return self.final.relative_width < self.tolerance

    @property
    def log_p_fail(self) -> float:
        """The truth used to judge the sampler: the final lower bound (nats)."""
        return self.final.log_p_fail

    def rel_changes(self) -> list[float]:
        """|lower_k - lower_{k-1}| / lower_k (nan for the first)."""
        out = [math.nan]
        for a, b in zip(self.results, self.results[1:]):
            out.append(abs(math.exp(b.log_p_fail - a.log_p_fail) - 1.0) if b.log_p_fail > -math.inf else math.nan)
        return out

    def table(self) -> str:
        """The refinement table as Markdown."""
        rows = [
            "| drop threshold (nats) | live sequences (max) | crash sequences | p_fail (enumerated) | + dropped bound "
            "| upper bound | width | change | wall s |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r, ch in zip(self.results, self.rel_changes()):
            rows.append(
                f"| {r.log_prune:g} | {r.max_paths:,} | {r.n_crash_paths:,} | {format_probability(r.log_p_fail, 4)} "
                f"| {format_probability(r.log_pruned_bound, 2)} | {format_probability(r.log_p_fail_upper, 4)} "
                f"| {r.relative_width:.2%} | {'-' if math.isnan(ch) else f'{ch:.3%}'} | {r.wall_s:.1f} |"
            )
        return "\n".join(rows)


def braking_truth(
    logit_at_gap: LogitFn,
    params: BrakingParams | None = None,
    *,
    tolerance: float = 0.005,
    log_prunes: Sequence[float] = (-46.0, -50.0, -54.0, -58.0, -62.0, -66.0, -70.0, -80.0, -90.0),
    bound_grid: int = 401,
    stop_when_converged: bool = True,
    on_result: Callable[[ExactResult], None] | None = None,
) -> Refinement:
    """Refine :func:`braking_exact` over ``log_prunes`` until (upper - lower) / lower < ``tolerance``.

    The default 0.5 % stops the main scenario at -58 nats: a bracket of
    0.07 % in ~20-40 s and ~3.4 million live sequences (a few hundred MB) at most. The miss bound is
    computed once and shared. Returns every step of the refinement (its table is the
    "refinement table"). ``converged`` is False if the thresholds ran out first.
    """
    p = params or BrakingParams()
    start = branching_start(p)
    bound = miss_bound(p, start, bound_grid)
    results: list[ExactResult] = []
    for log_prune in log_prunes:
        r = braking_exact(logit_at_gap, p, log_prune=log_prune, bound=bound)
        results.append(r)
        if on_result is not None:
            on_result(r)
        if stop_when_converged and r.relative_width < tolerance and len(results) >= 2:
            break
    return Refinement(tuple(results), tolerance)


# -- exact answers known without computing ---------------------------------------------------------------------

FINGERPRINT_GRID_M = np.linspace(0.0, 15.0, 151)
"""Gaps (metres) at which a PEM's logit identifies it for :data:`KNOWN_BRAKING_LOG_P`."""

KNOWN_BRAKING_LOG_P: dict[str, float] = {
    "915fec568bb72b65": -33.85370929668962,  # shipped ml-nn: 1.9839e-15, bracket [1.9839, 1.9852]e-15
    "a849e1ba0edc2286": -36.44958177841474,  # shipped gbt: 1.4796e-16, bracket width 0.23 %
    # the shipped ml-nn's bootstrap ensemble (pemviz/assets/ensemble_ml-nn.pt) and logit shifts; benchmarks/pem_uncertainty.py --exact
    "f250e328566c1bdc": -26.519035882869872,  # member 0: 3.0404e-12, bracket width 0.24%, 112 s
    "bf4c1c809687fa3e": -24.582823139469383,  # member 1: 2.1077e-11, bracket width 2.25%, 108 s
    "6679d181a4ad1065": -40.692820684632736,  # member 2: 2.1249e-18, bracket width 0.12%, 2 s
    "f45a54aef268e592": -42.37336213762117,  # member 3: 3.9581e-19, bracket width 0.26%, 2 s
    "2865f802c0e34a9f": -36.450254643064305,  # member 4: 1.4786e-16, bracket width 0.22%, 2 s
    "cb10a4aec0e39b49": -25.8995843144133,  # member 5: 5.6488e-12, bracket width 0.17%, 133 s
    "17c9d9e78cf0ea1a": -37.71154936352811,  # member 6: 4.1887e-17, bracket width 0.42%, 3 s
    "d5b31a4e3ebb6a5d": -33.24577332499537,  # member 7: 3.6437e-15, bracket width 0.18%, 68 s
    "a42a3cdf14f209d4": -41.92471722195736,  # member 8: 6.1991e-19, bracket width 0.19%, 2 s
    "3c7bd1e6da0399ee": -44.36087067152231,  # member 9: 5.4240e-20, bracket width 0.31%, 2 s
    "1cddd061cfb4d9e2": -29.767082073020156,  # member 10: 1.1812e-13, bracket width 0.28%, 159 s
    "16e916a13b0af486": -30.656530336175717,  # member 11: 4.8533e-14, bracket width 0.16%, 60 s
    "727704a288081421": -37.96782366082595,  # member 12: 3.2418e-17, bracket width 0.20%, 3 s
    "8b39c597fff0f664": -32.122059772812484,  # member 13: 1.1209e-14, bracket width 0.35%, 4 s
    "9b09e347d2bbab11": -31.441655465664738,  # member 14: 2.2134e-14, bracket width 0.46%, 4 s
    "d98a860c5776b2e6": -38.14790467801863,  # member 15: 2.7075e-17, bracket width 0.31%, 3 s
    "c9771b412341fea0": -38.96919470956119,  # member 16: 1.1910e-17, bracket width 0.15%, 98 s
    "e250c21d5239ba55": -27.581581652581,  # member 17: 1.0507e-12, bracket width 0.15%, 62 s
    "e9a4ecf850268631": -30.77471271309537,  # member 18: 4.3123e-14, bracket width 0.08%, 41 s
    "e50861e616900537": -33.80379754946193,  # member 19: 2.0854e-15, bracket width 0.04%, 31 s
    "105acd0b9e59722b": -25.0012741796926,  # shift -1: 1.3870e-11, bracket width 0.41%, 297 s
    "771895e45f856b43": -29.409057940104958,  # shift -0.5: 1.6897e-13, bracket width 0.22%, 71 s
    "164ec23e6f625d90": -38.32218323907766,  # shift +0.5: 2.2745e-17, bracket width 0.32%, 2 s
    "45816c12490d672f": -42.8015576615671,  # shift +1: 2.5794e-19, bracket width 0.14%, 1 s
}
"""PEM fingerprint (:func:`pem_fingerprint`) -> natural log of the exact crash probability of the main braking
scenario (default :class:`BrakingParams`), from :func:`braking_truth` (bracket width < 0.1 %): the enumeration
takes 20-40 s, so the answers for the shipped PEMs are kept here (``tests/test_truth.py`` recomputes them), and those
of the shipped PEM's ensemble members and logit shifts, for ``pemviz run --pem-uncertainty`` (from
:func:`braking_exact` with drop thresholds below each one's p, bracket widths 0.04-2.3 %;
``benchmarks/pem_uncertainty.py --exact`` recomputes them)."""


KNOWN_BRAKING_MARGIN_LOG_P: dict[tuple[str, float], float] = {
    ("915fec568bb72b65", 1.5): -38.045588630879486,  # shipped ml-nn: 2.9992e-17, bracket width 0.09 %
    ("915fec568bb72b65", 1.0): -42.20786245180999,  # 4.6704e-19, bracket width 0.11 %
}
"""(PEM fingerprint, crash gap in metres) -> natural log of the exact probability that the gap of the main braking
scenario drops below that crash gap (the points of the exceedance curve, :mod:`pemviz.core.severity`), from
:func:`braking_truth` with ``BrakingParams(crash_gap_m=...)`` and drop thresholds down to -110 nats
(``benchmarks/severity.py`` recomputes them)."""


def pem_fingerprint(logit_at_gap: LogitFn) -> str:
    """A short hash of a PEM's detection curve: its logits on :data:`FINGERPRINT_GRID_M` rounded to 1e-6."""
    values = np.round(np.asarray(logit_at_gap(FINGERPRINT_GRID_M), dtype=np.float64), 6) + 0.0  # no -0.0
    return hashlib.sha256(values.tobytes()).hexdigest()[:16]


def known_log_failure_probability(logit_at_gap: LogitFn, params: BrakingParams | None = None) -> float | None:
    """The exact log p_fail (nats) of a braking problem when it is cheap to know, else None.

    The latched-brake scenario is computed (:func:`latched_log_failure_probability`, milliseconds); the main
    scenario with default parameters is looked up in :data:`KNOWN_BRAKING_LOG_P` by the PEM's fingerprint, and with
    another crash gap in :data:`KNOWN_BRAKING_MARGIN_LOG_P`.
    """
    p = params or BrakingParams()
    if p.latched_brake:
        return latched_log_failure_probability(logit_at_gap, p).log_p_fail
    default = BrakingParams()
    if dataclasses.replace(p, crash_gap_m=default.crash_gap_m) != default:
        return None
    if p.crash_gap_m == default.crash_gap_m:
        return KNOWN_BRAKING_LOG_P.get(pem_fingerprint(logit_at_gap))
    return KNOWN_BRAKING_MARGIN_LOG_P.get((pem_fingerprint(logit_at_gap), float(p.crash_gap_m)))
