"""The default command of a scenario (``pemviz run --scenario NAME --seed S``, no other flag) over many seeds, against
the scenario's exact answer or plain Monte Carlo reference: the study behind the cut-in's default (the tilted
proposal, :mod:`pemviz.scenarios.cut_in.tilt`) and its acceptance.

Each seed runs what the command runs (its settings parsed by the command's own parser, the same engine and estimator;
no recording), and prints its estimate, 95 % interval, whether that holds the answer, ESS, k-hat, verdict, its
simulations (rollout-equivalents: the tilt's look-aheads and solve counted) and its wall time. The summary gives the
median and RMS relative error, the runs within x2, the intervals holding the answer, and every ``reliable`` verdict
whose estimate is off by more than x2 or whose interval misses the answer (a verdict that claims too much), and nan.

``--toy``: the tilted estimator on the toy braking model with a deliberately poor committor
(:mod:`pemviz.scenarios.toy.tilt`) against its exact answer 1e-3, ``--toy-seeds`` seeds of ``--toy-n`` rollouts.

Measured (2-core developer machine; cut-in reference 8.66e-5 [8.09e-5, 9.26e-5]):

- see the CHANGELOG and docs/cut-in.md for every run.

Usage::

    python benchmarks/default_runs.py --scenario cut-in --seeds 20
    python benchmarks/default_runs.py --scenario cut-in --seeds 20 --first-seed 20
    python benchmarks/default_runs.py --toy --toy-seeds 200
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def default_config(scenario: str, seed: int):  # noqa: ANN201 (an ExperimentConfig)
    """The settings of ``pemviz run --scenario SCENARIO --seed SEED``, parsed by the command's own parser."""
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args

    return config_from_args(build_parser("run").parse_args(["run", "--scenario", scenario, "--seed", str(seed)]))


def summary(ratios: np.ndarray, holds: np.ndarray, verdicts: list[str], logs: np.ndarray) -> str:
    """The seeds' summary line (``ratios``: estimate / answer; ``holds``: the interval holds the answer)."""
    rel = np.abs(ratios - 1.0)
    off = (ratios < 0.5) | (ratios > 2.0)
    claims = [v == "reliable" and (o or not h) for v, o, h in zip(verdicts, off, holds)]
    return (f"median relative error {np.median(rel):.2f}, RMS {np.sqrt(np.mean(rel ** 2)):.2f}, mean x"
            f"{np.mean(ratios):.2f}; within x2 in {int(np.sum(~off))} of {ratios.size}; intervals holding the answer "
            f"{int(np.sum(holds))} of {ratios.size}; verdicts " + ", ".join(f"{verdicts.count(v)} {v}" for v in
                                                                          dict.fromkeys(verdicts)) +
            f"; 'reliable' with the answer outside its interval or beyond x2: {sum(claims)}; nan: "
            f"{int(np.sum(np.isnan(logs)))}")  # fmt: skip


def scenario_runs(scenario: str, seeds: range) -> None:
    """The default command of ``scenario`` at each seed (module docstring)."""
    from pemviz.engine import Experiment
    from pemviz.scenarios.problems import problem_for

    ratios, holds, verdicts, logs = [], [], [], []
    problem = None
    for seed in seeds:
        cfg = default_config(scenario, seed)
        if problem is None:
            problem = problem_for(cfg)
            truth = problem.exact_log_p if problem.exact_log_p is not None else problem.reference.log_p
            what = "exact answer" if problem.exact_log_p is not None else "reference"
            print(f"pemviz run --scenario {scenario}: method {cfg.method}, N {cfg.n_per_stage}; {what} "
                  f"{math.exp(truth):.4g}", flush=True)  # fmt: skip
        t0 = time.perf_counter()
        final = Experiment(cfg, problem=problem).run().final
        wall = time.perf_counter() - t0
        e = final.estimate
        ratios.append(math.exp(e.log_mu_hat - truth))
        holds.append(e.covers(truth))
        verdicts.append(e.verdict)
        logs.append(e.log_mu_hat)
        print(f"  seed {seed}: {math.exp(e.log_mu_hat):.3e} {e.interval_text()} x{ratios[-1]:.2f} "
              f"({'holds' if holds[-1] else 'misses'} the {what}), {e.n_failures} failures, ESS {e.ess:.1f}, k-hat "
              f"{e.khat:.2f}, {e.verdict}; {final.n_simulations:,} simulations, {wall:.1f} s", flush=True)  # fmt: skip
    print(summary(np.array(ratios), np.array(holds), verdicts, np.array(logs)))


def toy_runs(n_seeds: int, n: int) -> None:
    """The tilted estimator with a deliberately poor committor on the toy (exact p = 1e-3), ``n_seeds`` seeds."""
    import dataclasses

    from pemviz.config import ExperimentConfig
    from pemviz.engine import Experiment
    from pemviz.scenarios.problems import build_problem
    from pemviz.testing import ESTIMATOR_PROBLEM

    problem = build_problem(ESTIMATOR_PROBLEM)
    ests = [Experiment(dataclasses.replace(ExperimentConfig(method="tilt", seed=s), n_per_stage=n),
                       problem=problem).run().final.estimate for s in range(n_seeds)]  # fmt: skip
    ratio = np.exp(np.array([e.log_mu_hat for e in ests]) - problem.exact_log_p)
    holds = np.array([e.covers(problem.exact_log_p) for e in ests])
    se = ratio.std(ddof=1) / math.sqrt(ratio.size)
    print(f"toy {problem.name}, exact p {math.exp(problem.exact_log_p):.4g}, tilt with a poor committor, {n} rollouts "
          f"a seed: mean of {ratio.size} estimates x{ratio.mean():.4f} of p (standard error {se:.4f}); the relative "
          f"variance a rollout {ratio.var(ddof=1) * n:.2f} (plain Monte Carlo: 1 / p - 1 = "
          f"{1 / math.exp(problem.exact_log_p) - 1:.0f})")  # fmt: skip
    print(summary(ratio, holds, [e.verdict for e in ests], np.array([e.log_mu_hat for e in ests])))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default=None, help="run this scenario's default command (e.g. cut-in, braking)")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--toy", action="store_true", help="the tilted estimator on the toy with a poor committor")
    ap.add_argument("--toy-seeds", type=int, default=200)
    ap.add_argument("--toy-n", type=int, default=2000)
    args = ap.parse_args()
    if args.scenario is None and not args.toy:
        raise SystemExit("give --scenario NAME and/or --toy")
    if args.toy:
        toy_runs(args.toy_seeds, args.toy_n)
    if args.scenario is not None:
        scenario_runs(args.scenario, range(args.first_seed, args.first_seed + args.seeds))


if __name__ == "__main__":
    main()
