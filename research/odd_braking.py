"""The braking scenario over an ODD of its start speed: p_ODD by quadrature of exact answers against the default
sampler's runs (one-off study; figures in docs/odd.md).

p(v) = the exact failure probability of the braking scenario starting at ego speed v
(:func:`pemviz.scenarios.braking.truth.braking_truth`, 1 % bracket); p_ODD = the mean of p over v ~ uniform(lo, hi), by
the trapezoid rule on a grid of ``--grid`` points (p(v) is smooth between the grid's points: it checks the rule by the
half grid too). Then ``--seeds`` runs of ``pemviz run --param ego_speed0_mps~uniform(lo, hi)`` (the default sampler,
``--n`` rollouts a stage) against it.

Usage::

    python research/odd_braking.py --lo 9 --hi 10.45 --grid 30 --seeds 10
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def exact_curve(lo: float, hi: float, grid: int) -> tuple[np.ndarray, np.ndarray]:
    from pemviz.pem import load_pem
    from pemviz.scenarios.braking.simulator import BrakingParams
    from pemviz.scenarios.braking.truth import braking_truth

    pem = load_pem()
    v = np.linspace(lo, hi, grid)
    cache = Path("/tmp/odd_braking_truth.json")  # speed -> log p, kept between runs of this study
    known = {float(k): x for k, x in json.loads(cache.read_text()).items()} if cache.is_file() else {}
    log_p = []
    for x in v:
        key = round(float(x), 6)
        if key not in known:
            t0 = time.perf_counter()
            r = braking_truth(pem.logit_at_gap, BrakingParams(ego_speed0_mps=key), tolerance=0.01)
            known[key] = r.log_p_fail
            cache.write_text(json.dumps({str(k): x for k, x in known.items()}))
            print(f"  v = {x:.3f} m/s: p = {math.exp(r.log_p_fail):.4e} ({time.perf_counter() - t0:.1f} s)", flush=True)
        log_p.append(known[key])
    return v, np.array(log_p)


def trapezoid_mean(v: np.ndarray, log_p: np.ndarray) -> float:
    p = np.exp(log_p)
    return float(np.sum((p[1:] + p[:-1]) / 2 * np.diff(v)) / (v[-1] - v[0]))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lo", type=float, default=9.0)
    ap.add_argument("--hi", type=float, default=10.45, help="at most 10.45 m/s: above, the exact enumeration refuses")
    ap.add_argument("--grid", type=int, default=30)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--n", type=int, default=None, help="rollouts a stage (default: the default sampler's)")
    args = ap.parse_args()
    v, log_p = exact_curve(args.lo, args.hi, args.grid)
    p_odd = trapezoid_mean(v, log_p)
    half = trapezoid_mean(v[::2], log_p[::2])
    print(
        f"p_ODD = {p_odd:.4e} (trapezoid, {args.grid} points; {half:.4e} on every second point); p(v) from "
        f"{math.exp(log_p.min()):.2e} to {math.exp(log_p.max()):.2e}",
        flush=True,
    )
    from pemviz.config import ExperimentConfig
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.registry import problem_for

    params = (("ego_speed0_mps", f"~uniform({args.lo:g}, {args.hi:g})"),)
    extra = {} if args.n is None else {"n_per_stage": args.n}
    problem = problem_for(ExperimentConfig.of(scenario_params=params))
    from research.odd_tally import Tally

    tally = Tally(math.log(p_odd))
    for seed in range(args.seeds):
        done = Experiment(ExperimentConfig.of(scenario_params=params, seed=seed, **extra), problem=problem).run()
        line = tally.add(done.final.estimate)
        print(f"  seed {seed}: {line} ({done.final.n_simulations} simulations)", flush=True)
    print(tally.summary())
    return 0


if __name__ == "__main__":
    sys.exit(main())
