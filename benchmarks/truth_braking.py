"""Ground truth of the braking scenario: exact enumeration vs. a grid DP with interpolation (issue 6).

Prints
1. the latched-brake scenario's exact p_fail (closed form over the deterministic simulator) and the
   enumeration's bracket for it (two independent algorithms, they must agree);
2. the refinement table of the main scenario's exact enumeration (pemviz.scenarios.braking.truth.braking_truth), down to
   a drop threshold where the bracket is far below 2 %;
3. the refinement table of a classical grid DP (backward value iteration on (gap, speed, integral) x pending
   with multilinear interpolation, the method first planned for issue 6) on both problems, to show why
   pemviz does not use it: V is a sum of step functions of the state, interpolation smears its jumps, and
   on the latched problem (exact answer known) the DP stays tens of % off on grids that look converged.

    python benchmarks/truth_braking.py            # ~2-5 min on 2 cores
    python benchmarks/truth_braking.py --fine     # adds the 801 x 801 grid DP (~5 min more)
"""

from __future__ import annotations

import argparse
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from pemviz.pem import load_pem
from pemviz.scenarios.braking.simulator import BrakingParams, braking_step, lead_speeds
from pemviz.scenarios.braking.truth import BrakingStart, braking_truth, branching_start
from pemviz.scenarios.braking.truth_latched import LogitFn, latched_log_failure_probability
from scipy.special import log_expit


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


DEFAULT_GRID = Grid(401, 401, 8)
"""The grid :func:`braking_dp` uses unless told otherwise."""


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
    grid: Grid = DEFAULT_GRID,
    *,
    chunk: int = 1 << 20,
) -> tuple[float, float]:
    """log p_fail by backward DP on a grid with multilinear interpolation of V; (log p, seconds)."""
    t_start = time.perf_counter()
    p = params or BrakingParams()
    start = branching_start(p)
    axes = _axes(p, start, grid)
    interp = _Interpolator(axes)
    vl = lead_speeds(p)
    n_gap, n_speed, n_int = (a.size for a in axes)
    gg, ss, ii = np.meshgrid(*axes, indexing="ij")
    gg, ss, ii = gg.ravel(), ss.ravel(), ii.ravel()
    logit = np.asarray(logit_at_gap(axes[0]), dtype=np.float64)
    p_hit = np.exp(log_expit(logit))[np.repeat(np.arange(n_gap), n_speed * n_int)]
    n_slice = n_gap * n_speed * n_int
    V = np.zeros(2 * n_slice)  # V_{T-1} on the grid: every node has gap >= 2
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
    positive = V[V > 0]
    if positive.size and positive.min() < 1e-290:
        raise ValueError("braking_dp: value function underflows float64; the problem needs a log-space DP")
    v_start = interp(
        V, np.array([start.pending]), (np.array([start.gap_m]), np.array([start.speed_mps]), np.array([start.integral]))
    )[0]
    log_p = math.log(v_start) if v_start > 0 else -math.inf
    return log_p, time.perf_counter() - t_start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fine", action="store_true", help="also run the grid DP on 801 x 801 x 4")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores")
    pem = load_pem()
    lt = latched_log_failure_probability(pem.logit_at_gap)
    print(
        f"\nlatched brake: exact p_fail = {lt.p_fail:.6e} = prod of (1 - p) over steps "
        f"{lt.first_step}..{lt.last_step}"
    )
    for latched in (True, False):
        name = "latched" if latched else "main"
        ref = braking_truth(
            pem.logit_at_gap,
            BrakingParams(latched_brake=latched),
            tolerance=0.002,
            log_prunes=(-46.0, -50.0, -54.0, -58.0, -62.0, -66.0, -70.0, -75.0),
        )
        print(f"\n## {name}: exact enumeration (converged to 0.2 %: {ref.converged})\n")
        print(ref.table())
        if latched:
            print(f"\nenumeration / closed form = {math.exp(ref.log_p_fail - lt.log_p_fail):.8f}")
    grids = [Grid(101, 101, 4), Grid(201, 201, 4), Grid(401, 401, 4)] + ([Grid(801, 801, 4)] if args.fine else [])
    truths = {True: lt.log_p_fail, False: braking_truth(pem.logit_at_gap, BrakingParams()).log_p_fail}
    for latched in (True, False):
        name = "latched" if latched else "main"
        print(f"\n## {name}: grid DP with multilinear interpolation (exact: {math.exp(truths[latched]):.4e})\n")
        print("| grid | p_fail | / exact | change | wall s |\n|---|---:|---:|---:|---:|")
        prev = None
        for g in grids:
            log_p, wall = braking_dp(pem.logit_at_gap, BrakingParams(latched_brake=latched), g)
            change = "-" if prev is None else f"{abs(math.expm1(log_p - prev)):.1%}"
            print(
                f"| {g} | {math.exp(log_p):.4e} | {math.exp(log_p - truths[latched]):.3f} | {change} | {wall:.1f} |",
                flush=True,
            )
            prev = log_p


if __name__ == "__main__":
    main()
