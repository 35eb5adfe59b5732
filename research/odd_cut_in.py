"""The cut-in over an ODD of its start gap, ``cut_in_gap_m~uniform(19.5, 21.5)``: the default command's runs (plain
Monte Carlo of 100,000 rollouts over an ODD) against a plain Monte Carlo reference ten times larger (one-off study;
figures in docs/odd.md).

The reference (made once, about 5 min on 2 cores)::

    pemviz run --scenario cut-in --param "cut_in_gap_m~uniform(19.5, 21.5)" --method mc --n 1000000 --seed 1000 \\
        --no-record --json ref.json

Usage::

    python research/odd_cut_in.py --reference ref.json --seeds 10
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ODD_PARAM = ("cut_in_gap_m", "~uniform(19.5, 21.5)")
REFERENCE = (4565, 1_000_000)
"""Failures and rollouts of the reference above (seed 1000): p_ODD 4.565e-3 [4.43e-3, 4.70e-3]."""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reference", type=Path, help="the reference run's --json document (default: the figures above)")
    ap.add_argument("--seeds", type=int, default=10)
    args = ap.parse_args()
    from pemviz.config import ExperimentConfig, scene_defaults
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.registry import problem_for

    failures, n = REFERENCE
    if args.reference is not None:
        doc = json.loads(args.reference.read_text())
        doc = doc[-1] if isinstance(doc, list) else doc
        failures, n = int(doc["estimate"]["n_failures"]), int(doc["estimate"]["n"])
    ref = failures / n
    print(f"reference p_ODD = {ref:.4e} ({failures:,} failures of {n:,} rollouts)", flush=True)
    settings = scene_defaults("cut-in", (ODD_PARAM,))
    cfg0 = ExperimentConfig.of(scenario="cut-in", scenario_params=(ODD_PARAM,), **settings)
    problem = problem_for(cfg0)
    ratios, holds, reliable_off, rollouts = [], 0, 0, 0
    for seed in range(args.seeds):
        done = Experiment(ExperimentConfig.of(**{**cfg0.__dict__, "seed": seed}), problem=problem).run()
        e = done.final.estimate
        r = math.exp(e.log_mu_hat) / ref
        lo, hi = e.shown_log_ci
        holds += lo <= math.log(ref) <= hi
        reliable_off += e.verdict == "reliable" and not 0.5 < r < 2
        ratios.append(r)
        rollouts = done.final.n_simulations
        print(
            f"  seed {seed}: {math.exp(e.log_mu_hat):.4e} x{r:.3f} {e.verdict} {e.interval_text()} "
            f"({rollouts:,} rollouts, {done.final.wall_s:.0f} s)",
            flush=True,
        )
    x = np.array(ratios)
    print(
        f"{settings}: median relative error {np.median(np.abs(x - 1)):.3f}, within x2 "
        f"{np.sum((x > 0.5) & (x < 2))}/{x.size}, intervals holding {holds}/{x.size}, reliable outside x2 "
        f"{reliable_off}, rollouts a run / the reference's {rollouts / n:.2f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
