"""Before/after of the opt-in sampler improvements (issue 6), one at a time, against exact answers.

Starts from the paper's settings and switches the ``improved`` preset's fields on cumulatively, in the order
below; prints, per problem and step, the median relative error of mu_hat over the seeds, how many seeds
are within a factor 2 of the truth, median failures of the final batch and median wall time. Every run
simulates 1,200 rollouts (100 pretraining + 10 x 100 + 100).

    python research/truth_sampler_improvements.py                       # main + toy, 10 seeds, 2 processes
    python research/truth_sampler_improvements.py --problems main --seeds 5 --jobs 1
"""

from __future__ import annotations

import argparse
import math
import os
import time

import numpy as np
from pemviz.core.estimate import relative_error
from pemviz.studies.exact_answers import exact_answer
from pemviz.studies.validation import Job, run_jobs

STEPS: tuple[tuple[str, dict], ...] = (
    ("paper", {}),
    ("+ proposal_inputs=state", {"proposal_inputs": "state"}),
    ("+ proposal_window", {"proposal_window": True}),
    ("+ weights_until_failure", {"weights_until_failure": True}),
    ("+ smoothing_at_failure=1", {"smoothing_at_failure": 1.0}),
    ("+ elite_ties=random", {"elite_ties": "random"}),
    ("+ pretrain_cap=0.9", {"pretrain_cap": 0.9}),
    ("+ defensive=0.2 (= improved)", {"defensive": 0.2}),
)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problems", default="main,toy", help="comma-separated problems of pemviz validate")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args()
    problems = [p for p in args.problems.split(",") if p]
    print(
        f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; {args.seeds} seeds; "
        f"{args.jobs} process(es)"
    )
    truths = {p: exact_answer(p) for p in problems}
    jobs, fields = [], {}
    for label, change in STEPS:
        fields = {**fields, **change}
        for p in problems:
            jobs += [Job(p, label, tuple(sorted(fields.items())), s) for s in range(args.seeds)]
    t0 = time.perf_counter()
    records = run_jobs(jobs, args.jobs)
    print(f"\n{len(jobs)} runs in {time.perf_counter() - t0:.0f} s\n")
    print(
        "| problem | sampler | median rel. error | within x2 | median mu_hat / truth | median failures "
        "| median wall s |"
    )
    print("|---|---|---:|---:|---:|---:|---:|")
    for p in problems:
        lt = truths[p].log_p_fail
        for label, _ in STEPS:
            rs = [r for r in records if r.problem == p and r.method == label]
            errs = [relative_error(r.log_mu_hat, lt) for r in rs]
            ratio = float(np.median([math.exp(r.log_mu_hat - lt) if r.log_mu_hat > -math.inf else 0.0 for r in rs]))
            within = sum(abs(r.log_mu_hat - lt) <= math.log(2.0) for r in rs)
            print(
                f"| {p} | {label} | {np.median(errs):.3f} | {within}/{len(rs)} | {ratio:.3g} | "
                f"{np.median([r.n_failures for r in rs]):g}/{rs[0].n} | {np.median([r.wall_s for r in rs]):.1f} |"
            )


if __name__ == "__main__":
    main()
