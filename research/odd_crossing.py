"""The crossing over an ODD of its AEB's trigger, ``brake_ttc_s~uniform(1.3, 1.5)`` (p from 2.98e-4 at 1.3 s to 1.29e-4
at 1.5 s): the default command's runs (plain Monte Carlo of 200,000 rollouts over an ODD) against a plain Monte Carlo
reference of independent seeds (one-off study; figures in docs/odd.md).

The reference (about 97 s a million rollouts), its seeds apart from the study's::

    pemviz run --scenario crossing --param "brake_ttc_s~uniform(1.3, 1.5)" --method mc --n 1000000 --seed 1000 \\
        --no-record --json ref1000.json      # and --seed 1001, ...

Usage::

    python research/odd_crossing.py --reference ref1000.json --seeds 10
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ODD_PARAM = ("brake_ttc_s", "~uniform(1.3, 1.5)")
REFERENCE = (179, 1_000_000)
"""Failures and rollouts of the reference above (seed 1000; 96.6 s wall at load 4-6 on 2 cores): p_ODD 1.79e-4
[1.54e-4, 2.07e-4]."""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reference", type=Path, nargs="*", help="the reference runs' --json documents (default: above)")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first-seed", type=int, default=0)
    args = ap.parse_args()
    from pemviz.config import ExperimentConfig, scene_defaults
    from pemviz.core.confidence import clopper_pearson
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.registry import problem_for
    from research.odd_tally import Tally

    failures, n = REFERENCE
    if args.reference:
        failures, n = 0, 0
        for path in args.reference:
            doc = json.loads(path.read_text())
            doc = doc[-1] if isinstance(doc, list) else doc
            failures, n = failures + int(doc["estimate"]["n_failures"]), n + int(doc["estimate"]["n"])
    lo, hi = clopper_pearson(failures, n)
    print(f"reference p_ODD = {failures / n:.4e} [{lo:.3e}, {hi:.3e}] ({failures:,} failures of {n:,} rollouts)")
    settings = scene_defaults("crossing", (ODD_PARAM,))
    cfg0 = ExperimentConfig.of(scenario="crossing", scenario_params=(ODD_PARAM,), **settings)
    problem = problem_for(cfg0)
    tally = Tally(math.log(failures / n))
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        done = Experiment(cfg0.replace(seed=seed), problem=problem).run()
        line = tally.add(done.final.estimate)
        print(f"  seed {seed}: {line} ({done.final.n_simulations:,} rollouts, {done.final.wall_s:.0f} s)", flush=True)
    print(f"{settings}: {tally.summary()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
