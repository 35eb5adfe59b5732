"""Does every claim a run prints hold? Every method on every shipped scene with a known answer, over seeds, against
the exact answer or plain Monte Carlo reference.

A run prints one of three claims about p (:attr:`pemviz.core.estimate.Estimate.shown_log_ci`):

- a 95 % interval, where the run backs one (plain Monte Carlo's exact Clopper-Pearson interval, or an
  importance-sampling or splitting estimate whose verdict is ``reliable``);
- a 95 % lower bound and no upper bound, where the weights back no interval (any other verdict): the bound holds
  whatever the weights' tail (:func:`pemviz.core.confidence.betting_lower_bound`; Markov's inequality for splitting);
- with no failure, plain Monte Carlo's rule-of-three bound p < 3 / N, or under a proposal nothing at all.

For each (scene, method) the study runs ``pemviz run --scenario SCENE --method METHOD --seed S`` at its default
budget (the scene's default command, with no ``--method``, where METHOD is the scene's default; the command's own
parser and engine, no recording) and prints, per run, the estimate, the claim and whether it holds the answer; then
the totals the claims are judged by:

- printed 95 % intervals that exclude the answer by more than x2 (the answer above twice the upper end or below half
  the lower end): goal none;
- printed lower bounds, and how many hold the answer: goal >= 95 % of them;
- ``reliable`` verdicts with the estimate outside x2 of the answer: goal none;
- nan estimates: goal none.

Usage::

    python benchmarks/honest_intervals.py                       # every scene and method, 10 seeds (about 40 min)
    python benchmarks/honest_intervals.py --seeds 3 --scenes braking crowd --methods adaptive mc
    python benchmarks/honest_intervals.py --jobs 2              # two runs at a time, one thread each
    python benchmarks/honest_intervals.py --follow-advice       # the next: line followed (cut-in, crossing; 3 seeds)

``--follow-advice`` runs the cross-entropy default (``--method adaptive``) on the cut-in and the crossing, seeds 0-2,
reads the plain Monte Carlo command its ``next:`` line names (``--method mc --rel-error 0.2 --max-sims N``), runs it
on the same seed, and prints whether its interval holds the reference and its wall time against the time the line
predicted.

Exit status 1 when a goal is missed. Measured figures: the Validation page ("Every printed claim against the
answer").
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SCENES = ("braking", "cut-in", "cut-in-rare", "crowd", "crossing")
"""The shipped scenes with an exact answer (braking, crowd), a plain Monte Carlo reference (cut-in, crossing) or a
provisional answer (cut-in-rare, :data:`PROVISIONAL`)."""
METHODS = ("adaptive", "tilt", "ams", "mc")
"""Every method; ``tilt`` where the scene has a tilted proposal of its own."""


@dataclass(frozen=True)
class Outcome:
    """One run: its scene, method, seed, the answer (log p, nats), the estimate (log, nats), the claim printed
    (``interval``, ``bound`` or ``none``) as natural logs (lo, hi; hi = inf for a bound), its verdict, simulations and
    seconds; ``refused`` says why a method did not run on the scene (None: it ran)."""

    scene: str
    method: str
    seed: int
    truth: float
    log_mu: float = math.nan
    claim: str = "none"
    lo: float = -math.inf
    hi: float = math.inf
    verdict: str = ""
    sims: int = 0
    wall_s: float = 0.0
    refused: str | None = None

    @property
    def holds(self) -> bool:
        """Whether the claim holds the answer (a claim of nothing holds trivially)."""
        return self.lo <= self.truth <= self.hi

    @property
    def interval_off_x2(self) -> bool:
        """A printed interval that excludes the answer by more than a factor of 2."""
        ln2 = math.log(2.0)
        return self.claim == "interval" and (self.truth > self.hi + ln2 or self.truth < self.lo - ln2)

    @property
    def reliable_off_x2(self) -> bool:
        """A ``reliable`` verdict with the estimate outside x2 of the answer."""
        return self.verdict == "reliable" and not abs(self.log_mu - self.truth) <= math.log(2.0)


PROVISIONAL = {"cut-in-rare": math.log(1.8e-7)}
"""log p (nats) of a scene with neither an exact answer nor a plain Monte Carlo reference: cut-in-rare's is the
geometric mean of 10 runs of its tilted proposal at 7,280 rollouts (1.8e-7; splitting by the same committor gives
8.8e-8; the tilt's runs bound p >= 1.3e-7 at 95 % by Markov's inequality: :mod:`pemviz.scenarios.cut_in.scenario`'s
``RARITY_SETTINGS``). A provisional answer: a claim judged against it is marked so in the table."""


def truth_of(problem, scene: str) -> float:  # noqa: ANN001 (a Problem)
    """The scene's exact answer, plain Monte Carlo reference or :data:`PROVISIONAL` answer, log p (nats); nan
    without any."""
    if problem.exact_log_p is not None:
        return float(problem.exact_log_p)
    if problem.reference is not None:
        return float(problem.reference.log_p)
    return PROVISIONAL.get(scene, math.nan)


def default_config(scene: str, seed: int, flags: tuple[str, ...] = ()):  # noqa: ANN201 (an ExperimentConfig)
    """The settings of ``pemviz run --scenario SCENE --seed SEED [FLAGS]``, parsed by the command's own parser."""
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args

    return config_from_args(build_parser("run").parse_args(["run", "--scenario", scene, "--seed", str(seed), *flags]))


def one_run(scene: str, method: str, seed: int) -> Outcome:
    """``pemviz run --scenario SCENE --method METHOD --seed SEED`` (no recording) and what it printed."""
    from pemviz.engine.experiment import Experiment
    from pemviz.estimators import check_runnable
    from pemviz.scenarios.registry import problem_for
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        try:
            cfg = default_config(scene, seed)  # the scene's default command, or ...
            if cfg.method != method:  # ... with --method where another is asked for (at its own default budget)
                cfg = default_config(scene, seed, ("--method", method))
            problem = problem_for(cfg)
            check_runnable(cfg, problem)
        except (SystemExit, ValueError) as exc:  # a method the scene does not offer (the tilt)
            return Outcome(scene, method, seed, math.nan, refused=str(exc) or "refused")
        truth = truth_of(problem, scene)
        t0 = time.perf_counter()
        try:
            final = Experiment(cfg, problem=problem).run().final
        except ValueError as exc:
            return Outcome(scene, method, seed, truth, refused=str(exc).splitlines()[0])
        e = final.estimate
        lo, hi = e.shown_log_ci
        claim = (
            "interval" if e.interval_backed and (e.n_failures or e.plain_mc) else "bound" if e.n_failures else "none"
        )
        if claim == "none":
            lo, hi = -math.inf, math.inf
        return Outcome(
            scene,
            method,
            seed,
            truth,
            e.log_mu_hat,
            claim,
            lo,
            hi,
            e.verdict,
            int(final.n_simulations),
            time.perf_counter() - t0,
        )


def _p(log_p: float) -> str:
    from pemviz.core.estimate import format_probability

    return format_probability(log_p, 2) if not math.isnan(log_p) else "nan"


def line(o: Outcome) -> str:
    """One run as a line."""
    if o.refused is not None:
        return f"  {o.scene} {o.method} seed {o.seed}: refused ({o.refused})"
    claim = {"interval": f"[{_p(o.lo)}, {_p(o.hi)}]", "bound": f"p >= {_p(o.lo)}", "none": "no claim"}[o.claim]
    ratio = f"x{math.exp(o.log_mu - o.truth):.3g}" if math.isfinite(o.log_mu) else "no failure"
    return (
        f"  {o.scene} {o.method} seed {o.seed}: {_p(o.log_mu)} {claim} ({'holds' if o.holds else 'MISSES'} "
        f"{_p(o.truth)}), {ratio}, {o.verdict}; {o.sims:,} simulations, {o.wall_s:.1f} s"
    )


def table(outcomes: list[Outcome]) -> tuple[list[str], bool]:
    """The per-(scene, method) table and the totals (module docstring), and whether every goal is met."""
    rows = [
        "| scene | method | runs | intervals (holding; off by > x2) | lower bounds (holding) | 'reliable' off x2 "
        "| nan | median simulations |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    ran = [o for o in outcomes if o.refused is None]
    for scene in dict.fromkeys(o.scene for o in outcomes):
        shown = f"{scene} (provisional answer)" if scene in PROVISIONAL else scene
        for method in dict.fromkeys(o.method for o in outcomes):
            os_ = [o for o in ran if o.scene == scene and o.method == method]
            if not os_:
                if any(o.scene == scene and o.method == method for o in outcomes):
                    rows.append(f"| {shown} | {method} | refused | | | | | |")
                continue
            iv = [o for o in os_ if o.claim == "interval"]
            bd = [o for o in os_ if o.claim == "bound"]
            sims = sorted(o.sims for o in os_)[len(os_) // 2]
            rows.append(
                f"| {shown} | {method} | {len(os_)} | {len(iv)} ({sum(o.holds for o in iv)}; "
                f"{sum(o.interval_off_x2 for o in iv)}) | {len(bd)} ({sum(o.holds for o in bd)}) | "
                f"{sum(o.reliable_off_x2 for o in os_)} | {sum(math.isnan(o.log_mu) for o in os_)} | "
                f"{sims:,} |"
            )
    off = [o for o in ran if o.interval_off_x2]
    bounds = [o for o in ran if o.claim == "bound"]
    held = sum(o.holds for o in bounds)
    wrong = [o for o in ran if o.reliable_off_x2]
    nan = [o for o in ran if math.isnan(o.log_mu)]
    share = held / len(bounds) if bounds else 1.0
    totals = [
        f"printed 95 % intervals off the answer by more than x2: {len(off)} of "
        f"{sum(o.claim == 'interval' for o in ran)} (goal 0)",
        f"printed lower bounds holding the answer: {held} of {len(bounds)} ({share:.1%}; goal >= 95 %)",
        f"'reliable' with the estimate outside x2: {len(wrong)} (goal 0)",
        f"nan: {len(nan)} (goal 0)",
    ]
    met = not off and share >= 0.95 and not wrong and not nan
    return rows + [""] + totals, met


ADVICE_SCENES = ("cut-in", "crossing")
"""The scenes on which :func:`follow_advice` follows the adaptive run's advice (a reference each)."""


def follow_advice(scene: str, seed: int) -> tuple[str, str]:
    """The adaptive run's ``next:`` line on ``scene`` at ``seed``, and the plain Monte Carlo run it names, as two
    lines: what was advised (rollouts, predicted time) and what the followed run gave (its claim, whether it holds
    the reference, its wall time)."""
    import re

    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.registry import problem_for
    from pemviz.sinks.console import next_step
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        cfg = default_config(scene, seed, ("--method", "adaptive"))
        problem = problem_for(cfg)
        final = Experiment(cfg, problem=problem).run().final
        advice = (
            next_step(final.estimate, cfg, problem.exact_log_p, problem.reference, final.n_simulations, final.wall_s)
            or ""
        )
        m = re.search(r"--method mc --rel-error \S+ --max-sims \d+", advice)
        said = re.search(r"~([^ ]+ (s|min|h|days|years)) at", advice)
        head = f"  {scene} seed {seed}: next: {advice[:160]}{'...' if len(advice) > 160 else ''}"
        if m is None:
            return head, f"  {scene} seed {seed}: the advice names no plain Monte Carlo command"
        mc = default_config(scene, seed, tuple(m.group(0).split()))
        t0 = time.perf_counter()
        e = Experiment(mc, problem=problem).run().final.estimate
        wall = time.perf_counter() - t0
    truth = truth_of(problem, scene)
    lo, hi = e.shown_log_ci
    return head, (
        f"  {scene} seed {seed}: followed ({m.group(0)}): {_p(e.log_mu_hat)} [{_p(lo)}, {_p(hi)}], "
        f"{e.verdict}, {'holds' if lo <= truth <= hi else 'MISSES'} the reference {_p(truth)}; {wall:.0f} s "
        f"against the ~{said.group(1) if said else '?'} predicted"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=10, help="seeds 0..N-1 a (scene, method) (default 10)")
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument("--jobs", type=int, default=1, help="runs at a time, one thread each (default 1)")
    ap.add_argument(
        "--follow-advice",
        action="store_true",
        help="follow the adaptive run's next: line on the cut-in and the crossing, seeds 0..N-1 (N <= 3)",
    )
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.jobs < 1:
        ap.error("--seeds and --jobs must be at least 1")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if args.follow_advice:
        work = [(s, seed) for s in ADVICE_SCENES for seed in range(min(args.seeds, 3))]
        with ProcessPoolExecutor(args.jobs) as pool:
            for lines in pool.map(follow_advice, *zip(*work, strict=False)):
                print("\n".join(lines), flush=True)
        return 0
    work = [(s, m, seed) for s in args.scenes for m in args.methods for seed in range(args.seeds)]
    t0 = time.perf_counter()
    outcomes: list[Outcome] = []
    with ProcessPoolExecutor(args.jobs) as pool:
        for o in pool.map(one_run, *zip(*work, strict=False)):
            outcomes.append(o)
            print(line(o), flush=True)
    rows, met = table(outcomes)
    print("\n".join(["", *rows]))
    print(f"{len(work)} runs in {time.perf_counter() - t0:.0f} s; every goal {'met' if met else 'NOT met'}")
    return 0 if met else 1


if __name__ == "__main__":
    sys.exit(main())
