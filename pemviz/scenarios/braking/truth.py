"""Exact failure probabilities of the braking scenario by enumeration.

The only randomness is the detector and the dynamics are deterministic, so p_fail is a sum over detection sequences.
:func:`braking_exact` follows every sequence exactly from the first step inside the braking distance and drops one
only when a rigorous bound on all it could still contribute is below a threshold: a dynamic program on a (gap,
speed) grid of the least number of misses that can still lead to a crash (:func:`miss_bound`; below a 1 m crash gap
the cell version :func:`~pemviz.scenarios.braking.truth_cells.cell_miss_bound`; :func:`exact_bound` picks). The
result is a bracket [enumerated, enumerated + dropped bound], refined until narrower than the tolerance
(:func:`braking_truth`). A value-function grid with interpolation smears V's jumps
(``benchmarks/truth_braking.py``).

The dynamics are :func:`pemviz.scenarios.braking.simulator.braking_step`; probabilities are natural logs (nats) in
float64."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.special import expit, log_expit, logsumexp

from pemviz.core.estimate import format_probability
from pemviz.scenarios.braking.simulator import BrakingParams, braking_step, lead_speeds
from pemviz.scenarios.braking.truth_cells import CellMissBound, cell_miss_bound, largest_gap_after
from pemviz.scenarios.braking.truth_latched import LogitFn


@dataclass(frozen=True)
class BrakingStart:
    """The scenario's state at the first step where a detection can matter (gap < braking distance).

    Every step before ``step`` has gap >= the braking distance, where both detector outputs lead to the
    same next state: the prefix is deterministic."""

    step: int
    gap_m: float
    speed_mps: float
    integral: float
    pending: bool


def branching_start(params: BrakingParams) -> BrakingStart:
    """Run the deterministic prefix until the gap first drops below the braking distance.

    Raises:
        ValueError: if that never happens within the episode (nothing random: p_fail is 0 or 1)."""
    vl = lead_speeds(params)
    g, v, i, b = (np.array([params.gap0_m]), np.array([params.ego_speed0_mps]), np.zeros(1), np.zeros(1, bool))
    for t in range(params.n_steps):
        if g[0] < params.braking_distance_m:
            return BrakingStart(t, float(g[0]), float(v[0]), float(i[0]), bool(b[0]))
        g, v, i, b = braking_step(params, vl[t], g, v, i, b, np.zeros(1, bool))
    raise ValueError("branching_start: the gap never drops below the braking distance; p_fail is 0 or 1")


# -- 3. main scenario: exact enumeration with a rigorous bound (module docstring) --------------------------------


def _relaxed_step(params: BrakingParams, lead_speed_mps: float, gap_m, speed_mps, pending, detected):
    """:func:`braking_step` of a controller that is never gentler (the PID integral at its largest, no PID brake):
    its next speed is at least the true one, and it is monotone in the speed (tests/scenarios/test_truth.py), so a
    state no safer stays no safer under the same action, which :class:`MissBound` rests on."""
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
        table: int32 [T, 2, G, S]: the bound at grid nodes per step and pending flag."""

    gap_axis: np.ndarray
    speed_axis: np.ndarray
    table: np.ndarray = field(repr=False)

    NO_CRASH = 1 << 20

    def __call__(self, step: int, gap_m: np.ndarray, speed_mps: np.ndarray, pending: np.ndarray) -> np.ndarray:
        """The bound for states at ``step``, int [N]: read at the grid node with the next smaller gap and
        the next larger speed (a state at least as dangerous), so it never exceeds the true number.

        Raises:
            ValueError: if a speed lies above the grid (the bound would not be valid)."""
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
"""The smallest crash gap (metres) for which :func:`miss_bound` is valid; below it :func:`exact_bound` takes
:func:`~pemviz.scenarios.braking.truth_cells.cell_miss_bound`: below the contact gap a state that stops just above
it is safer than one arriving faster, which breaks the table's order (checked in
``tests/scenarios/test_truth_cells.py``; docs/validation.md)."""


def miss_bound(params: BrakingParams, start: BrakingStart, n_grid: int = 401) -> MissBound:
    """Backward DP of the least number of misses to a crash on a (gap, speed) grid (see :class:`MissBound`).

    m_{T-1} = NO_CRASH; m_t(node) = min over the action of [1 if a miss] + (0 if the next gap < 2 else m_{t+1}(next
    state rounded to the more dangerous node)), under :func:`_relaxed_step`: by induction at most the true least
    number from any state it bounds.

    Raises:
        ValueError: if the gap can come back to the braking distance after ``start`` (then missing is not
            always a cost and the order argument fails), or ``n_grid`` < 2."""
    if n_grid < 2:
        raise ValueError(f"miss_bound: n_grid must be >= 2, got {n_grid}")
    if params.crash_gap_m < MISS_BOUND_MIN_GAP_M:
        raise ValueError(
            f"miss_bound: crash gap {params.crash_gap_m:g} m is below {MISS_BOUND_MIN_GAP_M:g} m, where the bound is "
            "not a bound (sampled failures at 0.5 m and 0 m need fewer misses than it says); use cell_miss_bound"
        )
    vl = lead_speeds(params)
    T = params.n_steps
    gap_hi = largest_gap_after(params, start.step, start.gap_m, "miss_bound")
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


CELL_GAP_REFINE = 5
"""Gap cells per speed cell of :func:`exact_bound`'s cell bound: a cell's next states touch the cell below nearly
every step (the box is a cell wide), so the bound loses up to a gap cell per step and needs finer gap cells than
the node table; at 2,000 x 400 cells its 1 m table equals :func:`miss_bound`'s at the start (9 misses)."""


def exact_bound(params: BrakingParams, start: BrakingStart, bound_grid: int = 401) -> MissBound | CellMissBound:
    """The miss bound the enumeration uses for ``params``: :func:`miss_bound` on a ``bound_grid`` x ``bound_grid``
    grid where it is valid (crash gap >= :data:`MISS_BOUND_MIN_GAP_M`), else
    :func:`~pemviz.scenarios.braking.truth_cells.cell_miss_bound` on ``CELL_GAP_REFINE * (bound_grid - 1)`` by
    ``bound_grid - 1`` cells.

    Raises:
        ValueError: see :func:`miss_bound` and :func:`~pemviz.scenarios.braking.truth_cells.cell_miss_bound`."""
    if params.crash_gap_m >= MISS_BOUND_MIN_GAP_M:
        return miss_bound(params, start, bound_grid)
    cells = max(bound_grid - 1, 1)
    return cell_miss_bound(params, start, n_gap=CELL_GAP_REFINE * cells, n_speed=cells)


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
        start: where the branching starts; wall_s: seconds taken."""

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
    bound: MissBound | CellMissBound | None = None,
    max_paths: int = 20_000_000,
    start: BrakingStart | None = None,
) -> ExactResult:
    """p_fail of the braking scenario (latched or not) by enumerating detection sequences.

    From :func:`branching_start` every live sequence splits into its miss and its detection and is stepped with
    :func:`braking_step`, adding to p_fail below the crash gap; a sequence of log-probability L is dropped when ``L
    + log P(Binomial(n_left, q_max) >= m) < log_prune`` (m its miss bound, :func:`exact_bound`), its bound added to
    ``log_pruned_bound``.

    Args:
        logit_at_gap: logit p_PEM(detect | gap) (e.g. ``pem.logit_at_gap``).
        params: the scenario (default :class:`BrakingParams`).
        log_prune: drop threshold (nats); lower = tighter bracket, more sequences.
        bound_grid: points per axis of the miss-bound grid (:func:`exact_bound`).
        bound: a miss bound already computed, reused (None: computed on ``bound_grid``).
        max_paths: refuse to go on beyond this many live sequences (memory).
        start: the state to enumerate from (None: :func:`branching_start`); the result is then the committor of that
            state (Kollman, Baggerly, Cox & Picard 1999, Ann. Appl. Probab. 9(2)).
    Returns:
        :class:`ExactResult`: p_fail in [exp(log_p_fail), exp(log_p_fail_upper)].
    Raises:
        ValueError: see :func:`miss_bound`; RuntimeError: beyond ``max_paths`` live sequences."""
    t_start = time.perf_counter()
    p = params or BrakingParams()
    start = start or branching_start(p)
    bound = bound or exact_bound(p, start, bound_grid)
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
        g, v, i, b = braking_step(
            p, vl[t], np.tile(g, 2)[live], np.tile(v, 2)[live], np.tile(i, 2)[live], np.tile(b, 2)[live], detected
        )
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
        float(logsumexp(crashes)),
        float(logsumexp(pruned)),
        float(log_prune),
        m0,
        int(max_live),
        int(crashes.size),
        start,
        time.perf_counter() - t_start,
    )


@dataclass(frozen=True)
class Refinement:
    """:func:`braking_exact` at decreasing drop thresholds until the bracket is narrow enough.

    Attributes:
        results: one :class:`ExactResult` per threshold, in the order run.
        tolerance: the target relative width (upper - lower) / lower."""

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
        for a, b in zip(self.results, self.results[1:], strict=False):
            out.append(abs(math.exp(b.log_p_fail - a.log_p_fail) - 1.0) if b.log_p_fail > -math.inf else math.nan)
        return out

    def table(self) -> str:
        """The refinement table as Markdown."""
        rows = [
            "| drop threshold (nats) | live sequences (max) | crash sequences | p_fail (enumerated) | + dropped bound "
            "| upper bound | width | change | wall s |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r, ch in zip(self.results, self.rel_changes(), strict=False):
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
    """Refine :func:`braking_exact` over ``log_prunes`` until (upper - lower) / lower < ``tolerance`` (the miss
    bound computed once and shared); returns every step of the refinement, ``converged`` False if the thresholds ran
    out first (timings: docs/validation.md)."""
    p = params or BrakingParams()
    start = branching_start(p)
    bound = exact_bound(p, start, bound_grid)
    results: list[ExactResult] = []
    for log_prune in log_prunes:
        r = braking_exact(logit_at_gap, p, log_prune=log_prune, bound=bound)
        results.append(r)
        if on_result is not None:
            on_result(r)
        if stop_when_converged and r.relative_width < tolerance and len(results) >= 2:
            break
    return Refinement(tuple(results), tolerance)
