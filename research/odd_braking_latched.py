"""Braking with the latched brake over an ODD of its start gap and speed, where p(theta) spans 13 orders of magnitude,
against a quadrature of exact answers (one-off study; figures in the CHANGELOG and docs/odd.md).

With the brake latched, the first effective detection decides a rollout, so p(theta) is exact at every start
(:func:`pemviz.scenarios.braking.truth_latched.latched_log_failure_probability`, about 5 ms), unlike the enumeration of
the main scenario, which refuses starts where the lead still moves once the ego is inside its braking distance.
p_ODD = the mean of p over the ODD, by the midpoint rule on an n x n grid (checked against the n/2 grid). Then
``--seeds`` runs of the default sampler at ``--budget`` times its rollouts a stage:

    pemviz run --param latched_brake=true --param "gap0_m~uniform(18.5, 19.5)" \\
        --param "ego_speed0_mps~uniform(12.8, 13)"

Usage::

    python research/odd_braking_latched.py --grid 160 --seeds 10 --budget 1
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


def quadrature(n: int) -> tuple[float, np.ndarray]:
    """log p_ODD (nats) by the midpoint rule on an n x n grid, and log p on the grid [speed, gap]."""
    from scipy.special import logsumexp

    from pemviz.pem import load_pem
    from pemviz.scenarios.braking.simulator import BrakingParams
    from pemviz.scenarios.braking.truth_latched import latched_log_failure_probability

    pem = load_pem()
    gaps = GAP[0] + (np.arange(n) + 0.5) * (GAP[1] - GAP[0]) / n
    speeds = SPEED[0] + (np.arange(n) + 0.5) * (SPEED[1] - SPEED[0]) / n
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
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--grid", type=int, default=160)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--budget", type=float, default=1.0, help="rollouts a stage, times the default's")
    args = ap.parse_args()
    t0 = time.perf_counter()
    exact, log_p = quadrature(args.grid)
    half, _ = quadrature(args.grid // 2)
    print(
        f"p_ODD = {math.exp(exact):.4e} ({args.grid} x {args.grid} midpoints; {math.exp(half):.4e} on "
        f"{args.grid // 2} x {args.grid // 2}); p(theta) from {math.exp(log_p.min()):.1e} to "
        f"{math.exp(log_p.max()):.1e} ({time.perf_counter() - t0:.0f} s)",
        flush=True,
    )
    from pemviz.config import ExperimentConfig
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.registry import problem_for

    params = (
        ("latched_brake", True),
        ("gap0_m", f"~uniform({GAP[0]:g}, {GAP[1]:g})"),
        ("ego_speed0_mps", f"~uniform({SPEED[0]:g}, {SPEED[1]:g})"),
    )
    cfg0 = ExperimentConfig(scenario_params=params)
    cfg0 = dataclasses.replace(cfg0, n_per_stage=int(round(cfg0.n_per_stage * args.budget)))
    problem = problem_for(cfg0)
    ratios, holds, reliable_off = [], 0, 0
    for seed in range(args.seeds):
        e = Experiment(dataclasses.replace(cfg0, seed=seed), problem=problem).run().final.estimate
        r = math.exp(e.log_mu_hat - exact)
        lo, hi = e.shown_log_ci
        holds += lo <= exact <= hi
        reliable_off += e.verdict == "reliable" and not 0.5 < r < 2
        ratios.append(r)
        print(f"  seed {seed}: x{r:.3f} {e.verdict} {e.interval_text()}", flush=True)
    x = np.array(ratios)
    print(
        f"budget x{args.budget:g}: median relative error {np.median(np.abs(x - 1)):.3f}, within x2 "
        f"{np.sum((x > 0.5) & (x < 2))}/{x.size}, intervals or bounds holding {holds}/{x.size}, reliable outside x2 "
        f"{reliable_off}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
