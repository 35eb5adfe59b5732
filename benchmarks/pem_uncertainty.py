"""p under the PEM's own uncertainty on braking: re-weighted estimates against the exact answer of every member.

For each member of the shipped ensemble (``pemviz/assets/ensemble_ml-nn.pt``) and each logit shift D in {-1, -0.5,
0.5, 1}, the exact p of the braking scenario under that PEM (``pemviz.scenarios.braking.truth.braking_truth``, 30-90 s
each; ``--exact`` recomputes them and prints the lines of ``KNOWN_BRAKING_LOG_P`` to keep), then ``--seeds`` default
runs with ``--pem-uncertainty``: per member the share of seeds whose re-weighted estimate lies within x1.5 of the exact
p_k and whose interval holds it, the spread printed against the exact spread, and the wall time with and without.

    python benchmarks/pem_uncertainty.py                 # 5 seeds (~1 min; the exact answers from the table)
    python benchmarks/pem_uncertainty.py --exact         # recompute the exact answers first (~20 min)
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from pemviz.config import ExperimentConfig
from pemviz.engine.experiment import Experiment
from pemviz.pem import load_pem
from pemviz.pem.ensemble import ensemble_path, load_ensemble
from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.scenarios.braking.truth import braking_exact, branching_start, miss_bound
from pemviz.scenarios.braking.truth_known import pem_fingerprint
from pemviz.scenarios.problems import PEM_SHIFTS, problem_for


def exact_answers(only: tuple[str, ...] = ()) -> None:
    """The enumeration under every member and shift, its drop thresholds set below a re-weighted guess of p (as
    ``benchmarks/rarity_sweep.py`` does: fixed thresholds keep tens of millions of sequences alive where p ~ 1e-11)."""
    pem = load_pem()
    cfg = ExperimentConfig.of(seed=0, pem_uncertainty=True)
    spread = Experiment(cfg, problem=problem_for(cfg)).run().final.pem_spread
    guesses = [a.estimate.log_mu_hat for a in (*spread.members, *spread.shifts)]
    targets = [(f"member {k}", m.logit_at_gap) for k, m in enumerate(load_ensemble(ensemble_path("ml-nn")))]
    targets += [
        (f"shift {d:+g}", lambda g, d=d: np.asarray(pem.logit_at_gap(g), dtype=np.float64) + d) for d in PEM_SHIFTS
    ]
    params = BrakingParams()
    bound = miss_bound(params, branching_start(params))
    for (label, fn), guess in zip(targets, guesses, strict=False):
        if only and label not in only:
            continue
        t = time.perf_counter()
        last = None
        for k in range(8):  # lower the drop threshold until the bracket is within 0.5 %, or the sequences too many
            try:
                last = braking_exact(fn, params, log_prune=guess - 12.0 - 4.0 * k, bound=bound)
            except RuntimeError:
                break
            if last.relative_width < 0.005 and k >= 1:
                break
        width = last.relative_width
        print(
            f'    "{pem_fingerprint(fn)}": {last.log_p_fail!r},  # {label}: {math.exp(last.log_p_fail):.4e}, bracket '
            f"width {width:.2%}, {time.perf_counter() - t:.0f} s",
            flush=True,
        )


def runs(seeds: int) -> None:
    base = [
        Experiment(ExperimentConfig.of(seed=s), problem=problem_for(ExperimentConfig.of(seed=s))) for s in range(seeds)
    ]
    t = time.perf_counter()
    for e in base:
        e.run()
    plain = (time.perf_counter() - t) / seeds
    spreads = []
    t = time.perf_counter()
    for s in range(seeds):
        cfg = ExperimentConfig.of(seed=s, pem_uncertainty=True)
        spreads.append(Experiment(cfg, problem=problem_for(cfg)).run().final.pem_spread)
    with_u = (time.perf_counter() - t) / seeds
    alts = [*spreads[0].members, *spreads[0].shifts]
    print(
        f"\n{'target':<12} {'exact p':>10} {'median est':>11} {'within x1.5':>12} {'covers':>7} {'reliable':>9} "
        f"{'median ESS':>11}"
    )
    n_within = n_cover = n_known = 0
    for i, a in enumerate(alts):
        ests = [([*sp.members, *sp.shifts])[i].estimate for sp in spreads]
        ex = a.exact_log_p
        med = float(np.median([e.log_mu_hat for e in ests]))
        if ex is not None:
            within = sum(abs(e.log_mu_hat - ex) <= math.log(1.5) for e in ests)
            cover = sum(e.covers(ex) for e in ests)
            if a.label.startswith("member"):
                n_known += 1
                n_within += within == seeds
                n_cover += cover == seeds
        else:
            within = cover = "-"
        rel = sum(e.verdict == "reliable" for e in ests)
        print(
            f"{a.label:<12} {'-' if ex is None else format(math.exp(ex), '.3e'):>10} {math.exp(med):>11.3e} "
            f"{within!s:>8}/{seeds} {cover!s:>5}/{seeds} {rel:>6}/{seeds} {np.median([e.ess for e in ests]):>11.1f}"
        )
    print(
        f"\nmembers within x1.5 in every seed: {n_within}/{n_known}; "
        f"interval holds p_k in every seed: {n_cover}/{n_known}"
    )
    for s, sp in enumerate(spreads):
        med, lo, hi = sp.spread()
        ex = sp.exact_spread()
        if ex is not None:
            print(
                f"seed {s}: spread median {math.exp(med):.3e} [{math.exp(lo):.3e}, {math.exp(hi):.3e}] vs exact "
                f"{math.exp(ex[0]):.3e} [{math.exp(ex[1]):.3e}, {math.exp(ex[2]):.3e}]: ratios "
                f"{math.exp(abs(med - ex[0])):.3f}, {math.exp(abs(lo - ex[1])):.3f}, {math.exp(abs(hi - ex[2])):.3f}"
            )
    print(f"\nwall time per run: {plain:.2f} s plain, {with_u:.2f} s with --pem-uncertainty (x{with_u / plain:.2f})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--exact", action="store_true", help="recompute the exact answers first")
    ap.add_argument(
        "--only", default="", help="with --exact: these targets only, comma-separated ('member 3,shift +1')"
    )
    a = ap.parse_args()
    if a.exact:
        exact_answers(tuple(x.strip() for x in a.only.split(",") if x.strip()))
    runs(a.seeds)


if __name__ == "__main__":
    main()
