"""The default command of a scenario (``pemviz run --scenario NAME --seed S``, no other flag) over many seeds, against
the scenario's exact answer or plain Monte Carlo reference: the study behind the cut-in's default (the tilted
proposal, :mod:`pemviz.scenarios.cut_in.tilt`) and its acceptance.

Each seed runs what the command runs (its settings parsed by the command's own parser, the same engine and estimator;
no recording), and prints its estimate, 95 % interval, whether that holds the answer, ESS, k-hat, verdict, its
simulations (rollout-equivalents: the tilt's look-aheads and solve counted) and its wall time. The summary gives the
median and RMS relative error, the runs within x2, the intervals holding the answer, the ``reliable`` verdicts whose
estimate is off by more than x2 (a verdict that claims too much) or whose interval misses the answer, and nan; then
the seeds' spread against the intervals they give, the work-normalised relative variance (relvar x simulations), and
for the failures' importance weights, how far they are from a zero-variance proposal's (all equal to p).

- ``--flags '...'`` adds flags to the command (``--flags '--method tilt --n 7280'`` on ``--scenario cut-in-rare``).
- ``--against '...'`` runs the command with other flags on the same seeds too and says how the two agree
  (``--flags '--method tilt --n 7280' --against '--method ams --ams-score committor --n 1000 --ams-killed 100'``:
  the cut-in's tilt against splitting scored by the same committor).
- ``--mc-reference N`` compares with a plain Monte Carlo reference of N rollouts drawn first (a setting without one).
- ``--toy``: the tilted estimator on the toy braking model with a deliberately poor committor
  (:mod:`pemviz.scenarios.toy.tilt`) against its exact answer 1e-3, ``--toy-seeds`` seeds of ``--toy-n`` rollouts.
- ``--heaviest SEED N K``: the cut-in's tilt on N rollouts of SEED, its K heaviest failures step by step.
- ``--acceptance``: every target the committor tilt was built against, measured (the default cut-in command on 20
  seeds and its wall time, the tilt and splitting at the rare setting on 10, braking's default on 200, braking's grid
  committor against the exact one, the authors'-settings preset's seed 0, the toy), then a table of the targets, each
  with its figure and whether it is met; exit 1 while one is not (about 33 min on 2 cores, ``--jobs`` parts at a time).

Measured (2-core developer machine; cut-in reference then 8.66e-5 [8.09e-5, 9.26e-5]; now 7.95e-5):

- see docs/validation.md, docs/cut-in.md and research/cut-in-notes.md for every run.

Usage::

    python benchmarks/default_runs.py --scenario cut-in --seeds 20
    python benchmarks/default_runs.py --scenario cut-in --seeds 20 --first-seed 20
    python benchmarks/default_runs.py --scenario braking --seeds 200
    python benchmarks/default_runs.py --scenario cut-in-rare --seeds 10 --flags '--method tilt --n 7280' \\
        --against '--method ams --ams-score committor --n 1000 --ams-killed 100'
    python benchmarks/default_runs.py --scenario cut-in --seeds 5 --flags '--param cut_in_gap_m=19.5' \\
        --mc-reference 200000
    python benchmarks/default_runs.py --toy --toy-seeds 200
    python benchmarks/default_runs.py --heaviest 7 4000 8
    python benchmarks/default_runs.py --acceptance
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def default_config(scenario: str, seed: int, flags: tuple[str, ...] = ()):  # noqa: ANN201 (an ExperimentConfig)
    """The settings of ``pemviz run --scenario SCENARIO --seed SEED [FLAGS]``, parsed by the command's own parser."""
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args

    argv = ["run", "--scenario", scenario, "--seed", str(seed), *flags]
    return config_from_args(build_parser("run").parse_args(argv))


def summary(ratios: np.ndarray, holds: np.ndarray, verdicts: list[str], logs: np.ndarray) -> str:
    """The seeds' summary line (``ratios``: estimate / answer; ``holds``: the interval holds the answer): a
    ``reliable`` verdict beyond x2 is a wrong claim; one whose 95 % interval misses the answer is counted apart (such
    intervals miss 1 run in 20 by design)."""
    rel = np.abs(ratios - 1.0)
    off = (ratios < 0.5) | (ratios > 2.0)
    reliable = np.array([v == "reliable" for v in verdicts])
    return (
        f"median relative error {np.median(rel):.3f}, RMS {np.sqrt(np.mean(rel ** 2)):.3f}, mean x"
        f"{np.mean(ratios):.3f}; within x2 in {int(np.sum(~off))} of {ratios.size}; intervals holding the answer "
        f"{int(np.sum(holds))} of {ratios.size} ({np.mean(holds):.1%}); verdicts "
        + ", ".join(f"{verdicts.count(v)} {v}" for v in dict.fromkeys(verdicts))
        + f"; 'reliable' beyond x2: {int(np.sum(reliable & off))}, 'reliable' with the answer outside its interval: "
        f"{int(np.sum(reliable & ~holds))}; nan: {int(np.sum(np.isnan(logs)))}"
    )


def relative_variance(logs: np.ndarray) -> float:
    """The runs' relative variance Var(p_hat) / E(p_hat)^2 from their log estimates [R] (nats; -inf for 0), R >= 2."""
    p = np.exp(logs)
    return float(np.var(p, ddof=1) / np.mean(p) ** 2)


def log_gap(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """The difference of two sets of runs' mean log estimates (nats; [Ra], [Rb], finite) and its standard error from
    the runs' spread (nan with fewer than two runs in a set)."""
    se = math.sqrt(a.var(ddof=1) / a.size + b.var(ddof=1) / b.size) if min(a.size, b.size) > 1 else math.nan
    return float(a.mean() - b.mean()), se


def spread(logs: np.ndarray, half_widths: np.ndarray, sims: np.ndarray) -> str:
    """How the seeds' spread compares with the intervals they give: the standard deviation of the log estimates
    against the mean 95 % half-width in logs over 1.96, and the work-normalised relative variance (the estimates'
    relative variance times the mean simulations a run; 1 / p - 1 for plain Monte Carlo, 0 at zero variance)."""
    if logs.size < 2:
        return "spread of the seeds: one run"
    p = np.exp(logs)
    none = int(np.sum(p == 0.0))
    if none == logs.size:
        return f"spread of the seeds: no run saw a failure ({logs.size} runs, {np.mean(sims):,.0f} simulations a run)"
    relvar = relative_variance(logs)
    if none:
        return (
            f"spread of the seeds: {none} of {logs.size} runs saw no failure, so the logs' spread and the lower "
            f"bound are not defined; relvar x simulations {relvar * float(np.mean(sims)):.3g} (relvar "
            f"{relvar:.3g}, {np.mean(sims):,.0f} simulations a run)"
        )
    from pemviz.core.confidence import markov_lower_bound

    bound = markov_lower_bound(logs)
    return (
        f"spread of the seeds: sd of the log estimates {np.std(logs, ddof=1):.3f} against the intervals' mean "
        f"half-width in logs / 1.96 = {np.mean(half_widths) / 1.96:.3f}; relvar x simulations "
        f"{relvar * float(np.mean(sims)):.3g} (relvar {relvar:.3g}, {np.mean(sims):,.0f} simulations a run; "
        f"{logs.size} runs); geometric mean {math.exp(np.mean(logs)):.3g}, so p >= {math.exp(bound):.3g} at 95 % "
        f"(Markov's inequality on the product of the runs, which needs only their unbiasedness)"
    )


def weight_profile(log_weights: list[np.ndarray], truth: float) -> str:
    """Where the seeds' estimates come from: the failures' importance log-weights (nats, one array a run) against the
    answer's log ``truth``. A zero-variance proposal gives every failure the weight p, so the spread says how far the
    proposal is from it: the failures it over-draws weigh far below p, those it under-draws far above."""
    runs = [lw for lw in log_weights if lw.size]
    if not runs:
        return "failures' weights: no failure"
    heaviest = [np.sort(np.exp(lw - lw.max()))[::-1] for lw in runs]  # each run's weights, largest first
    top1 = np.mean([w[: max(1, w.size // 100)].sum() / w.sum() for w in heaviest])
    lw = np.concatenate(runs) - truth
    w = np.exp(lw - lw.max())
    low, high = lw < -math.log(1000.0), lw > 0
    return (
        f"failures' weights over p (zero variance: all 1), {len(runs)} runs pooled: quantiles 10/50/90 % "
        f"{', '.join(f'{math.exp(q):.2g}' for q in np.quantile(lw, [0.1, 0.5, 0.9]))}; below p / 1000: "
        f"{low.mean():.0%} of the failures, carrying {w[low].sum() / w.sum():.2%} of the estimates; above p: "
        f"{high.mean():.1%}, carrying {w[high].sum() / w.sum():.0%}; the heaviest 1 % of a run's failures carry "
        f"{top1:.0%} of its estimate (mean over the runs)"
    )


def mc_reference(cfg, problem, n: int) -> tuple[float, str]:  # noqa: ANN001 (an ExperimentConfig, a Problem)
    """A plain Monte Carlo reference of ``problem`` (the run's scene and parameters): log p (nats; nan without a
    failure) of ``n`` rollouts of the PEMs (seed 12345), and its text with the Clopper-Pearson interval."""
    from pemviz.engine.experiment import Experiment

    e = Experiment(cfg.replace(method="mc", n_per_stage=n, seed=12345), problem=problem).run().final.estimate
    text = f"plain Monte Carlo reference {e.mu_hat:.4g} {e.interval_text()} ({e.n_failures} failures in {n:,} rollouts)"
    return (e.log_mu_hat if e.n_failures else math.nan), text


def scenario_runs(scenario: str, seeds: range, flags: tuple[str, ...] = (), mc: int = 0) -> dict[str, Any]:
    """The default command of ``scenario`` at each seed (module docstring), with ``flags`` added, against the scene's
    exact answer or reference, or with ``mc`` > 0 a plain Monte Carlo reference of ``mc`` rollouts drawn here; without
    any, the seeds' spread only. Returns the runs: ``truth`` (log p, nats; nan without one), and one entry a seed in
    ``logs`` (log estimates, nats), ``cis`` (log 95 % intervals), ``ratios`` (estimate / answer), ``holds``,
    ``verdicts``, ``sims`` (rollout-equivalents) and ``walls`` (seconds in the engine)."""
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.problems import problem_for

    ratios, holds, verdicts, logs, halves, sims, weights, cis, walls = [], [], [], [], [], [], [], [], []
    problem, truth = None, math.nan
    for seed in seeds:
        cfg = default_config(scenario, seed, flags)
        if problem is None:
            sys.path.insert(0, str(Path(__file__).resolve().parent))
            from braking_committor import with_braking_tilt  # braking's tilt: research/braking_tilt.py

            problem = with_braking_tilt(problem_for(cfg), cfg)
            if mc:
                truth, what = mc_reference(cfg, problem, mc)
            elif problem.exact_log_p is not None:
                truth, what = problem.exact_log_p, f"exact answer {math.exp(problem.exact_log_p):.4g}"
            elif problem.reference is not None:
                truth, what = problem.reference.log_p, f"reference {math.exp(problem.reference.log_p):.4g}"
            else:
                what = "no exact answer or reference"
            command = " ".join(["pemviz run --scenario", scenario, *flags])
            print(f"{command}: method {cfg.method}, N {cfg.n_per_stage}; {what}", flush=True)
        t0 = time.perf_counter()
        final = Experiment(cfg, problem=problem).run().final
        wall = time.perf_counter() - t0
        e = final.estimate
        ratios.append(math.exp(e.log_mu_hat - truth))
        holds.append(e.covers(truth))
        verdicts.append(e.verdict)
        logs.append(e.log_mu_hat)
        halves.append(0.5 * (e.log_ci[1] - e.log_ci[0]))
        cis.append(e.log_ci)
        sims.append(final.n_simulations)
        walls.append(wall)
        if final.failures is not None:
            weights.append(final.failures.log_weight)
        against = "" if math.isnan(truth) else f" x{ratios[-1]:.3f} ({'holds' if holds[-1] else 'misses'} it)"
        print(
            f"  seed {seed}: {math.exp(e.log_mu_hat):.3e} {e.interval_text()}{against}, {e.n_failures} failures, "
            f"ESS {e.ess:.1f}, k-hat {e.khat:.2f}, {e.verdict}; {final.n_simulations:,} simulations, {wall:.1f} s",
            flush=True,
        )
    if not math.isnan(truth):
        print(summary(np.array(ratios), np.array(holds), verdicts, np.array(logs)))
    print(spread(np.array(logs), np.array(halves), np.array(sims)))
    if weights and not math.isnan(truth):
        print(weight_profile(weights, truth))
    return {
        "truth": truth,
        "logs": np.array(logs),
        "cis": cis,
        "ratios": np.array(ratios),
        "holds": np.array(holds),
        "verdicts": verdicts,
        "sims": np.array(sims),
        "walls": np.array(walls),
    }


def overlaps(a: dict[str, Any], b: dict[str, Any]) -> int:
    """How many seeds' 95 % intervals of two estimators' runs (:func:`scenario_runs`) overlap."""
    return sum(max(x[0], y[0]) <= min(x[1], y[1]) for x, y in zip(a["cis"], b["cis"], strict=False))


def agreement(a: dict[str, Any], b: dict[str, Any]) -> str:
    """How two estimators' runs on the same seeds (:func:`scenario_runs`) agree: the seeds whose two intervals
    overlap, and the ratio of their geometric means with the standard error of its log from the seeds' spread."""
    la, lb = a["logs"], b["logs"]
    overlap = overlaps(a, b)
    none = [int(np.sum(~np.isfinite(x))) for x in (la, lb)]
    if any(none):
        return (
            f"agreement over {la.size} seeds: the two intervals overlap in {overlap}; runs without a failure: "
            f"{none[0]} and {none[1]}, so the geometric means cannot be compared"
        )
    diff, se = log_gap(la, lb)
    return (
        f"agreement over {la.size} seeds: the two intervals overlap in {overlap}; geometric means "
        f"{math.exp(la.mean()):.3g} and {math.exp(lb.mean()):.3g}, ratio x{math.exp(diff):.2f} (log ratio "
        f"{diff:+.2f} nats, standard error {se:.2f} from the seeds' spread: {abs(diff) / se:.1f} SE)"
    )


def heaviest_failures(seed: int, n: int, k: int) -> None:
    """The cut-in's tilted proposal (its default settings) on ``n`` rollouts of ``seed``: the ``k`` failures of the
    largest importance weight, each tilted step off the central class (or whose log p / q is beyond +-1 nats) with its
    class, log p / q, log Q of the class drawn and log V = log sum_c p(c) Q(c) of the state (nats). Under a
    zero-variance proposal each step's log p / q is log V - log Q, and every failure's log weight log p."""
    from pemviz.core import exact
    from pemviz.pem import load_pem
    from pemviz.scenarios.cut_in.problem import cut_in_params, cut_in_problem
    from pemviz.scenarios.cut_in.scenario import MONTE_CARLO_REFERENCE
    from pemviz.scenarios.cut_in.tilt import CutInTilt

    class Traced(CutInTilt):
        def branch_log_q(self, sim, t, idx, u, rows, prefix_min, sfeat, p0):  # noqa: ANN001, ANN202
            self.last = super().branch_log_q(sim, t, idx, u, rows, prefix_min, sfeat, p0), p0
            return self.last[0]

        def drawn(self, t: int, idx: np.ndarray, cls: np.ndarray, pc: np.ndarray) -> None:
            lqb, p0 = self.last
            _, qc = self.grid.proposal(p0, self.beta * lqb, self.eps)
            log_q_cls, rr = self.grid.class_values(lqb), np.arange(idx.size)
            self.trace[idx, t] = np.column_stack(
                [cls, exact.log(pc[rr, cls]) - exact.log(qc[rr, cls]), log_q_cls[rr, cls], self.grid.log_value(p0, lqb)]
            )

    params = cut_in_params("moderate")
    problem = cut_in_problem(load_pem(), params)
    tilt = Traced(params, problem.target)
    tilt.solve()
    tilt.trace = np.full((n, params.n_steps, 4), np.nan)
    batch, log_w, _ = tilt.stage(n, np.random.default_rng(seed))
    failed = problem.failed(batch, problem.robustness(batch, "classic"))
    failures, rollouts = MONTE_CARLO_REFERENCE["moderate"]
    nb, central = tilt.grid.nb, f"r{tilt.grid.nb // 2}l{tilt.grid.nb // 2}"
    print(
        f"seed {seed}, {n} rollouts: {int(failed.sum())} failures, mu_hat {np.mean(np.exp(log_w) * failed):.3e}; "
        f"log p of the reference {math.log(failures / rollouts):.2f}; class rIlJ: range error bin I, lateral bin J "
        f"of {nb} (central {central})"
    )
    for i in np.argsort(-np.where(failed, log_w, -np.inf))[:k]:
        steps = []
        for t in np.flatnonzero(~np.isnan(tilt.trace[i, :, 0])):
            c, lr, lq, lv = tilt.trace[i, t]
            name = "miss" if c == 0 else "r{}l{}".format(*divmod(int(c) - 1, nb))
            if name != central or abs(lr) > 1.0:
                steps.append(f"{t}:{name}({lr:+.1f}, Q {lq:.1f}, V {lv:.1f})")
        print(f"  log w {log_w[i]:.2f}: " + " ".join(steps))


def toy_runs(n_seeds: int, n: int) -> dict[str, float]:
    """The tilted estimator with a deliberately poor committor on the toy (exact p = 1e-3), ``n_seeds`` seeds; returns
    the estimates' ``mean`` over p and its standard error ``se``."""
    import dataclasses

    from pemviz.config import ExperimentConfig
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.problems import build_problem
    from pemviz.testing import ESTIMATOR_PROBLEM

    problem = build_problem(ESTIMATOR_PROBLEM)
    ests = [
        Experiment(dataclasses.replace(ExperimentConfig.of(method="tilt", seed=s), n_per_stage=n), problem=problem)
        .run()
        .final.estimate
        for s in range(n_seeds)
    ]
    ratio = np.exp(np.array([e.log_mu_hat for e in ests]) - problem.exact_log_p)
    holds = np.array([e.covers(problem.exact_log_p) for e in ests])
    se = ratio.std(ddof=1) / math.sqrt(ratio.size)
    print(
        f"toy {problem.name}, exact p {math.exp(problem.exact_log_p):.4g}, tilt with a poor committor, {n} rollouts "
        f"a seed: mean of {ratio.size} estimates x{ratio.mean():.4f} of p (standard error {se:.4f}); the relative "
        f"variance a rollout {ratio.var(ddof=1) * n:.2f} (plain Monte Carlo: 1 / p - 1 = "
        f"{1 / math.exp(problem.exact_log_p) - 1:.0f})"
    )
    print(summary(ratio, holds, [e.verdict for e in ests], np.array([e.log_mu_hat for e in ests])))
    return {"mean": float(ratio.mean()), "se": float(se)}


PAPER_PRESET_SEED0 = 5.6372e-19
"""What ``pemviz run --preset paper --seed 0`` gave on braking when the acceptance was written (a build whose runs
differed between CPUs)."""


def _part(name: str) -> tuple[str, str, Any]:
    """One part of :func:`acceptance`, run in a worker: (its name, what it printed, its numbers)."""
    import contextlib
    import io

    from pemviz.engine.resources import torch_threads

    out = io.StringIO()
    with contextlib.redirect_stdout(out), torch_threads(1, blas=1):  # one core a part: the parts run side by side
        data = ACCEPTANCE_PARTS[name]()
    return name, out.getvalue(), data


def _command_wall() -> float:
    """Seconds of ``pemviz run --scenario cut-in --seed 1`` in a fresh process, its recording written."""
    import subprocess
    import tempfile

    pemviz = [sys.executable, "-c", "from pemviz.cli import main; main()"]  # what the console script runs
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        subprocess.run(
            [*pemviz, "run", "--scenario", "cut-in", "--seed", "1", "--save", f"{tmp}/r.rrd"],
            check=True,
            capture_output=True,
        )
        return time.perf_counter() - t0


def _paper_seed0() -> float:
    """log of ``pemviz run --preset paper --seed 0``'s estimate on braking (nats)."""
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.problems import problem_for

    cfg = default_config("braking", 0, ("--preset", "paper"))
    e = Experiment(cfg, problem=problem_for(cfg)).run().final.estimate
    print(f"pemviz run --preset paper --seed 0: {math.exp(e.log_mu_hat):.5g} {e.interval_text()}, {e.verdict}")
    return e.log_mu_hat


def _braking_committor() -> dict[str, float]:
    """``benchmarks/braking_committor.py``'s study at its defaults: the grid committor against the exact one."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from braking_committor import study

    return study()


RARE_TILT, RARE_AMS = (
    ("--method", "tilt", "--n", "7280"),
    ("--method", "ams", "--ams-score", "committor", "--n", "1000", "--ams-killed", "100"),
)
ACCEPTANCE_PARTS = {
    "cut-in": lambda: scenario_runs("cut-in", range(20)),
    "rare tilt": lambda: scenario_runs("cut-in-rare", range(10), RARE_TILT),
    "rare ams 0-4": lambda: scenario_runs("cut-in-rare", range(5), RARE_AMS),
    "rare ams 5-9": lambda: scenario_runs("cut-in-rare", range(5, 10), RARE_AMS),
    "braking": lambda: scenario_runs("braking", range(200)),
    "braking committor": _braking_committor,
    "paper": _paper_seed0,
    "toy": lambda: toy_runs(200, 2000),
}
"""The acceptance's parts (:func:`acceptance`), the longest first."""


def _joined(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """Two sets of runs of :func:`scenario_runs` (one scene, one truth) as one."""
    return {
        k: a[k] + b[k] if isinstance(a[k], list) else (np.concatenate([a[k], b[k]]) if k != "truth" else a[k])
        for k in a
    }


def acceptance_rows(r: dict[str, Any]) -> list[tuple[str, str, bool | None]]:
    """Each target of the committor tilt's acceptance, its measured figure and whether it is met (None: printed
    only), from :func:`acceptance`'s parts' numbers ``r``."""
    cut, rare_t, brk, toy = r["cut-in"], r["rare tilt"], r["braking"], r["toy"]
    rare_a = _joined(r["rare ams 0-4"], r["rare ams 5-9"])
    rel, off = np.abs(cut["ratios"] - 1.0), (cut["ratios"] < 0.5) | (cut["ratios"] > 2.0)
    held = int(cut["holds"].sum())
    rows: list[tuple[str, str, bool | None]] = [
        (
            f"cut-in, default command, {rel.size} seeds: median relative error <= 0.2",
            f"{np.median(rel):.3f}",
            bool(np.median(rel) <= 0.2),
        ),
        ("  the reference inside the 95 % interval in >= 18 of 20", f"{held} of {rel.size}", held >= 0.9 * rel.size),
        (
            "  no run off by more than x2",
            f"{int(off.sum())} beyond (x{cut['ratios'].min():.2f} to " f"x{cut['ratios'].max():.2f})",
            not off.any(),
        ),
        (
            "  cost <= 13,000 rollout-equivalents (first run; a run reusing the proposal)",
            f"{int(cut['sims'][0]):,}; {int(np.median(cut['sims'][1:])):,}",
            bool(cut["sims"][0] <= 13000),
        ),
        (
            "  wall time <= 30 s (the command with its recording, a fresh process)",
            f"{r['cut-in wall']:.1f} s",
            r["cut-in wall"] <= 30.0,
        ),
    ]
    gm = "a run without a failure"
    if np.all(np.isfinite(np.concatenate([rare_t["logs"], rare_a["logs"]]))):
        diff, se = log_gap(rare_t["logs"], rare_a["logs"])
        gm = f"geometric means x{math.exp(diff):.2f} apart ({abs(diff) / se:.1f} SE)"
    ov = overlaps(rare_t, rare_a)
    n_rare = rare_t["logs"].size
    rows.append(
        (
            f"cut-in rare, tilt and splitting, {n_rare} seeds: every seed's two intervals overlap",
            f"{ov} of {n_rare}; {gm}",
            ov == n_rare,
        )
    )
    for name, runs in (("tilt", rare_t), ("splitting", rare_a)):
        sd = float(np.std(runs["logs"], ddof=1))
        half = float(np.mean([(hi - lo) / 2 for lo, hi in runs["cis"]])) / 1.96
        rows.append(
            (
                f"  {name}: the seeds' spread matches the intervals (sd of logs / interval sd in 2/3..3/2)",
                f"{sd:.2f} / {half:.2f}",
                bool(2 / 3 <= sd / half <= 1.5),
            )
        )
    b_rel = np.abs(brk["ratios"] - 1.0)
    b_held = int(brk["holds"].sum())
    relvar_sims = relative_variance(brk["logs"]) * float(np.mean(brk["sims"]))
    bc = r["braking committor"]
    paper = math.exp(r["paper"])
    rows += [
        (
            f"braking, default command, {b_rel.size} seeds: median relative error <= 0.021",
            f"{np.median(b_rel):.4f}",
            bool(np.median(b_rel) <= 0.021),
        ),
        (
            "  RMS relative error <= 0.034",
            f"{np.sqrt(np.mean(b_rel ** 2)):.4f}",
            bool(np.sqrt(np.mean(b_rel**2)) <= 0.034),
        ),
        ("  the exact answer inside the interval in >= 95 %", f"{b_held} of {b_rel.size}", b_held >= 0.95 * b_rel.size),
        ("  relvar x simulations of the default (printed)", f"{relvar_sims:.2f}", None),
        (
            "  the tilt by the grid committor: relvar x simulations <= 0.5 (goal)",
            f"{bc['relvar_sims_solving']:.2f} solving it, {bc['relvar_sims_reusing']:.2f} reusing it",
            bc["relvar_sims_solving"] <= 0.5,
        ),
        (
            "  the grid committor against the exact one (log10 V, grid less exact; log odds shift, nats)",
            f"median {bc['log10_v_median']:+.2f}, RMS {bc['log10_v_rms']:.2f}; shift RMS {bc['shift_rms']:.2f}",
            None,
        ),
        (
            f"  the authors'-settings preset, seed 0, gives {PAPER_PRESET_SEED0:.5g}",
            f"{paper:.5g}",
            abs(paper / PAPER_PRESET_SEED0 - 1.0) < 5e-5,
        ),
    ]
    runs = (cut, rare_t, brk, rare_a)
    wrong = sum(
        v == "reliable" and not 0.5 <= x <= 2.0  # the scenes with an answer to be wrong against
        for a in (cut, brk)
        for v, x in zip(a["verdicts"], a["ratios"], strict=False)
    )
    nans = int(sum(np.isnan(a["logs"]).sum() for a in runs))
    n_runs = sum(len(a["verdicts"]) for a in runs)
    rows.append(
        (
            f"every verdict honest: no 'reliable' beyond x2, no nan ({n_runs} runs)",
            f"{wrong} wrong 'reliable', {nans} nan",
            wrong == 0 and nans == 0,
        )
    )
    rows.append(
        (
            "the tilt on the toy with a poor committor is unbiased (mean within 3 standard errors of p)",
            f"x{toy['mean']:.4f} (standard error {toy['se']:.4f})",
            abs(toy["mean"] - 1.0) <= 3 * toy["se"],
        )
    )
    return [(target, figure, None if met is None else bool(met)) for target, figure, met in rows]


def acceptance(jobs: int) -> int:
    """Run every part of the committor tilt's acceptance: the default cut-in command's wall time alone, then
    :data:`ACCEPTANCE_PARTS`, ``jobs`` at a time; print each part's output, then the targets with their figures.
    Returns 0 when every target is met, else 1."""
    from concurrent.futures import ProcessPoolExecutor, as_completed

    t0 = time.perf_counter()
    results: dict[str, Any] = {"cut-in wall": _command_wall()}  # alone: the machine's cores to itself
    print(
        f"== pemviz run --scenario cut-in --seed 1 (its recording written): {results['cut-in wall']:.1f} s", flush=True
    )
    with ProcessPoolExecutor(jobs) as pool:
        for fut in as_completed([pool.submit(_part, name) for name in ACCEPTANCE_PARTS]):
            name, text, data = fut.result()
            results[name] = data
            print(f"== {name} ({time.perf_counter() - t0:.0f} s)\n{text}", flush=True)
    rows = acceptance_rows(results)
    print("\n| target | measured | met |\n|---|---|---|")
    for target, figure, met in rows:
        print(f"| {target} | {figure} | {'-' if met is None else ('yes' if met else '**no**')} |")
    return int(any(met is False for _, _, met in rows))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenario", default=None, help="run this scenario's default command (e.g. cut-in, braking)")
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--flags", default="", help="flags added to the command, e.g. '--method tilt --n 7280'")
    ap.add_argument(
        "--against",
        default=None,
        metavar="FLAGS",
        help="run the command with these flags instead on the same seeds too, and compare the two",
    )
    ap.add_argument(
        "--mc-reference",
        type=int,
        default=0,
        metavar="N",
        help="compare with a plain Monte Carlo reference of N rollouts drawn here (another setting)",
    )
    ap.add_argument(
        "--heaviest",
        type=int,
        nargs=3,
        metavar=("SEED", "N", "K"),
        help="the cut-in's tilt on N rollouts of SEED: the K heaviest failures, step by step",
    )
    ap.add_argument("--toy", action="store_true", help="the tilted estimator on the toy with a poor committor")
    ap.add_argument("--toy-seeds", type=int, default=200)
    ap.add_argument("--toy-n", type=int, default=2000)
    ap.add_argument(
        "--acceptance",
        action="store_true",
        help="every target of the committor tilt's acceptance, then a table of them (about 35 min, 2 jobs)",
    )
    ap.add_argument("--jobs", type=int, default=2, help="--acceptance: parts run at a time (at least 1)")
    args = ap.parse_args()
    if args.jobs < 1:
        ap.error(f"--jobs {args.jobs}: the parts run at a time must be at least 1")
    if args.acceptance:
        raise SystemExit(acceptance(args.jobs))
    if args.scenario is None and not args.toy and args.heaviest is None:
        raise SystemExit("give --scenario NAME, --toy, --heaviest SEED N K or --acceptance")
    if args.heaviest is not None:
        heaviest_failures(*args.heaviest)
    if args.toy:
        toy_runs(args.toy_seeds, args.toy_n)
    if args.scenario is not None:
        seeds = range(args.first_seed, args.first_seed + args.seeds)
        first = scenario_runs(args.scenario, seeds, tuple(args.flags.split()), args.mc_reference)
        if args.against is not None:
            print(agreement(first, scenario_runs(args.scenario, seeds, tuple(args.against.split()), args.mc_reference)))


if __name__ == "__main__":
    main()
