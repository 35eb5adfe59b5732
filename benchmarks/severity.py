"""The exceedance curve P(min gap < x) of the braking scenario against its exact points.

Prints, for the default ``pemviz run`` on braking over ``--seeds`` seeds, each point of the curve the run reports
(``reached``: verdict ``reliable``) against the exact answer where one is known (``pemviz.scenarios.braking.truth``:
:data:`KNOWN_BRAKING_MARGIN_LOG_P`, the enumeration with ``BrakingParams(crash_gap_m=x)``): the ratio to it, whether
the interval holds it, and how many seeds reach the point at all; then the same for runs that target a level
(``--margin x``). With ``--exact`` it first recomputes the exact points (``braking_truth``: 1.5 m and 1 m on the
node bound, 0.5 m and 0 m on the cell bound, 0.5-2 minutes each, 5 GB at 0.5 m). With
``--zero-gap-seeds K`` it ends with K runs that target a gap below 0 m at the default budget (``pemviz run --margin 0
--seed s``, s = 0..K-1, each with the look-ahead below 6 m: :mod:`pemviz.scenarios.braking.lookahead`): every
estimate against the exact 0 m point whatever its verdict (within x1.5, interval holding, the median relative error),
the verdicts, and how many runs whose weights said reliable (before the scenario's cap at ``doubtful``) were wrong.

    python benchmarks/severity.py                    # 20 seeds of the default run, 5 of each targeted run (~4 min)
    python benchmarks/severity.py --seeds 5 --exact  # and the enumeration
    python benchmarks/severity.py --seeds 0 --targeted-seeds 0 --zero-gap-seeds 40   # ~6 min
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from pemviz.config import ExperimentConfig
from pemviz.engine.experiment import Experiment
from pemviz.scenarios.problems import problem_for

TARGET_RATIO = 1.5
"""Every point a run reports lies within this factor of the exact answer (and its interval holds it)."""


def curve(config: ExperimentConfig):
    return Experiment(config, problem=problem_for(config)).run().final.severity


def table(label: str, configs: list[ExperimentConfig]) -> bool:
    rows: dict[str, list] = {}
    exact: dict[str, float | None] = {}
    t0 = time.perf_counter()
    for cfg in configs:
        c = curve(cfg)
        for pt in c.points:
            key = c.point_text(pt)
            exact[key] = pt.exact_log_p
            rows.setdefault(key, []).append(pt)
    print(f"\n{label}: {len(configs)} seeds, {time.perf_counter() - t0:.0f} s")
    print(
        f"{'point':<30} {'reached':>8} {'median p':>10} {'exact':>10} {'worst ratio':>12} {'covers':>8} "
        f"{'median ESS':>11}"
    )
    ok = True
    for key, pts in rows.items():
        reached = [p for p in pts if p.reached]
        med = float(np.median([p.estimate.log_mu_hat for p in reached])) if reached else -math.inf
        ex = exact[key]
        if ex is not None and reached:
            ratios = [math.exp(abs(p.estimate.log_mu_hat - ex)) for p in reached]
            covers = sum(p.estimate.covers(ex) for p in reached)
            worst, cov = f"{max(ratios):.3f}", f"{covers}/{len(reached)}"
            ok &= max(ratios) <= TARGET_RATIO and covers == len(reached)
        else:
            worst = cov = "-"
        ess = f"{np.median([p.estimate.ess for p in reached]):.1f}" if reached else "-"
        print(
            f"{key:<30} {len(reached):>4}/{len(pts):<3} {math.exp(med) if reached else 0:>10.3e} "
            f"{'-' if ex is None else format(math.exp(ex), '.3e'):>10} {worst:>12} {cov:>8} {ess:>11}"
        )
    return ok


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--targeted-seeds", type=int, default=5)
    ap.add_argument("--exact", action="store_true", help="recompute the exact points first")
    ap.add_argument(
        "--zero-gap-seeds", type=int, default=0, help="this many runs that target a gap below 0 m at the end"
    )
    a = ap.parse_args()
    if a.exact:
        from pemviz.pem import load_pem
        from pemviz.scenarios.braking.simulator import BrakingParams
        from pemviz.scenarios.braking.truth import braking_truth

        pem = load_pem()
        for m in (1.5, 1.0, 0.5, 0.0):
            t = time.perf_counter()
            r = braking_truth(
                pem.logit_at_gap,
                BrakingParams(crash_gap_m=m),
                log_prunes=(-46.0, -50.0, -54.0, -58.0, -62.0, -66.0, -70.0, -80.0, -90.0, -100.0, -110.0),
            )
            print(
                f"exact P(min gap < {m:g} m) = {math.exp(r.log_p_fail):.4e} (log {r.log_p_fail!r}), bracket width "
                f"{r.final.relative_width:.2e}, {time.perf_counter() - t:.0f} s"
            )
    ok = table("default run (pemviz run)", [ExperimentConfig.of(seed=s) for s in range(a.seeds)]) if a.seeds else True
    targeted_ok = True
    for m in (1.0, 0.5, 0.0):
        if a.targeted_seeds:
            targeted_ok &= table(
                f"targeted run (pemviz run --margin {m:g})",
                [ExperimentConfig.of(seed=s, margin=m) for s in range(a.targeted_seeds)],
            )
    print(
        f"\nevery reported point of the default run within x{TARGET_RATIO} of the exact one and inside its interval: "
        f"{'MET' if ok else 'MISSED'}; of the targeted runs: {'MET' if targeted_ok else 'MISSED'}"
    )
    if a.zero_gap_seeds:
        zero_gap_study(a.zero_gap_seeds)


def zero_gap_study(seeds: int) -> None:
    """``seeds`` runs that target a gap below 0 m (``--margin 0``, seeds 0..K-1, the default budget) against the exact
    point."""
    t0 = time.perf_counter()
    runs = [curve(ExperimentConfig.of(seed=s, margin=0.0)).points[0] for s in range(seeds)]
    ex = runs[0].exact_log_p
    err = np.array([abs(math.expm1(p.estimate.log_mu_hat - ex)) for p in runs])
    within = [math.exp(abs(p.estimate.log_mu_hat - ex)) <= TARGET_RATIO for p in runs]
    holds = [p.estimate.covers(ex) for p in runs]
    verdicts: dict[str, int] = {}
    for p in runs:
        verdicts[p.estimate.verdict] = verdicts.get(p.estimate.verdict, 0) + 1
    capped = [p.estimate.verdict == "reliable" or p.estimate.reason.startswith("a gap below") for p in runs]
    wrong = sum(c and not (w and h) for c, w, h in zip(capped, within, holds, strict=False))
    print(
        f"\ngap below 0 m, {seeds} runs of pemviz run --margin 0 (seeds 0-{seeds - 1}, "
        f"{time.perf_counter() - t0:.0f} s), "
        f"exact {math.exp(ex):.4e}: median relative error {np.median(err):.3f}; within x{TARGET_RATIO} "
        f"{sum(within)}/{seeds}; interval holds {sum(holds)}/{seeds}; seeds 0-4 all within x{TARGET_RATIO} and "
        f"holding: {'MET' if all(within[:5]) and all(holds[:5]) else 'MISSED'}; verdicts {verdicts}; weights that "
        f"said reliable: {sum(capped)}, {wrong} of them wrong (outside x{TARGET_RATIO} or the interval missing)"
    )


if __name__ == "__main__":
    main()
