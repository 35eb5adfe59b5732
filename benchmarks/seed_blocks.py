"""How much a median over a few seeds says: the spread of block medians of the relative error.

Reads the runs of a ``pemviz validate`` folder (its runs.jsonl) and prints, per problem and method, the relative
error |mu_hat / p - 1| against the exact answer over all seeds (median, RMS, largest, 95 % intervals that hold the
truth), the median of each block of ``--block`` consecutive seeds, and the chance that the median of ``--block``
seeds is at most ``--threshold``: the fraction of 100,000 bootstrap draws of ``--block`` seeds (Efron 1979) from
the observed ones whose median is. A median over ten seeds of a sampler whose true median is at the threshold
passes about half the time, so a check on ten seeds says little about a sampler near it.

    pemviz validate --problems main --baselines "" --seeds 200 --n-final 100 --jobs 2 --out /tmp/v200
    python benchmarks/seed_blocks.py /tmp/v200 --block 10 --threshold 0.03
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np
from pemviz.core.estimate import relative_error
from pemviz.studies.exact_answers import exact_answer
from pemviz.studies.validation import RUNS_FILE, read_records

DRAWS = 100_000
"""Bootstrap draws of a block of seeds."""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="a pemviz validate --out folder")
    ap.add_argument("--block", type=int, default=10, help="seeds per block (default 10)")
    ap.add_argument("--threshold", type=float, default=0.03, help="median relative error to pass (default 0.03)")
    args = ap.parse_args()
    if args.block < 1 or not args.threshold > 0.0:
        sys.exit(f"seed_blocks: --block {args.block} / --threshold {args.threshold}: need block >= 1, threshold > 0")
    runs = args.folder / RUNS_FILE
    records = read_records(runs)
    if not records:
        sys.exit(f"seed_blocks: {runs}: no runs (give the --out folder of a pemviz validate run)")
    groups: dict[tuple[str, str, str], dict[int, tuple[float, bool]]] = {}
    truths: dict[str, float] = {}
    for key, rec in records:  # runs of one setting: the job key without its seed (a resumed study may hold several)
        job = json.loads(key)
        setting = json.dumps({k: v for k, v in job.items() if k != "seed"}, sort_keys=True)
        if rec.problem not in truths:
            try:
                truths[rec.problem] = exact_answer(rec.problem).log_p_fail
            except ValueError as e:  # a problem this pemviz does not know
                sys.exit(f"seed_blocks: {runs}: {e}")
        lt = truths[rec.problem]
        by_seed = groups.setdefault((rec.problem, rec.method, setting), {})
        by_seed[rec.seed] = (relative_error(rec.log_mu_hat, lt), rec.covers(lt))
    rng = np.random.default_rng(0)
    for (problem, method, _), by_seed in groups.items():
        seeds = sorted(by_seed)
        err = np.array([by_seed[s][0] for s in seeds])
        covered = sum(by_seed[s][1] for s in seeds)
        print(
            f"{problem} / {method}: {len(seeds)} seeds ({seeds[0]}..{seeds[-1]}): median relative error "
            f"{np.median(err):.4f}, RMS {math.sqrt(float(np.mean(err ** 2))):.4f}, largest {err.max():.3f}; "
            f"95 % interval holds the truth {covered}/{len(seeds)}"
        )
        blocks = [err[i : i + args.block] for i in range(0, len(err) - args.block + 1, args.block)]
        if blocks:
            print(
                f"  medians of {len(blocks)} blocks of {args.block} seeds: "
                + " ".join(f"{np.median(b):.3f}" for b in blocks)
            )
        medians = np.median(rng.choice(err, size=(DRAWS, args.block)), axis=1)
        print(
            f"  P(median of {args.block} seeds <= {args.threshold:g}) = {np.mean(medians <= args.threshold):.2f} "
            f"(bootstrap, {DRAWS:,} draws)"
        )


if __name__ == "__main__":
    main()
