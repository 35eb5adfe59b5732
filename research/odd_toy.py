"""The toy over an ODD whose p(theta) spans 9 orders of magnitude, against its closed form (one-off study; figures in
docs/odd.md): ``--param total=16 --param safe=3 --param "braking~choice(5, 6, ..., 14)"``, p(b) =
1e-3 ... 1e-12, p_ODD their mean (:func:`pemviz.scenarios.toy.odd.toy_odd_log_failure_probability`). ``--seeds`` runs of
the default command (the default sampler at ``--budget`` times its default rollouts a stage); for each, the estimate
against p_ODD and each of the map's ten points (p(failure | braking = b), its interval or lower bound) against p(b).

Usage::

    python research/odd_toy.py --seeds 20 --budget 1
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

VALUES = tuple(range(5, 15))
PARAMS = (("total", 16), ("safe", 3), ("braking", "~choice(" + ", ".join(map(str, VALUES)) + ")"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--budget", type=float, default=1.0, help="rollouts a stage, times the default's")
    args = ap.parse_args()
    from pemviz.config import ExperimentConfig
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.registry import problem_for
    from pemviz.scenarios.toy.simulator import ToyParams, toy_log_failure_probability

    base = ToyParams(total=16, braking=5, safe=3)
    exact_b = {b: toy_log_failure_probability(dataclasses.replace(base, braking=b)) for b in VALUES}
    cfg0 = ExperimentConfig.of(scenario="toy", scenario_params=PARAMS)
    cfg0 = dataclasses.replace(cfg0, n_per_stage=int(round(cfg0.n_per_stage * args.budget)))
    problem = problem_for(cfg0)
    exact = problem.exact_log_p
    print(
        f"p_ODD = {math.exp(exact):.4e} (closed form); p(b) from {math.exp(max(exact_b.values())):.0e} to "
        f"{math.exp(min(exact_b.values())):.0e}; N = {cfg0.n_per_stage} a stage",
        flush=True,
    )
    from research.odd_tally import Tally

    tally = Tally(exact)
    for seed in range(args.seeds):
        done = Experiment(dataclasses.replace(cfg0, seed=seed), problem=problem).run()
        line = tally.add(done.final.estimate)
        m = done.final.odd_map
        held = sum(tally.add_point(b.estimate, exact_b[int(round((b.lo + b.hi) / 2))]) for b in m.bins)
        print(
            f"  seed {seed}: {line}; map {held}/{len(m.bins)} points hold p(b) ({done.final.n_simulations:,} "
            "simulations)",
            flush=True,
        )
    print(f"{tally.summary()}; {tally.points_text()} (against their closed form)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
