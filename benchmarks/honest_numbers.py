"""Honest numbers on every scene: no nan, no "reliable" when wrong, every default interval holds, a precision target.

Prints, as markdown tables (the figures of the user guide's Validation page):

1. ``matrix``: braking and cut-in, every method (adaptive under each preset, mc, naive50, mixed50, ams, tilt), N = 100
   (the default budget: every method's default N) and N = 1000, ``--seeds`` seeds: the verdicts, how many intervals hold
   the exact answer (braking) or the plain Monte Carlo reference (cut-in), how many runs print nan or inf, and how
   many say "reliable" with the answer outside a factor of 2 (a wrong claim); a preset the scene refuses is listed
   as refused, with the one line it prints.
2. ``defaults``: the default command of each scene (``pemviz run [--scenario S]``: the scene's own default method,
   :func:`pemviz.config.scene_defaults`), 20 seeds: how many intervals hold the answer (target >= 19 of 20).
3. ``rel-error``: ``pemviz run --rel-error 0.05`` on braking, 20 seeds: the relative half-width reached, the
   simulations, how many intervals hold the exact answer (target >= 19 of 20).
4. ``cut-in-mc``: ``pemviz run --scenario cut-in --method mc --rel-error 0.2 --max-time 600``: where it stops, and
   whether mu_hat is within x1.5 of the reference.
5. ``refusal``: the seconds ``pemviz run --preset paper --scenario cut-in`` takes to refuse (target < 2 s).
6. ``speed``: the cut-in's plain Monte Carlo throughput as the ratio to braking's, both in fresh processes run back to
   back, three times (``benchmarks/sim_speed.py --cut-in``; target <= 14, about 69 before the cut-in was batched);
   measure on a quiet machine (the load average is printed).

Exit 1 if any run prints nan or inf or says "reliable" when wrong. Run from the repository root:

    python benchmarks/honest_numbers.py                          # everything: about 40 min on 2 cores
    python benchmarks/honest_numbers.py --part matrix --seeds 3  # one part, fewer seeds
    python benchmarks/honest_numbers.py --json out.json          # every run's numbers as well
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENES = ("braking", "cut-in")
PRESET_RUNS = ("state-ce", "paper", "authors-code", "quick", "state-ce-step")
METHOD_RUNS = ("mc", "naive50", "mixed50", "ams", "tilt")
BUDGETS = (100, 1000)
PARTS = ("matrix", "defaults", "rel-error", "cut-in-mc", "refusal", "speed")


def config(scene: str, seed: int, preset: str | None = None, method: str | None = None, **fields):
    """The config ``pemviz run`` builds from these flags (a scene's own defaults with neither method nor preset)."""
    from pemviz.config import ExperimentConfig, scene_defaults
    from pemviz.presets import DEFAULT_PRESET, PRESETS

    base = dict(PRESETS[preset or DEFAULT_PRESET])
    if preset is None and method is None:
        base.update(scene_defaults(scene))
    if method is not None:
        base["method"] = method
    return ExperimentConfig.of(**{**base, "scenario": scene, "seed": seed, **fields})


def one(job: dict) -> dict:
    """One run of ``job`` (``scene``, ``seed``, optional ``preset`` / ``method`` / config fields), summarised."""
    from pemviz.config import ConfigError
    from pemviz.engine.experiment import Experiment
    from pemviz.engine.resources import torch_threads
    from pemviz.scenarios.problems import problem_for

    spec = {k: v for k, v in job.items() if k not in ("part", "label")}
    try:
        cfg = config(**spec)
    except ConfigError as exc:
        return {**job, "refused": str(exc)}
    sys.path.insert(0, str(REPO / "benchmarks"))
    from braking_committor import with_braking_tilt  # braking's tilt is research's (research/braking_tilt.py)

    problem = with_braking_tilt(problem_for(cfg), cfg)
    truth = problem.exact_log_p if problem.exact_log_p is not None else problem.reference.log_p
    t0 = time.perf_counter()
    with torch_threads(1, blas=1):
        final = Experiment(cfg, problem=problem).run().final
    e = final.estimate
    values = (e.log_mu_hat, e.ess, *e.log_ci, e.log_mean_weight)
    return {
        **job,
        "verdict": e.verdict,
        "covers": e.covers(truth),
        "log_mu_hat": e.log_mu_hat,
        "log_truth": truth,
        "nan_or_inf": any(math.isnan(v) or v == math.inf for v in values),
        "within2": abs(e.log_mu_hat - truth) <= math.log(2.0),
        "rel_half_width": e.rel_half_width,
        "n_simulations": final.n_simulations,
        "stop": final.stop,
        "wall_s": time.perf_counter() - t0,
    }


def jobs_of(part: str, seeds: int, scenes: tuple[str, ...] = SCENES) -> list[dict]:
    if part == "matrix":
        jobs = []
        for scene in scenes:
            for n in BUDGETS:
                for label, spec in [(p, {"preset": p, "method": "adaptive"}) for p in PRESET_RUNS] + [
                    (m, {"method": m}) for m in METHOD_RUNS
                ]:
                    jobs += [
                        {"part": part, "label": label, "scene": scene, "seed": s, "n_per_stage": n, **spec}
                        for s in range(seeds)
                    ]
        return jobs
    if part == "defaults":
        return [{"part": part, "label": "default", "scene": scene, "seed": s} for scene in scenes for s in range(20)]
    if part == "rel-error":
        return [
            {"part": part, "label": "rel-error 0.05", "scene": "braking", "seed": s, "rel_error": 0.05}
            for s in range(20)
        ]
    if part == "cut-in-mc":
        return [
            {
                "part": part,
                "label": "mc rel-error 0.2",
                "scene": "cut-in",
                "seed": 0,
                "method": "mc",
                "n_per_stage": 20_000,
                "rel_error": 0.2,
                "max_time_s": 600.0,
            }
        ]
    return []


def table(runs: list[dict], keys: tuple[str, ...]) -> int:
    """Print one row per group of ``keys``; returns the wrong claims and nan/inf runs."""
    print(
        "| " + " | ".join(keys) + " | runs | verdicts | interval holds | within x2 | nan or inf | reliable when wrong |"
    )
    print("|" + "---|" * (len(keys) + 6))
    bad = 0
    for key in dict.fromkeys(tuple(r.get(k) for k in keys) for r in runs):
        g = [r for r in runs if tuple(r.get(k) for k in keys) == key]
        cells = " | ".join(str(k) for k in key)
        if "refused" in g[0]:
            print(f"| {cells} | {len(g)} | refused at once: {g[0]['refused']} | - | - | - | - |")
            continue
        wrong = sum(r["verdict"] == "reliable" and not r["within2"] for r in g)
        nan = sum(r["nan_or_inf"] for r in g)
        bad += wrong + nan
        verdicts = ", ".join(f"{v} {c}" for v, c in sorted(Counter(r["verdict"] for r in g).items()))
        print(
            f"| {cells} | {len(g)} | {verdicts} | {sum(r['covers'] for r in g)} | {sum(r['within2'] for r in g)} "
            f"| {nan} | {wrong} |"
        )
    return bad


def refusal_seconds() -> tuple[float, int, str]:
    t0 = time.perf_counter()
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; from pemviz.cli import main; sys.exit(main())",
            "run",
            "--preset",
            "paper",
            "--scenario",
            "cut-in",
            "--no-record",
        ],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    return time.perf_counter() - t0, proc.returncode, proc.stderr.strip()


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--part", choices=PARTS, action="append", help="one part (repeatable; default: all)")
    p.add_argument("--seeds", type=int, default=10, help="seeds of the matrix (default 10)")
    p.add_argument("--scenes", default=",".join(SCENES), help="the scenes of the matrix and the defaults")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--json", type=Path, help="write every run's numbers here")
    a = p.parse_args()
    parts = a.part or list(PARTS)
    bad, everything = 0, []
    for part in parts:
        print(f"\n## {part}\n")
        if part == "refusal":
            s, rc, line = refusal_seconds()
            print(f"`pemviz run --preset paper --scenario cut-in`: exit {rc} after {s:.2f} s (target < 2 s): {line}")
            bad += rc != 2 or s >= 2.0
            continue
        if part == "speed":
            sys.path.insert(0, str(REPO / "benchmarks"))
            from sim_speed import cut_in_vs_braking

            bad += not all(ratio <= 14.0 for ratio in cut_in_vs_braking(None, 3))
            continue
        t0 = time.perf_counter()
        with ProcessPoolExecutor(a.jobs) as ex:
            runs = list(ex.map(one, jobs_of(part, a.seeds, tuple(a.scenes.split(",")))))
        everything += runs
        bad += table(runs, ("scene", "label", "n_per_stage") if part == "matrix" else ("scene", "label"))
        done = [r for r in runs if "refused" not in r]
        if part in ("defaults", "rel-error"):
            for scene in dict.fromkeys(r["scene"] for r in done):
                g = [r for r in done if r["scene"] == scene]
                held = sum(r["covers"] for r in g)
                bad += held < 19
                widths = sorted(r["rel_half_width"] for r in g)
                print(
                    f"\n{scene}: the interval holds the answer in {held} of {len(g)} (target >= 19); relative "
                    f"half-width median {widths[len(g) // 2]:.3g}, max {widths[-1]:.3g}; simulations median "
                    f"{sorted(r['n_simulations'] for r in g)[len(g) // 2]:,}"
                )
        if part == "cut-in-mc":
            r = done[0]
            ratio = math.exp(abs(r["log_mu_hat"] - r["log_truth"]))
            print(
                f"\nmu_hat {math.exp(r['log_mu_hat']):.3g} vs reference {math.exp(r['log_truth']):.3g}: x{ratio:.2f} "
                f"(target <= 1.5 or a cap said), {r['n_simulations']:,} simulations in {r['wall_s']:.0f} s; "
                f"stop: {r['stop']}"
            )
            bad += ratio > 1.5 and not r["stop"].startswith("stopped at a cap")
        print(f"\n({len(runs)} runs in {time.perf_counter() - t0:.0f} s)")
    if a.json:
        a.json.write_text(json.dumps(everything, indent=1, default=str))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
