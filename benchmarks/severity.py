"""The exceedance curve P(min gap < x) of the braking scenario against its exact points.

Prints, for the default ``pemviz run`` on braking over ``--seeds`` seeds, each point of the curve the run reports
(``reached``: verdict ``reliable``) against the exact answer where one is known (``pemviz.scenarios.braking.truth``:
:data:`KNOWN_BRAKING_MARGIN_LOG_P`, the enumeration with ``BrakingParams(crash_gap_m=x)``): the ratio to it, whether
the interval holds it, and how many seeds reach the point at all; then the same for runs that target a level
(``--margin x``). With ``--exact`` it first recomputes the exact points (``braking_truth``: 1.5 m and 1 m on the
node bound, 0.5 m and 0 m (contact) on the cell bound, 0.5-2 minutes each, 5 GB at 0.5 m). With ``--contact-seeds K``
it ends with the mean of K targeted contact runs at a larger budget (``--margin 0 --n 1000 --n-final 20000``): each
run's estimate is unbiased, so their mean is an independent check of the exact contact point.

    python benchmarks/severity.py                    # 20 seeds of the default run, 5 of each targeted run (~3 min)
    python benchmarks/severity.py --seeds 5 --exact  # and the enumeration
    python benchmarks/severity.py --seeds 0 --targeted-seeds 0 --contact-seeds 20   # ~2 min
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from pemviz.config import ExperimentConfig
from pemviz.scenarios.problems import problem_for
from pemviz.engine.experiment import Experiment

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
    print(f"{'point':<30} {'reached':>8} {'median p':>10} {'exact':>10} {'worst ratio':>12} {'covers':>8} {'median ESS':>11}")
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
        print(f"{key:<30} {len(reached):>4}/{len(pts):<3} {math.exp(med) if reached else 0:>10.3e} "
              f"{'-' if ex is None else format(math.exp(ex), '.3e'):>10} {worst:>12} {cov:>8} {ess:>11}")
    return ok


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--targeted-seeds", type=int, default=5)
    ap.add_argument("--exact", action="store_true", help="recompute the exact points first")
    ap.add_argument("--contact-seeds", type=int, default=0, help="mean of this many larger contact runs at the end")
    a = ap.parse_args()
    if a.exact:
        from pemviz.scenarios.braking.truth import braking_truth
        from pemviz.pem import load_pem
        from pemviz.scenarios.braking import BrakingParams

        pem = load_pem()
        for m in (1.5, 1.0, 0.5, 0.0):
            t = time.perf_counter()
            r = braking_truth(pem.logit_at_gap, BrakingParams(crash_gap_m=m),
                              log_prunes=(-46.0, -50.0, -54.0, -58.0, -62.0, -66.0, -70.0, -80.0, -90.0, -100.0, -110.0))
            print(f"exact P(min gap < {m:g} m) = {math.exp(r.log_p_fail):.4e} (log {r.log_p_fail!r}), bracket width "
                  f"{r.final.relative_width:.2e}, {time.perf_counter() - t:.0f} s")
    ok = table("default run (pemviz run)", [ExperimentConfig(seed=s) for s in range(a.seeds)]) if a.seeds else True
    targeted_ok = True
    for m in (1.0, 0.5, 0.0):
        if a.targeted_seeds:
            targeted_ok &= table(f"targeted run (pemviz run --margin {m:g})",
                                 [ExperimentConfig(seed=s, margin=m) for s in range(a.targeted_seeds)])
    print(f"\nevery reported point of the default run within x{TARGET_RATIO} of the exact one and inside its interval: "
          f"{'MET' if ok else 'MISSED'}; of the targeted runs: {'MET' if targeted_ok else 'MISSED'}")
    if a.contact_seeds:
        contact_mean(a.contact_seeds)


def contact_mean(seeds: int) -> None:
    """The mean of ``seeds`` targeted contact runs at a larger budget against the exact contact point."""
    t0 = time.perf_counter()
    runs = []
    for s in range(seeds):
        cfg = ExperimentConfig(seed=1000 + s, margin=0.0, n_per_stage=1000, n_final=20000)
        pt = curve(cfg).points[0]
        runs.append(pt)
    ex = runs[0].exact_log_p
    mus = np.array([math.exp(p.estimate.log_mu_hat) for p in runs])
    reliable = [p for p in runs if p.reached]
    good = sum(math.exp(abs(p.estimate.log_mu_hat - ex)) <= TARGET_RATIO and p.estimate.covers(ex) for p in reliable)
    se = mus.std(ddof=1) / math.sqrt(seeds)
    print(f"\ncontact, {seeds} runs of pemviz run --margin 0 --n 1000 --n-final 20000 "
          f"({time.perf_counter() - t0:.0f} s): mean {mus.mean():.3e} +- {se:.2e} (standard error), "
          f"median {np.median(mus):.3e}, exact {math.exp(ex):.3e}; {len(reliable)} reliable, {good} of them "
          f"within x{TARGET_RATIO} with the exact answer inside the interval")


if __name__ == "__main__":
    main()
