"""Are verdicts honest on the cut-in? Every fixed method and the default sampler, several seeds, against the cut-in's
plain Monte Carlo reference: counts of nan, of each verdict, of intervals that hold the reference, and of runs that
say "reliable" with the reference outside a factor of 2 (a wrong claim).

    python benchmarks/verdict_study.py                 # 70 runs, about 6 min on 2 cores
    python benchmarks/verdict_study.py --seeds 3 --jobs 2

Exit 1 if any run prints nan or says "reliable" when wrong.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import Counter
from concurrent.futures import ProcessPoolExecutor


def one(job: tuple[str, int | None, int]) -> dict:
    """One cut-in run of ``(method, N or None for the default, seed)``, summarised."""
    from pemviz.config import ExperimentConfig
    from pemviz.core.problems import problem_for
    from pemviz.engine import Experiment
    from pemviz.engine.resources import torch_threads

    method, n, seed = job
    cfg = ExperimentConfig(scenario="cut-in", method=method, seed=seed, **({} if n is None else {"n_per_stage": n}))
    problem = problem_for(cfg)
    ref = problem.reference.log_p
    with torch_threads(1, blas=1):
        e = Experiment(cfg, problem=problem).run().final.estimate
    values = (e.log_mu_hat, e.ess, *e.log_ci)
    return {"method": method, "n": n, "seed": seed, "verdict": e.verdict, "covers": e.covers(ref),
            "nan": any(math.isnan(v) for v in values), "within2": abs(e.log_mu_hat - ref) <= math.log(2.0)}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--jobs", type=int, default=2)
    a = p.parse_args()
    jobs = [("adaptive", None, s) for s in range(a.seeds)]
    jobs += [(m, n, s) for m in ("mc", "naive50", "mixed50") for n in (100, 1000) for s in range(a.seeds)]
    with ProcessPoolExecutor(a.jobs) as ex:
        runs = list(ex.map(one, jobs))
    print("| method | N | runs | verdicts | interval holds the reference | within x2 | nan | reliable when wrong |")
    print("|---|---|---|---|---|---|---|---|")
    bad = 0
    for key in dict.fromkeys((r["method"], r["n"]) for r in runs):
        g = [r for r in runs if (r["method"], r["n"]) == key]
        wrong = sum(r["verdict"] == "reliable" and not r["within2"] for r in g)
        nan = sum(r["nan"] for r in g)
        bad += wrong + nan
        verdicts = ", ".join(f"{v} {c}" for v, c in Counter(r["verdict"] for r in g).items())
        print(f"| {key[0]} | {key[1] or 'default'} | {len(g)} | {verdicts} | {sum(r['covers'] for r in g)} "
              f"| {sum(r['within2'] for r in g)} | {nan} | {wrong} |")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
