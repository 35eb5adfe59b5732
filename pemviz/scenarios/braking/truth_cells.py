"""A miss bound for the braking enumeration that needs no monotone dynamics: a dynamic program over cells.

:class:`pemviz.scenarios.braking.truth.MissBound` takes a smaller gap and a larger speed as never safer, which fails
below the contact gap (:attr:`BrakingParams.contact_gap_m`), where the scene stops the ego; crash gaps of 0.5 m and
0 m need a bound that does not rest on it. :func:`cell_miss_bound` bounds sets instead of points: the states inside
the braking distance and above the contact gap are cut into (gap, speed) cells per brake-pending flag; for each cell
and detector output the DP encloses all next states in a box (widened by ``_EPS`` = 1e-9, :func:`speed_ranges`) and
takes the least bound over the cells it touches, plus the states decided at once. By induction a cell's bound is at
most the least number of misses with which any of its states can still crash: the enclosure argument of interval
analysis (Moore, Kearfott & Cloud, *Introduction to Interval Analysis*, SIAM 2009). Its wrapping effect needs finer
gap cells (:data:`pemviz.scenarios.braking.truth.CELL_GAP_REFINE`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pemviz.scenarios.braking.simulator import BrakingParams, braking_step, lead_speeds

NO_CRASH = 1 << 20
"""The bound of a state from which no crash can happen any more (the same value as ``MissBound.NO_CRASH``)."""

_NC16 = np.int16(30000)
"""NO_CRASH inside the int16 tables (never more misses than steps, so no clash)."""

_EPS = 1e-9
"""Every box is widened by this much (metres, m/s) on each side, which covers float64 rounding in the cell indices."""


def largest_gap_after(params: BrakingParams, step: int, gap_m: float, who: str) -> float:
    """The largest gap (metres) the scenario can reach after ``step``, where the gap is ``gap_m`` (a branching start,
    :func:`pemviz.scenarios.braking.truth.branching_start`): that gap plus every later step's lead travel (the ego
    never reverses), the upper end of a miss bound's gap axis.

    Raises:
        ValueError: naming ``who``, if that gap reaches the braking distance (then a miss is not always a cost and
            the order argument of the bounds fails)."""
    gap_hi = gap_m + params.dt_s * float(np.sum(lead_speeds(params)[step:]))
    if gap_hi >= params.braking_distance_m:
        raise ValueError(
            f"{who}: the gap can return to {gap_hi:.2f} m >= the braking distance after step {step}; "
            "the exact enumeration needs the lead to stay stopped once the ego is inside the braking distance"
        )
    return gap_hi


def integral_range(params: BrakingParams, start_integral: float, speed_top_mps: float) -> tuple[float, float]:
    """The PID integral's reachable range (km/h s) from ``start_integral`` while the speed stays in [0,
    ``speed_top_mps``]: ``I' = leak I + e dt`` with ``e`` in [target - 3.6 top, target] stays between ``e dt / (1 -
    leak)`` at the two ends (and the start).

    Raises:
        ValueError: ``integral_leak`` = 1 (no bounded range)."""
    p = params
    if p.integral_leak >= 1.0:
        raise ValueError("integral_range: integral_leak = 1 leaves the PID integral unbounded")
    e_lo, e_hi = p.target_speed_kmh - 3.6 * speed_top_mps, p.target_speed_kmh
    k = p.dt_s / (1.0 - p.integral_leak)
    return min(start_integral, e_lo * k), max(start_integral, e_hi * k)


def speed_lipschitz(params: BrakingParams, speed_top_mps: float) -> float:
    """A bound on |d v' / d v| of the ego's one-step speed map (:func:`braking_step`) for speeds in [0,
    ``speed_top_mps``], any integral, command and detector output, inside the braking distance and above the contact
    gap: ``1 + dt (|a'_throttle| + |a'_pid| + |decel'|)``, each slope bounded from its formula (clipping only
    flattens)."""
    p = params
    kc = 3.6 * (p.kp + p.ki * p.dt_s)  # |dc/dv|
    a_top = max(abs(p.throttle_accel0_mps2), abs(p.throttle_accel0_mps2 - p.throttle_accel_slope_per_s * speed_top_mps))
    knots, decel = np.asarray(p.brake_knots_mps), np.asarray(p.brake_decel_mps2)
    slopes = np.abs(np.diff(decel) / np.diff(knots)) if knots.size > 1 else np.zeros(1)
    d_slope, d_max = float(slopes.max(initial=0.0)), float(np.max(np.abs(decel)))
    throttle = (p.throttle_accel_slope_per_s * p.max_throttle + a_top * kc) / p.max_throttle
    pid = (d_slope * p.max_pid_brake + d_max * kc) / p.emergency_brake
    return 1.0 + p.dt_s * (throttle + pid + d_slope)


def speed_ranges(
    params: BrakingParams,
    speed_edges: np.ndarray,
    integral_lo: float,
    integral_hi: float,
    pending: bool,
    detected: bool,
    samples: int = 513,
) -> tuple[np.ndarray, np.ndarray, bool]:
    """The range of the ego's next speed over each speed cell and the integral's range, and the next brake command.

    The next speed is non-decreasing in the integral, so its extremes over the integral are at ``integral_lo`` and
    ``integral_hi``; over the cell's speeds it is Lipschitz (:func:`speed_lipschitz`, L), so each cell's range is
    the samples' range widened by ``L h / 2`` and ``_EPS``.

    Args:
        params: the scenario's constants.
        speed_edges: cell edges (m/s), float64 [S + 1], increasing.
        integral_lo: the PID integral's least value (km/h s, :func:`integral_range`).
        integral_hi: its largest value (km/h s).
        pending: the brake command of the last step.
        detected: this step's detector output.
        samples: speeds evaluated per cell.
    Returns:
        (lo [S], hi [S]) in m/s with lo <= v' <= hi for every speed of the cell and integral of the range, and the
            next brake command.
    Raises:
        ValueError: a speed above ``a0 / a1``, where more throttle would slow the ego and the integral's order
            fails."""
    p = params
    top = float(speed_edges[-1])
    if p.throttle_accel_slope_per_s > 0 and top > p.throttle_accel0_mps2 / p.throttle_accel_slope_per_s:
        raise ValueError(f"speed_ranges: speeds up to {top:.2f} m/s pass a0/a1, where the throttle decelerates")
    lo_edges, hi_edges = speed_edges[:-1], speed_edges[1:]
    u = np.linspace(0.0, 1.0, samples)
    v = lo_edges[:, None] + (hi_edges - lo_edges)[:, None] * u[None, :]  # [S, samples]
    gap = np.full(v.shape, 0.5 * (max(p.contact_gap_m, 0.0) + p.braking_distance_m))
    if not p.contact_gap_m < gap[0, 0] < p.braking_distance_m:
        raise ValueError("speed_ranges: no gap lies between the contact gap and the braking distance")
    out = []
    for integral in (integral_lo, integral_hi):
        _, v2, _, b2 = braking_step(
            p, 0.0, gap, v, np.full(v.shape, integral), np.full(v.shape, pending), np.full(v.shape, detected)
        )
        out.append(v2)
    margin = speed_lipschitz(p, top) * float(np.max(hi_edges - lo_edges)) / (samples - 1) / 2.0 + _EPS
    lo = np.maximum(np.minimum(out[0], out[1]).min(axis=1) - margin, 0.0)
    hi = np.maximum(out[0], out[1]).max(axis=1) + margin
    return lo, hi, bool(b2.flat[0])


class _RangeMin:
    """Least value of an int16 [G, S] table over index rectangles (a 2-D sparse table: O(1) per query)."""

    def __init__(self, table: np.ndarray, max_rows: int, max_cols: int) -> None:
        self.kx = max(int(max_rows).bit_length(), 1)
        self.ky = max(int(max_cols).bit_length(), 1)
        g, s = table.shape
        st = np.empty((self.kx, self.ky, g, s), dtype=table.dtype)
        st[0, 0] = table
        for ky in range(1, self.ky):
            w = 1 << (ky - 1)
            st[0, ky] = st[0, ky - 1]
            np.minimum(st[0, ky - 1][:, : s - w], st[0, ky - 1][:, w:], out=st[0, ky][:, : s - w])
        for kx in range(1, self.kx):
            w = 1 << (kx - 1)
            st[kx] = st[kx - 1]
            np.minimum(st[kx - 1][:, : g - w], st[kx - 1][:, w:], out=st[kx][:, : g - w])
        self.st = st

    def __call__(self, ia, ib, ja, jb) -> np.ndarray:
        """min of table[ia..ib, ja..jb] (inclusive; ib >= ia, jb >= ja), elementwise over the index arrays."""
        kx = np.floor(np.log2(ib - ia + 1)).astype(np.int64)
        ky = np.floor(np.log2(jb - ja + 1)).astype(np.int64)
        if kx.size and (kx.max() >= self.kx or ky.max() >= self.ky):
            raise RuntimeError("_RangeMin: a query wider than the table was built for")
        ib2, jb2 = ib - (1 << kx) + 1, jb - (1 << ky) + 1
        st = self.st
        return np.minimum(
            np.minimum(st[kx, ky, ia, ja], st[kx, ky, ib2, ja]), np.minimum(st[kx, ky, ia, jb2], st[kx, ky, ib2, jb2])
        )


@dataclass(frozen=True)
class CellMissBound:
    """A lower bound on the number of misses (detector failures inside the braking distance) still needed to crash,
    from (step, gap, speed, pending), valid at any crash gap (:func:`cell_miss_bound`); ``NO_CRASH`` when no crash
    can happen any more.

    Attributes:
        params: the scenario; first_step: the first step the table covers (the branching start).
        gap_edges: cell edges over the gaps above max(crash gap, contact gap) (metres), uniform, float64 [G + 1].
        speed_edges: cell edges over [0, top] (m/s), uniform, float64 [S + 1].
        table: int16 [T - first_step, 2, G, S]: the bound per step from ``first_step``, pending flag and cell
            (30000: no crash)."""

    params: BrakingParams
    first_step: int
    gap_edges: np.ndarray
    speed_edges: np.ndarray
    table: np.ndarray = field(repr=False)

    NO_CRASH = NO_CRASH

    def __call__(self, step: int, gap_m: np.ndarray, speed_mps: np.ndarray, pending: np.ndarray) -> np.ndarray:
        """The bound for states at ``step``, int64 [N]: the table of the cell holding each state; a state at or
        below the contact gap is decided exactly (0 if the gap it still moves crosses the crash gap in time, else
        ``NO_CRASH``), one below the crash gap is 0.

        Raises:
            ValueError: a step before :attr:`first_step`, or a state above the grid (the bound would not hold)."""
        p = self.params
        if step < self.first_step:
            raise ValueError(f"CellMissBound: step {step} is before the table's first step {self.first_step}")
        g = np.asarray(gap_m, dtype=np.float64)
        v = np.asarray(speed_mps, dtype=np.float64)
        b = np.asarray(pending, dtype=np.int64)
        T = p.n_steps
        if step >= T - 1:
            return np.where(g < p.crash_gap_m, 0, NO_CRASH)
        g0, dg = self.gap_edges[0], self.gap_edges[1] - self.gap_edges[0]
        dv = self.speed_edges[1] - self.speed_edges[0]
        dom = (g > p.contact_gap_m) & (g >= p.crash_gap_m)  # the cells' dynamics: the ego not stopped
        if g.size and (
            np.max(np.where(dom, g, -np.inf)) > self.gap_edges[-1]
            or np.max(np.where(dom, v, -np.inf)) > self.speed_edges[-1]
        ):
            raise ValueError(
                f"CellMissBound: a state above the grid (gap <= {self.gap_edges[-1]:.3f} m, "
                f"speed <= {self.speed_edges[-1]:.3f} m/s)"
            )
        n_g, n_v = self.gap_edges.size - 1, self.speed_edges.size - 1
        gi = np.minimum(np.maximum((g - g0) / dg, 0.0), n_g - 1).astype(np.int64)  # floor of a number >= 0
        vi = np.minimum(np.maximum(v / dv, 0.0), n_v - 1).astype(np.int64)
        flat = (b * n_g + gi) * n_v + vi
        out = np.take(self.table[step - self.first_step].reshape(-1), flat).astype(np.int64)
        out[out >= int(_NC16)] = NO_CRASH
        rest = ~dom
        if rest.any():  # at or below the contact gap (decided next step) or below the crash gap (crashed)
            vl = lead_speeds(p)[step]
            gr, vr = g[rest], v[rest]
            zone_crash = (gr + (vl - vr) * p.dt_s < p.crash_gap_m) & (step + 1 <= T - 1)
            out[rest] = np.where((gr < p.crash_gap_m) | zone_crash, 0, NO_CRASH)
        return out


def cell_miss_bound(
    params: BrakingParams, start, n_gap: int = 2000, n_speed: int = 400, speed_margin_mps: float = 1.5
) -> CellMissBound:
    """Backward DP over cells of the least number of misses to a crash (see the module and :class:`CellMissBound`).

    Args:
        params: the scenario (any crash gap >= 0).
        start: the branching start (:func:`pemviz.scenarios.braking.truth.branching_start`).
        n_gap: cells along the gap.
        n_speed: cells along the ego's speed.
        speed_margin_mps: the speed axis reaches max(start speed, target speed) plus this.
    Returns:
        :class:`CellMissBound`: M_t(cell, b) = min over the detector output of [1 if a miss] + the least value over
            the box of next states.
    Raises:
        ValueError: if the gap can come back to the braking distance after ``start``, a grid of fewer than 2 cells,
            or see :func:`integral_range` and :func:`speed_ranges`."""
    p = params
    if n_gap < 2 or n_speed < 2:
        raise ValueError(f"cell_miss_bound: n_gap and n_speed must be >= 2, got {n_gap}, {n_speed}")
    vl = lead_speeds(p)
    T, dt = p.n_steps, p.dt_s
    gap_hi = largest_gap_after(p, start.step, start.gap_m, "cell_miss_bound")
    floor_gap = max(p.crash_gap_m, p.contact_gap_m)
    zone = p.crash_gap_m <= p.contact_gap_m  # gaps at or below the contact gap can be reached without a crash
    speed_top = max(start.speed_mps, p.target_speed_kmh / 3.6) + speed_margin_mps
    gap_edges = np.linspace(floor_gap, max(gap_hi, floor_gap + 1e-6), n_gap + 1)
    speed_edges = np.linspace(0.0, speed_top, n_speed + 1)
    i_lo, i_hi = integral_range(p, start.integral, speed_top)
    dg, dv = gap_edges[1] - gap_edges[0], speed_edges[1] - speed_edges[0]
    ranges = {(b, d): speed_ranges(p, speed_edges, i_lo, i_hi, bool(b), d) for b in (0, 1) for d in (False, True)}
    max_cols = max(int(np.max(np.floor(hi / dv) - np.floor(lo / dv))) + 1 for lo, hi, _ in ranges.values())
    max_rows = int(math.ceil((dg + dv * dt + 2 * _EPS) / dg)) + 1
    t0 = start.step
    table = np.full((T - t0, 2, n_gap, n_speed), _NC16, dtype=np.int16)
    g_lo_cell, g_hi_cell = gap_edges[:-1, None], gap_edges[1:, None]
    v_lo_cell, v_hi_cell = speed_edges[None, :-1], speed_edges[None, 1:]
    for t in range(T - 2, start.step - 1, -1):
        s = t + 1
        rmq = None
        if s <= T - 2:
            rmq = [_RangeMin(table[s - t0, b2], max_rows, max_cols) for b2 in (0, 1)]
        G_lo = g_lo_cell + (vl[t] - v_hi_cell) * dt - _EPS  # [G, S]
        G_hi = g_hi_cell + (vl[t] - v_lo_cell) * dt + _EPS
        crash = G_lo < p.crash_gap_m
        for b in (0, 1):
            best = np.full((n_gap, n_speed), NO_CRASH, dtype=np.int64)
            for detected, cost in ((True, 0), (False, 1)):
                V_lo, V_hi, b2 = ranges[(b, detected)]
                V_lo, V_hi = np.broadcast_to(V_lo[None, :], G_lo.shape), np.broadcast_to(V_hi[None, :], G_lo.shape)
                val = np.full(G_lo.shape, NO_CRASH, dtype=np.int64)
                if zone and s + 1 <= T - 1:
                    zone_crash = (G_lo <= p.contact_gap_m) & (G_lo + (vl[s] - V_hi) * dt < p.crash_gap_m)
                    val[zone_crash] = 0
                dom = G_hi >= floor_gap
                if rmq is not None and dom.any():
                    beyond = (G_hi > gap_edges[-1]) | (V_hi > speed_edges[-1])
                    ia = np.clip(
                        np.floor((np.maximum(G_lo, floor_gap) - floor_gap) / dg).astype(np.int64), 0, n_gap - 1
                    )
                    ib = np.clip(np.floor((G_hi - floor_gap) / dg).astype(np.int64), ia, n_gap - 1)
                    ja = np.clip(np.floor(V_lo / dv).astype(np.int64), 0, n_speed - 1)
                    jb = np.clip(np.floor(V_hi / dv).astype(np.int64), ja, n_speed - 1)
                    m = rmq[int(b2)](ia[dom], ib[dom], ja[dom], jb[dom]).astype(np.int64)
                    m = np.where(m >= int(_NC16), NO_CRASH, m)
                    m = np.where(beyond[dom], 0, m)
                    val[dom] = np.minimum(val[dom], m)
                val[crash] = 0
                best = np.minimum(best, val + cost)
            table[t - t0, b] = np.minimum(best, int(_NC16)).astype(np.int16)
    return CellMissBound(p, start.step, gap_edges, speed_edges, table)
