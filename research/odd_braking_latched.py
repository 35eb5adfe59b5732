"""Braking with the latched brake over an ODD of its start gap and speed, where p(theta) spans 13 orders of magnitude,
against a quadrature of exact answers (one-off study; figures in docs/odd.md).

With the brake latched, the first effective detection decides a rollout, so p(theta) is exact at every start
(:func:`pemviz.scenarios.braking.truth_latched.latched_log_failure_probability`, about 5 ms), unlike the enumeration of
the main scenario, which refuses starts where the lead still moves once the ego is inside its braking distance.
p_ODD = the mean of p over the ODD, by the midpoint rule on an n x n grid (checked against the n/2 grid). Then
``--seeds`` runs of the default sampler at ``--budget`` times its rollouts (of each CE stage and the final batch):

    pemviz run --param latched_brake=true --param "gap0_m~uniform(18.5, 19.5)" \\
        --param "ego_speed0_mps~uniform(12.8, 13)"

Usage (the grid's log p cached in ``--cache``, about 9 minutes at 320)::

    python research/odd_braking_latched.py --grid 320 --cache latched320.npy --seeds 20 --budget 1
    python research/odd_braking_latched.py --grid 4000 --gap 18 20 --speed 13 13 --seeds 20   # the gap alone
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

GAP = (18.5, 19.5)
SPEED = (12.8, 13.0)


def quadrature(n: int, gap: tuple[float, float] = GAP, speed: tuple[float, float] = SPEED) -> tuple[float, np.ndarray]:
    """log p_ODD (nats) by the midpoint rule on an n x n grid, and log p on the grid [speed, gap]."""
    from pemviz.pem import load_pem
    from pemviz.scenarios.braking.simulator import BrakingParams
    from pemviz.scenarios.braking.truth_latched import latched_log_failure_probability
    from scipy.special import logsumexp

    pem = load_pem()
    gaps = gap[0] + (np.arange(n) + 0.5) * (gap[1] - gap[0]) / n
    speeds = speed[0] + (np.arange(n if speed[1] > speed[0] else 1) + 0.5) * (speed[1] - speed[0]) / n
    log_p = np.array(
        [
            [
                latched_log_failure_probability(
                    pem.logit_at_gap, BrakingParams(gap0_m=float(g), ego_speed0_mps=float(v), latched_brake=True)
                ).log_p_fail
                for g in gaps
            ]
            for v in speeds
        ]
    )
    return float(logsumexp(log_p) - math.log(log_p.size)), log_p


def main() -> int:
    from scipy.special import logsumexp

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--grid", type=int, default=160)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument(
        "--budget",
        type=float,
        default=1.0,
        help="rollouts of each CE stage and of the final batch, times the default's",
    )
    ap.add_argument("--gap", type=float, nargs=2, default=GAP, help="the start gap's uniform range, metres")
    ap.add_argument(
        "--speed", type=float, nargs=2, default=SPEED, help="the ego's start speed's range, m/s (a b with a = b: fixed)"
    )
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--cache", help="a .npy file holding the grid's log p (written when absent)")
    args = ap.parse_args()
    gap, speed = tuple(args.gap), tuple(args.speed)
    t0 = time.perf_counter()
    cache = Path(args.cache) if args.cache else None
    if cache is not None and cache.exists():  # the grid's log p, computed before (5 ms a point)
        log_p = np.load(cache)
        exact = float(logsumexp(log_p) - math.log(log_p.size))
    else:
        exact, log_p = quadrature(args.grid, gap, speed)
        if cache is not None:
            np.save(cache, log_p)
    half = quadrature(args.grid // 2, gap, speed)[0] if cache is None else math.nan  # the cache's was checked
    print(
        f"p_ODD = {math.exp(exact):.4e} ({log_p.size} midpoints; {math.exp(half):.4e} on {log_p.size // 4 or 1}"
        f"{'' if log_p.shape[0] > 1 else ' x 2'}); p(theta) from {math.exp(log_p.min()):.1e} to "
        f"{math.exp(log_p.max()):.1e} ({time.perf_counter() - t0:.0f} s)",
        flush=True,
    )
    from pemviz.config import ExperimentConfig
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.registry import problem_for

    params = (
        ("latched_brake", True),
        ("gap0_m", f"~uniform({gap[0]:g}, {gap[1]:g})"),
        ("ego_speed0_mps", f"~uniform({speed[0]:g}, {speed[1]:g})" if speed[1] > speed[0] else speed[0]),
    )
    cfg0 = ExperimentConfig.of(scenario_params=params)
    cfg0 = cfg0.replace(
        n_per_stage=int(round(cfg0.n_per_stage * args.budget)),
        n_final=int(round(cfg0.adaptive.n_final * args.budget)),
    )
    problem = problem_for(cfg0)
    n = args.grid
    axes = {
        "gap0_m": (gap[0] + (np.arange(n) + 0.5) * (gap[1] - gap[0]) / n, 1),
        "ego_speed0_mps": (speed[0] + (np.arange(n) + 0.5) * (speed[1] - speed[0]) / n, 0),
    }

    def exact_bin(name: str, lo: float, hi: float) -> float:
        """log p(failure | parameter in [lo, hi)) by the midpoints inside the bin."""
        from scipy.special import logsumexp

        points, axis = axes[name]
        inside = (points >= lo) & (points < hi)
        part = log_p[:, inside] if axis == 1 else log_p[inside, :]
        return float(logsumexp(part) - math.log(part.size))

    from research.odd_tally import Tally

    tally = Tally(exact)
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        t1 = time.perf_counter()
        final = Experiment(dataclasses.replace(cfg0, seed=seed), problem=problem).run().final
        line = tally.add(final.estimate)
        held = sum(tally.add_point(b.estimate, exact_bin(b.name, b.lo, b.hi)) for b in final.odd_map.bins)
        print(
            f"  seed {seed}: {line}; map {held}/{len(final.odd_map.bins)} points hold ({final.n_simulations:,} "
            f"simulations, {time.perf_counter() - t1:.0f} s)",
            flush=True,
        )
    print(f"budget x{args.budget:g}: {tally.summary()}; {tally.points_text()} (against their quadrature)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
