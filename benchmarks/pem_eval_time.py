"""Benchmark: wall and CPU time of the full ``pemviz pem eval`` protocol (budget: 15 min on 2 cores).

Runs the 5-fold cross-validation of every model (ML-NN 300 epochs, LR, Guess-mu, B-NN 2000 SVI steps and
800 samples, 300 boosted trees) without writing files, and prints per-model fit times and the ratio of the
wall time to the 900 s budget (below 1 is within budget). Every model trains on one thread, so on a busy
machine compare the CPU time, which other processes do not inflate.

    python benchmarks/pem_eval_time.py            # full protocol
    python benchmarks/pem_eval_time.py --quick    # the CI size (fold 0, small models)
"""

from __future__ import annotations

import argparse
import time

from pemviz.io.data import load_salient_data
from pemviz.studies.pem_eval import EvalConfig, evaluate_pems, summary_lines

BUDGET_S = 900.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fold 0, 20 epochs, 60 trees, 200 SVI steps")
    args = parser.parse_args()
    config = (
        EvalConfig(folds=(0,), mlnn_epochs=20, gbt_trees=60, bnn_steps=200, bnn_samples=100)
        if args.quick
        else EvalConfig()
    )
    data = load_salient_data()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    result = evaluate_pems(data.inputs, data.labels, config)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    print("\n".join(summary_lines(result)))
    for m in result.models:
        print(f"{m.name:9s} fit {sum(f.fit_s for f in m.folds):7.1f} s over {len(m.folds)} fold(s)")
    print(f"wall {wall:.0f} s, CPU {cpu:.0f} s; ratio of wall to the {BUDGET_S:.0f} s budget {wall / BUDGET_S:.2f}")


if __name__ == "__main__":
    main()
