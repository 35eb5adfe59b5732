"""How far the braking tilt's committor is from the exact one, and what that costs the estimate.

The braking scene's only randomness is the detector, so the exact committor of a state, P(crash | state), is an
enumeration of every detection sequence after it (:func:`pemviz.scenarios.braking.truth.braking_exact` from that
state). The tilt's committor is a dynamic program on a (gap, speed) grid (``research/braking_tilt.py``).
This script prints

1. the grid committor's solve (steps, seconds) and its value at the branching start against the exact answer;
2. for states drawn from the tilt's own rollouts (one per rollout, at a step inside the braking distance before its
   crash): log10 V of the grid and of the enumeration, and the quantity the proposal is made of, the log odds
   log V(s'_detect) - log V(s'_miss) of the two outcomes' next states (nats), from both;
3. the tilt's relative variance over seeds at 1,000 rollouts: relvar x simulations for a run that solves the
   committor and for one that reuses it (the default sampler's, cross-entropy, is 1.4-2.0: docs/validation.md).

    python benchmarks/braking_committor.py                 # 12 states, 100 seeds: ~3-6 min on 2 cores
    python benchmarks/braking_committor.py --states 30 --seeds 200
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np
from pemviz.core.detectors import PEMDetector
from pemviz.pem import load_pem
from pemviz.scenarios.braking.simulator import BrakingParams, braking_step, lead_speeds
from pemviz.scenarios.braking.truth import BrakingStart, braking_exact, branching_start, exact_bound
from pemviz.scenarios.braking.truth_known import known_log_failure_probability
from scipy.special import logsumexp

_spec = importlib.util.spec_from_file_location(
    "braking_tilt", Path(__file__).resolve().parents[1] / "research" / "braking_tilt.py"
)
assert _spec is not None and _spec.loader is not None
_tilt = sys.modules["braking_tilt"] = importlib.util.module_from_spec(_spec)  # research/ is not a package
_spec.loader.exec_module(_tilt)
BrakingTilt, BrakingTiltDetector, draw_tilted = _tilt.BrakingTilt, _tilt.BrakingTiltDetector, _tilt.draw_tilted
solve_committor = _tilt.solve_committor


def with_braking_tilt(problem, cfg):
    """``problem`` with the braking tilt attached where ``cfg`` runs ``method = "tilt"`` on braking (pemviz run has
    none there: ``research/braking_tilt.py``), else ``problem`` itself."""
    if cfg.method != "tilt" or cfg.scenario != "braking":
        return problem
    from pemviz.pem import load_pem

    return _tilt.tilted_problem(problem, load_pem(cfg.value("pem")))


LN10 = np.log(10.0)


def exact_log_v(logit, p: BrakingParams, bound, state: BrakingStart, guess: float) -> tuple[float, float]:
    """(log V, its bracket's upper end) of ``state`` by enumeration (nats), dropping sequences 25 nats below the
    grid's guess (at most -58 nats)."""
    if state.gap_m < p.crash_gap_m:
        return 0.0, 0.0
    if state.step >= p.n_steps - 1:
        return -np.inf, -np.inf
    r = braking_exact(logit, p, bound=bound, start=state, log_prune=min(-20.0, max(-58.0, guess - 25.0)))
    return r.log_p_fail, r.log_p_fail_upper


def successors(p: BrakingParams, s: BrakingStart) -> tuple[BrakingStart, BrakingStart]:
    """The states after a detection and after a miss at ``s``."""
    out = []
    for detected in (True, False):
        g, v, i, b = braking_step(
            p,
            float(lead_speeds(p)[s.step]),
            np.array([s.gap_m]),
            np.array([s.speed_mps]),
            np.array([s.integral]),
            np.array([s.pending]),
            np.array([detected]),
        )
        out.append(BrakingStart(s.step + 1, float(g[0]), float(v[0]), float(i[0]), bool(b[0])))
    return out[0], out[1]


def study(states: int = 12, seeds: int = 100, seed: int = 0) -> dict[str, float]:
    """Print the module docstring's three parts: ``states`` states drawn from the tilt's rollouts of ``seed``, then
    ``seeds`` tilted runs of 1,000 rollouts. Returns the grid committor's distance from the exact one over the states
    (``log10_v_median``, ``log10_v_rms``: log10 V, grid less exact; ``shift_rms``: the log odds shift's error, nats)
    and the tilt's ``mean`` (x p), ``relvar_sims_solving`` and ``relvar_sims_reusing``."""
    pem, p = load_pem(), BrakingParams()
    logit = pem.logit_at_gap
    log_p = known_log_failure_probability(logit, p)
    t0 = time.perf_counter()
    grid = solve_committor(p, logit)
    solve_s = time.perf_counter() - t0
    start = branching_start(p)
    at_start = float(
        grid.log_value(start.step, np.array([start.gap_m]), np.array([start.speed_mps]), np.array([start.pending]))[0]
    )
    print(
        f"grid committor: {grid.gap_axis.size} gaps x {grid.speed_axis.size} speeds x 2, steps {grid.first_step}-"
        f"{p.n_steps - 1}; solve {grid.steps:,} steps ({grid.steps / p.n_steps:,.0f} rollout-equivalents), "
        f"{solve_s:.2f} s"
    )
    print(
        f"at the branching start (step {start.step}, gap {start.gap_m:.2f} m): grid V {np.exp(at_start):.3e}, "
        f"exact {np.exp(log_p):.3e} (x{np.exp(at_start - log_p):.3g})"
    )

    bound = exact_bound(p, start, 401)
    rng = np.random.default_rng(seed)
    detector = BrakingTiltDetector(grid, logit)
    batch = draw_tilted(detector, PEMDetector(pem), states, rng)
    gaps, detected = batch.observations[..., 0], np.asarray(batch.detected).reshape(batch.n, batch.n_steps)
    vl = lead_speeds(p)
    rows = []
    print("\n step  gap m  speed  pend | log10 V grid  exact [upper] | log odds shift grid  exact (nats)   s")
    for k in range(batch.n):
        crash = int(np.argmax(gaps[k] < p.crash_gap_m)) if (gaps[k] < p.crash_gap_m).any() else p.n_steps
        window = [t for t in range(grid.first_step, crash) if gaps[k, t] < p.braking_distance_m]
        if not window:
            continue
        t = int(rng.choice(window))
        g, v, i, b = (np.array([p.gap0_m]), np.array([p.ego_speed0_mps]), np.zeros(1), np.zeros(1, dtype=bool))
        for u in range(t):
            g, v, i, b = braking_step(p, float(vl[u]), g, v, i, b, detected[k, u : u + 1])
        state = BrakingStart(t, float(g[0]), float(v[0]), float(i[0]), bool(b[0]))
        t1 = time.perf_counter()
        guess = float(grid.log_value(t, g, v, b)[0])
        exact, upper = exact_log_v(logit, p, bound, state, guess)
        s_det, s_miss = successors(p, state)
        g_det, g_miss, _ = grid.next_log_values(t, g, v, i, b)
        e_det = exact_log_v(logit, p, bound, s_det, float(g_det[0]))[0]
        e_miss = exact_log_v(logit, p, bound, s_miss, float(g_miss[0]))[0]
        shift_grid, shift_exact = float(g_det[0] - g_miss[0]), e_det - e_miss
        rows.append((guess - exact, shift_grid - shift_exact))
        print(
            f" {t:4d}  {state.gap_m:5.2f}  {state.speed_mps:5.2f}  {int(state.pending):4d} | {guess / LN10:12.3f}  "
            f"{exact / LN10:6.3f} [{upper / LN10:6.3f}] | {shift_grid:19.2f}  {shift_exact:6.2f}  "
            f"{time.perf_counter() - t1:6.1f}"
        )
    err = np.array([r[0] for r in rows]) / LN10
    shift = np.array([r[1] for r in rows])
    ok = np.isfinite(err) & np.isfinite(shift)
    e_ok, s_ok = err[ok], shift[ok]
    print(
        f"\ngrid over exact, {ok.sum()} states: log10 V median {np.median(e_ok):+.2f}, RMS "
        f"{np.sqrt(np.mean(e_ok**2)):.2f}, largest {np.abs(e_ok).max():.2f}; log odds shift error median "
        f"{np.median(s_ok):+.2f} nats, RMS {np.sqrt(np.mean(s_ok**2)):.2f}, largest {np.abs(s_ok).max():.2f}"
    )

    estimates, look_ahead = [], 0
    for run in range(seeds):
        tilt = BrakingTilt(p, logit, PEMDetector(pem))
        tilt.committor = grid
        b, steps = tilt.draw(1000, np.random.default_rng(run))
        look_ahead += steps
        fail = (b.observations[..., 0] < p.crash_gap_m).any(axis=1)
        lw = np.where(fail, (b.log_p - b.log_q).sum(axis=1), -np.inf)
        estimates.append(np.exp(logsumexp(lw) - np.log(b.n) - log_p))
    e = np.array(estimates)
    relvar = float(e.var(ddof=1))
    reused = 1000 + look_ahead / seeds / p.n_steps
    first = reused + grid.steps / p.n_steps
    print(
        f"tilt, {seeds} seeds of 1,000 rollouts: mean x{e.mean():.3f}, relvar {relvar:.5f} (per rollout "
        f"{relvar * 1000:.2f}); relvar x simulations {relvar * first:.2f} solving the committor ({first:,.0f} "
        f"rollout-equivalents a run), {relvar * reused:.2f} reusing it ({reused:,.0f})"
    )
    return {
        "log10_v_median": float(np.median(e_ok)),
        "log10_v_rms": float(np.sqrt(np.mean(e_ok**2))),
        "shift_rms": float(np.sqrt(np.mean(s_ok**2))),
        "mean": float(e.mean()),
        "relvar_sims_solving": relvar * first,
        "relvar_sims_reusing": relvar * reused,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--states", type=int, default=12, help="states drawn from the tilt's rollouts")
    ap.add_argument("--seeds", type=int, default=100, help="tilted runs of 1,000 rollouts for the relative variance")
    ap.add_argument("--seed", type=int, default=0, help="the seed of the rollouts the states come from")
    args = ap.parse_args()
    study(args.states, args.seeds, args.seed)


if __name__ == "__main__":
    main()
