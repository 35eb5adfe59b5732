"""The rarity ladder: the crossing and the cut-in each at ``--param`` settings with p near 1e-4, 1e-5, 1e-6 and 1e-7,
and what the default command (``pemviz run --scenario SCENE --param ...``, nothing else) gives on each.

The rungs are :data:`RUNGS`, one table: the scene, its ``--param`` settings, the decade it stands for, the reference
(a plain Monte Carlo count with its Clopper-Pearson 95 % interval, where it comes from and the command that made it) or
``None`` where none is affordable (:attr:`Rung.no_reference` then says what would make one and what it would cost),
and how the rung was located. Each run is the default command at one seed, parsed by the command's own parser and run
in-process on the engine (:func:`default_runs.default_config`), no recording.

Per rung it prints: the median relative error |mu_hat / p - 1|, the runs within x2 of p, the printed 95 % intervals
(``reliable`` runs and plain Monte Carlo's; a lower bound is not an interval) holding p, the ``reliable`` runs
outside x2, the nan estimates, the verdicts, the mean cost in rollout-equivalents, and plain Monte Carlo's cost for
the same median relative error, ``(0.6745 / m)^2 (1 - p) / p`` rollouts (:func:`scene_neutral.mc_cost`: plain Monte
Carlo's relative error is about normal with standard deviation sqrt((1 - p) / (N p)), whose median absolute value is
0.6745 of it), and the ratio of the two. Two costs are given: the run's simulations (every rollout drawn, its
stages, retry and plain fallback; the tilt's look-aheads and solve as rollout-equivalents) and its CPU seconds over
the CPU seconds of one plain rollout of the rung (measured once a process on :data:`PLAIN_PROBE` rollouts), which
counts the fits too. The acceptance's targets (issue: median <= 0.2, >= 95 % within x2, >= 90 % intervals holding,
no ``reliable`` outside x2, no nan; cost <= 0.2 of plain Monte Carlo's at 1e-4, <= 0.05 at 1e-5, <= 50,000
rollout-equivalents at 1e-6 and 1e-7) are marked on each row. A rung without a reference prints the seeds' estimates,
their geometric mean and spread only.

``--out runs.jsonl`` keeps one line per run as it ends; ``--resume`` skips the (rung, seed) pairs already there, and an
existing file is never replaced without ``--overwrite``. ``--report FILE`` prints the table of a JSONL without running.

Usage::

    nice -n 10 python benchmarks/rarity_ladder.py --list
    nice -n 10 python benchmarks/rarity_ladder.py --seeds 3 --rungs cut-in-1e-4 cut-in-1e-5 --out ladder.jsonl
    nice -n 10 python benchmarks/rarity_ladder.py --seeds 20 --jobs 2 --out ladder.jsonl --resume
    python benchmarks/rarity_ladder.py --report ladder.jsonl crossing.jsonl

Measured figures: docs/validation.md, "The rarity ladder".
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from default_runs import default_config  # noqa: E402  (the command's own settings)
from scene_neutral import mc_cost  # noqa: E402  (plain Monte Carlo's cost for a median relative error)

SERIAL = ("--executor", "serial")
"""Every run simulates in its own process (a seed gives the same rollouts and estimate on any executor, bit for bit),
so that its CPU seconds are all counted and ``--jobs`` runs take ``--jobs`` cores."""

PLAIN_PROBE = 20_000
"""Plain rollouts timed once a process and rung: their CPU seconds each convert a run's CPU time to rollouts."""


def _sci(x: float) -> str:
    """``x`` to 3 significant figures, e.g. ``1.29e-4``."""
    return f"{x:.2e}".replace("e-0", "e-")


@dataclass(frozen=True)
class Reference:
    """A rung's answer: ``failures`` in ``rollouts`` of plain Monte Carlo under the shipped PEMs, where they come
    from (``source``) and the command(s) that drew them (``command``). p = failures / rollouts, with its
    Clopper-Pearson 95 % interval (:func:`pemviz.core.confidence.clopper_pearson`)."""

    failures: int
    rollouts: int
    source: str
    command: str

    @property
    def p(self) -> float:
        return self.failures / self.rollouts

    @property
    def interval(self) -> tuple[float, float]:
        from pemviz.core.confidence import clopper_pearson

        lo, hi = clopper_pearson(self.failures, self.rollouts)
        return float(lo), float(hi)

    @property
    def relative_se(self) -> float:
        """The relative standard error of p, sqrt((1 - p) / failures)."""
        return math.sqrt((1.0 - self.p) / self.failures)

    def short(self) -> str:
        """``p [lo, hi]``, e.g. ``7.95e-5 [7.50e-5, 8.41e-5]``."""
        lo, hi = self.interval
        return f"{_sci(self.p)} [{_sci(lo)}, {_sci(hi)}]"

    def text(self) -> str:
        lo, hi = self.interval
        return f"{_sci(self.p)} [{_sci(lo)}, {_sci(hi)}] ({self.failures:,} in {self.rollouts:,}, {self.source})"


@dataclass(frozen=True)
class Rung:
    """One rung: ``name`` (``SCENE-1eK``), the registered ``scene``, its ``params`` (``NAME=VALUE`` each, as
    ``--param`` takes them), the ``decade`` it stands for (log10 p), the ``reference`` or None, ``no_reference``
    (without one: the command that would make one and its cost) and ``located`` (how the setting was found)."""

    name: str
    scene: str
    params: tuple[str, ...]
    decade: int
    reference: Reference | None
    located: str
    no_reference: str = ""

    @property
    def flags(self) -> tuple[str, ...]:
        return tuple(f for p in self.params for f in ("--param", p))

    @property
    def command(self) -> str:
        return " ".join(["pemviz run --scenario", self.scene, *self.flags])


CROSSING_MC = "pemviz run --scenario crossing --method mc --param {} --n {} --seed S --no-record"
CUT_IN_MC = "python benchmarks/cut_in_mc.py --param {} --n {} --seed S"

RUNGS: tuple[Rung, ...] = (
    Rung(
        "crossing-1e-4",
        "crossing",
        ("brake_ttc_s=1.5",),
        -4,
        Reference(
            414,
            3_200_000,
            "plain Monte Carlo, shipped PEMs: 27, 74, 58, 62, 74, 60 and 59 failures at seeds 1-7",
            CROSSING_MC.format("brake_ttc_s=1.5", "200000 (seed 1), 500000 (seeds 2-7)"),
        ),
        "plain Monte Carlo of 200,000 rollouts: 27 failures, 1.35e-4 [8.9e-5, 1.96e-4]; the default brake_ttc_s=1.3 "
        "gives 2.98e-4; splitting checked against it as a second estimator (--method ams --ams-score lookahead --n "
        "400 --ams-killed 40 --ams-replicas 8, seeds 1-20): median relative error 0.139, 20/20 within x2, 20/20 "
        "intervals holding p, at 0.54 of plain Monte Carlo's cost for that error (0.2 asked)",
    ),
    Rung(
        "crossing-1e-5",
        "crossing",
        ("brake_mps2=9.5", "brake_ttc_s=2.0"),
        -5,
        Reference(
            424,
            42_000_000,
            "plain Monte Carlo, shipped PEMs: 22, 19, 12, 15, 18, 18, 20, 14, 16, 25, 20, 26, 28, 22, 24, 13, 23, 27, "
            "14, 21 and 27 failures at seeds 1-21",
            CROSSING_MC.format("brake_mps2=9.5 --param brake_ttc_s=2.0", "2000000") + " --workers 1, S = 1..21",
        ),
        "the deceleration acts by whole steps of the stop: brake_mps2=9.5 and 9.75 gave the same 76 failures in "
        "2,000,000 (seed 1), 3.80e-5 [2.99e-5, 4.76e-5], not the 1e-5 interpolated between 9 (4.30e-5) and 10 m/s^2 "
        "(3.0e-6); an earlier trigger, brake_ttc_s=2.0, brought it to 1.10e-5 (22 in 2,000,000, seed 1); splitting "
        "checked against it as a second estimator (--method ams --ams-score lookahead --n 400 --ams-killed 40 "
        "--ams-replicas 8, seeds 1-20, research/ams_replicas.py): median relative error 0.172, 20/20 within x2, 18/20 "
        "intervals holding p, none reliable outside x2, at 0.081 of plain Monte Carlo's cost for that error (0.05 "
        "asked)",
    ),
    Rung(
        "crossing-1e-6",
        "crossing",
        ("brake_mps2=10", "brake_ttc_s=2.0"),
        -6,
        None,
        "located, no reference: plain Monte Carlo of 2 x 10^7 rollouts (seeds 1-10 of 2,000,000, --workers 1) saw "
        "15 failures (1, 1, 4, 1, 4, 1, 1, 0, 0, 2), 7.5e-7 [4.2e-7, 1.2e-6] (exact Poisson); brake_mps2=10 alone gave "
        "3.00e-6 (seed 0's 10^6: 3 failures, the same 3 rollouts as at 11 m/s^2, crashes the brake never starts for); "
        "the earlier "
        "trigger takes it to 7.5e-7; splitting ranked by the look-ahead (--method ams --ams-score lookahead --n 400 "
        "--ams-killed 40, seed 1) gave 7.2e-7 at brake_mps2=10, doubtful, ESS 1.2; a second estimator, the same "
        "splitting with --ams-replicas 4 at this rung (seeds 1-9 and 2 replicas of seed 10: 38 replicas, 614,000 "
        "rollout-equivalents, research/ams_replicas.py), pooled 1.40e-6 [7.6e-7, 2.6e-6], whose interval meets plain "
        "Monte Carlo's on [7.6e-7, 1.2e-6]: they agree, barely (3 of the 38 replicas carry half the sum)",
        "plain Monte Carlo at 5 % needs 400 failures, about 5.3e8 rollouts at 7.5e-7: "
        + CROSSING_MC.format("brake_mps2=10 --param brake_ttc_s=2.0", "2000000")
        + " --workers 1 for S = 1..267: about 13 core-hours",
    ),
    Rung(
        "crossing-1e-7",
        "crossing",
        ("brake_mps2=11",),
        -7,
        None,
        "NOT located: meant to lie between the splitting runs at 10 (7.2e-7) and 12 m/s^2 (3.6e-9, doubtful, ESS 1.0), "
        "but the default command's plain Monte Carlo (seed 0) saw the same 3 failures in 10^6 as at 10 m/s^2, "
        "3.00e-6 [6.19e-7, 8.77e-6]: crashes the brake never starts for, which no deceleration prevents",
        "plain Monte Carlo at 5 % needs 400 failures, about 1.3e8 rollouts at 3e-6: "
        + CROSSING_MC.format("brake_mps2=11", "2000000")
        + " for S = 1..70: about 1.5 core-hours",
    ),
    Rung(
        "cut-in-1e-4",
        "cut-in",
        ("cut_in_gap_m=20",),
        -4,
        Reference(
            1176,
            14_800_000,
            "the engine's plain Monte Carlo, MONTE_CARLO_REFERENCE",
            CUT_IN_MC.format("cut_in_gap_m=20", "10000000 --chunk 200000")
            + " (and ten --method adaptive runs' plain fallback; docs/cut-in.md)",
        ),
        "the scene's default (moderate) setting",
    ),
    Rung(
        "cut-in-1e-5",
        "cut-in",
        ("cut_in_gap_m=21.5",),
        -5,
        None,
        "the cut-in's gap moves p by steps: at 21 m, this rung's former setting, the engine's plain Monte Carlo gives "
        "3.18e-5 [2.78e-5, 3.62e-5] (229 in 7,200,000, seeds 2100-2135, GAP_21_REFERENCE of "
        "benchmarks/scene_neutral.py): half a decade up; at 21.5 m the tilt's geometric mean is 4.0e-6 "
        "(docs/cut-in.md, Rarity)",
        "plain Monte Carlo at 5 % needs 400 failures, about 8e7 rollouts at ~5e-6: "
        + CUT_IN_MC.format("cut_in_gap_m=21.5", "80000000 --chunk 200000")
        + ": about 14 core-hours at 0.62 ms a rollout",
    ),
    Rung(
        "cut-in-1e-6",
        "cut-in",
        ("cut_in_gap_m=22.5", "cut_in_lateral_time_s=1.1"),
        -6,
        None,
        "the cut-in car's lane-change time is the second knob: the gap alone moves p by steps (about 5e-6 at 22.125 m, "
        "1.7e-7 at 22.25 m), while at 22.5 m a slower lane change raises it, the tilt giving 1.2e-6 and 4.1e-7 at "
        "cut_in_lateral_time_s=1.05 (seeds 0, 1), 4.0e-7 to 2.0e-6 at 1.1 (seeds 0-5: geometric mean 9.7e-7, p >= "
        "5.9e-7 at 95 %, Markov), and 5.8e-5 at 1.2 with the gap 22.125 m (seed 0); splitting by the same committor "
        "1.3e-7, 7.2e-8 and 2.4e-7 (seeds 0-2): x7.4 below",
        "plain Monte Carlo at 5 % needs 400 failures, 4e8 rollouts at 1e-6: "
        + CUT_IN_MC.format("cut_in_gap_m=22.5 --param cut_in_lateral_time_s=1.1", "400000000 --chunk 1000000")
        + ": about 38 core-hours at 2,900 rollouts/s",
    ),
    Rung(
        "cut-in-1e-7",
        "cut-in",
        ("cut_in_gap_m=22.5",),
        -7,
        None,
        "the rare setting (cut-in-rare's scene): 10 tilted runs' geometric mean 1.8e-7, p >= 1.3e-7 at 95 % "
        "(Markov); splitting by the committor 8.8e-8 (docs/cut-in.md)",
        "plain Monte Carlo at 5 % needs 400 failures, 2.2e9 rollouts at 1.8e-7: "
        + CUT_IN_MC.format("cut_in_gap_m=22.5", "2200000000 --chunk 1000000")
        + ": about 210 core-hours at 2,900 rollouts/s",
    ),
)
"""The ladder (module docstring)."""


def rung(name: str) -> Rung:
    """The rung called ``name``; ValueError naming the rungs if there is none."""
    for r in RUNGS:
        if r.name == name:
            return r
    raise ValueError(f"no rung {name!r}: the rungs are {', '.join(r.name for r in RUNGS)}")


# -- runs -----------------------------------------------------------------------------------------------------------

_PLAIN_CPU: dict[str, float] = {}
"""CPU seconds of one plain rollout, by rung (this process's)."""


def plain_cpu_per_rollout(r: Rung) -> float:
    """CPU seconds of one plain Monte Carlo rollout of the rung's scene (:data:`PLAIN_PROBE` of them, timed once a
    process): what converts a run's CPU seconds to rollout-equivalents."""
    if r.name not in _PLAIN_CPU:
        from pemviz.engine.experiment import Experiment
        from pemviz.scenarios.problems import problem_for

        cfg = default_config(r.scene, 999_999, (*r.flags, *SERIAL, "--method", "mc", "--n", str(PLAIN_PROBE)))
        problem = problem_for(cfg)
        t0 = time.process_time()
        Experiment(cfg, problem=problem).run()
        _PLAIN_CPU[r.name] = (time.process_time() - t0) / PLAIN_PROBE
    return _PLAIN_CPU[r.name]


def one_run(name: str, seed: int) -> dict[str, Any]:
    """The default command of rung ``name`` at ``seed`` (one thread, :data:`SERIAL`), as a JSON-able record: the
    estimate (``log_mu``, nats, -inf as null), what it printed (``lo``, ``hi``: its interval, or its lower bound and
    +inf), whether that is an ``interval``, the verdict, failures, ``sims`` (rollout-equivalents), ``cpu_s`` and
    ``wall_s`` of the run, ``plain_cpu_s`` (one plain rollout's) and whether the answer is plain Monte Carlo's."""
    import os

    from pemviz.engine.experiment import Experiment
    from pemviz.engine.resources import torch_threads
    from pemviz.scenarios.problems import problem_for

    r = rung(name)
    with torch_threads(1, blas=1):
        plain_cpu = plain_cpu_per_rollout(r)
        cfg = default_config(r.scene, seed, (*r.flags, *SERIAL))
        problem = problem_for(cfg)
        t0, c0 = time.perf_counter(), time.process_time()
        final = Experiment(cfg, problem=problem).run().final
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    e = final.estimate
    lo, hi = e.shown_log_ci
    return {
        "rung": name,
        "command": r.command,
        "seed": seed,
        "method": cfg.method,
        "log_mu": _json_float(e.log_mu_hat),
        "lo": _json_float(lo),
        "hi": _json_float(hi),
        "interval": bool(e.interval_backed and e.n_failures > 0),
        "verdict": e.verdict,
        "failures": int(e.n_failures),
        "plain": bool(e.plain_mc),
        "sims": int(final.n_simulations),
        "cpu_s": round(cpu, 2),
        "wall_s": round(wall, 2),
        "plain_cpu_s": plain_cpu,
        "load": round(os.getloadavg()[0], 2),
    }


def _json_float(x: float) -> float | str:
    return x if math.isfinite(x) else ("nan" if math.isnan(x) else ("inf" if x > 0 else "-inf"))


def _float(x: float | str) -> float:
    return float(x)


# -- the table ------------------------------------------------------------------------------------------------------

HEADER = (
    "| rung | `--param` | p (reference) | seeds | median rel. error | within x2 | intervals holding | reliable "
    "outside x2 | nan | verdicts | cost (simulations) | cost (CPU, rollouts) | plain MC, same median | ratio | "
    "targets |\n|---|---|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|---:|---|"
)


def targets(r: Rung, med: float, within: int, held: int, wrong: int, nan: int, n: int, cost: float, mc: float) -> str:
    """The acceptance's targets the row meets and misses (module docstring), e.g. ``median, x2, cost; NOT holding``."""
    met = {
        "median <= 0.2": med <= 0.2,
        "x2 >= 95 %": within >= 0.95 * n,
        "holding >= 90 %": held >= 0.9 * n,
        "no reliable outside x2": wrong == 0,
        "no nan": nan == 0,
    }
    if r.decade >= -4:
        met["cost <= 0.2 MC"] = cost <= 0.2 * mc
    elif r.decade == -5:
        met["cost <= 0.05 MC"] = cost <= 0.05 * mc
    else:
        met["cost <= 50,000"] = cost <= 50_000
    missed = [k for k, ok in met.items() if not ok]
    return "all met" if not missed else "missed: " + ", ".join(missed)


def row(r: Rung, runs: list[dict[str, Any]]) -> str:
    """The rung's line of the table (:data:`HEADER`)."""
    n = len(runs)
    logs = [_float(x["log_mu"]) for x in runs]
    sims = statistics.mean(x["sims"] for x in runs)
    cpu = statistics.mean(x["cpu_s"] / x["plain_cpu_s"] for x in runs)
    nan = sum(math.isnan(v) for v in logs)
    verdicts = ", ".join(
        f"{sum(x['verdict'] == v for x in runs)} {v}" for v in dict.fromkeys(x["verdict"] for x in runs)
    )
    plain = sum(x["plain"] for x in runs)
    shown = sum(x["interval"] for x in runs)
    params = " ".join(f"`{p}`" for p in r.params)
    head = f"| {r.name} | {params} | "
    tail = f"{verdicts}; {plain} by plain MC | {sims:,.0f} | {cpu:,.0f} |"
    if r.reference is None:
        finite = [v for v in logs if math.isfinite(v)]
        gm = _sci(math.exp(statistics.mean(finite))) if finite else "-"
        spread = f"{_sci(math.exp(min(finite)))} to {_sci(math.exp(max(finite)))}" if finite else "no failure"
        return (
            f"{head}no reference | {n} | - (estimates {spread}, geometric mean {gm}) | - | {shown} printed | - | {nan} "
            f"| {tail} - | - | cost <= 50,000: {'met' if cpu <= 50_000 and sims <= 50_000 else 'missed'} |"
        )
    truth = math.log(r.reference.p)
    ratios = [math.exp(v - truth) if v > -math.inf else 0.0 for v in logs]
    med = statistics.median(abs(q - 1.0) for q in ratios)
    within = sum(0.5 <= q <= 2.0 for q in ratios)
    held = sum(x["interval"] and _float(x["lo"]) <= truth <= _float(x["hi"]) for x in runs)
    wrong = sum(x["verdict"] == "reliable" and not 0.5 <= q <= 2.0 for x, q in zip(runs, ratios, strict=True))
    mc = mc_cost(r.reference.p, med) if med < 1.0 else math.inf
    cost = max(sims, cpu)
    ratio = "-" if math.isinf(mc) else f"{sims / mc:.2g} / {cpu / mc:.2g}"
    mc_text = "-" if math.isinf(mc) else f"{mc:,.0f}"
    return (
        f"{head}{r.reference.short()} | {n} | {med:.3f} | {within}/{n} | {held}/{shown} of {n} | {wrong} | {nan} | "
        f"{tail} {mc_text} | {ratio} | {targets(r, med, within, held, wrong, nan, n, cost, mc)} |"
    )


def report(runs: list[dict[str, Any]], names: list[str]) -> str:
    """The table of ``runs`` for the rungs ``names`` that have runs, with a line on the costs. A run whose command is
    not its rung's now (a rung moved since) is left out, and a line says so."""
    lines, stale = [HEADER], []
    for name in names:
        mine = [x for x in runs if x["rung"] == name and x["command"] == rung(name).command]
        stale += [f"{x['rung']} seed {x['seed']} ({x['command']})" for x in runs if x["rung"] == name and x not in mine]
        if mine:
            lines.append(row(rung(name), sorted(mine, key=lambda x: x["seed"])))
    if stale:
        lines.append(f"\nleft out, run at a rung's former setting: {'; '.join(stale)}")
    lines.append(
        "\ncost: the mean over the seeds of the run's simulations (rollout-equivalents) and of its CPU seconds over "
        "one plain rollout's; ratio: each over plain Monte Carlo's (0.6745 / m)^2 (1 - p) / p rollouts for the same "
        "median relative error m; the cost target takes the larger of the two."
    )
    return "\n".join(lines)


# -- the command ----------------------------------------------------------------------------------------------------


def read_runs(path: Path) -> list[dict[str, Any]]:
    """The runs of a JSONL written by this script (one JSON object a line), the first of each (rung, seed)."""
    runs: dict[tuple[str, int], dict[str, Any]] = {}
    with path.open(encoding="utf-8") as f:
        for line in f:
            if line.strip():
                x = json.loads(line)
                runs.setdefault((x["rung"], x["seed"]), x)
    return list(runs.values())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20, help="seeds a rung (0 .. SEEDS-1 from --first-seed)")
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--rungs", nargs="+", default=[r.name for r in RUNGS], metavar="RUNG")
    ap.add_argument("--jobs", type=int, default=1, help="runs at a time (processes)")
    ap.add_argument("--out", type=Path, default=None, help="JSONL of the runs, a line each as it ends")
    ap.add_argument("--resume", action="store_true", help="keep --out's runs and add only the missing ones")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    ap.add_argument(
        "--report", type=Path, nargs="+", default=None, metavar="JSONL", help="print the table of JSONLs, run none"
    )
    ap.add_argument("--list", action="store_true", help="print the rungs, their references and how they were located")
    args = ap.parse_args(argv)
    try:
        names = [rung(n).name for n in args.rungs]
    except ValueError as exc:
        ap.exit(2, f"rarity_ladder.py: error: --rungs: {exc}\n")
    if args.seeds < 1 or args.jobs < 1:
        ap.exit(2, f"rarity_ladder.py: error: --seeds {args.seeds}, --jobs {args.jobs}: each must be at least 1\n")
    if args.list:
        for r in RUNGS:
            ref = r.reference.text() if r.reference else f"no reference: {r.no_reference}"
            made = f"\n    made by: {r.reference.command}" if r.reference else ""
            print(f"{r.name}: {r.command}\n    p: {ref}{made}\n    located: {r.located}")
        return 0
    if args.report is not None:
        missing = [str(p) for p in args.report if not p.is_file()]
        if missing:
            ap.exit(2, f"rarity_ladder.py: error: --report {', '.join(missing)}: no such file\n")
        print(report([x for p in args.report for x in read_runs(p)], names))
        return 0
    done: list[dict[str, Any]] = []
    if args.out is not None and args.out.exists():
        if args.resume:
            done = read_runs(args.out)
        elif not args.overwrite:
            ap.exit(2, f"rarity_ladder.py: error: --out {args.out} exists: give --resume or --overwrite\n")
        else:
            args.out.unlink()
    have = {(x["rung"], x["seed"]) for x in done}
    todo = [(n, s) for n in names for s in range(args.first_seed, args.first_seed + args.seeds) if (n, s) not in have]
    runs = [x for x in done if x["rung"] in names]
    with ProcessPoolExecutor(args.jobs) as pool:
        for x in pool.map(one_run, *zip(*todo, strict=True)) if todo else ():
            runs.append(x)
            print(
                f"{x['rung']} seed {x['seed']}: {math.exp(_float(x['log_mu'])):.3e} "
                f"[{math.exp(_float(x['lo'])):.2e}, {math.exp(_float(x['hi'])):.2e}]"
                f"{'' if x['interval'] else ' (a lower bound)'}, {x['verdict']}, {x['failures']} failures, "
                f"{x['sims']:,} simulations, {x['cpu_s']:.0f} s CPU ({x['cpu_s'] / x['plain_cpu_s']:,.0f} plain "
                f"rollouts' worth), {x['wall_s']:.0f} s",
                flush=True,
            )
            if args.out is not None:
                with args.out.open("a", encoding="utf-8") as f:
                    f.write(json.dumps(x) + "\n")
    print(report(runs, names))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
