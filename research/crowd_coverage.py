"""A study: why the crowd's 95 % intervals held its exact answer in only 170 of 200 seeds, and what holds 95 %.

For each seed it runs ``pemviz run --scenario crowd --seed S`` (the default sampler, no recording; what
``benchmarks/scene_neutral.py`` runs) and appends one JSON line to ``--out``: which step answered (the first
cross-entropy stages, their retry at 4N, plain Monte Carlo), the printed interval and whether it holds the exact
answer, the side of a miss, ESS, k-hat, failures, N, the relative half-width, and the answer's terms: each pooled
part's size n_k, its lambda_k and the log terms log(1[fail] w lambda_k N / n_k) of its failures (nats), so that other
intervals can be computed from the same runs without running them again (``--intervals``).

Commands (one process at a time on the shared machine)::

    nice -n 10 python research/crowd_coverage.py --seeds 200 --out /tmp/crowd-cov.jsonl
    python research/crowd_coverage.py --summary /tmp/crowd-cov.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def one_run(seed: int, scenario: str = "crowd", skip_plain: bool = False) -> dict:
    """One default run of ``scenario`` at ``seed`` and what it answered, with its pooled parts (module docstring);
    ``skip_plain``: where the default would draw plain Monte Carlo, stop there and record ``plain-skipped`` (its
    Clopper-Pearson interval is exact and no change to the stages' interval touches it)."""
    import pemviz.engine.experiment as experiment
    import pemviz.estimators.base as base
    import pemviz.estimators.fallback as fallback
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args
    from pemviz.scenarios.registry import problem_for

    built: list = []
    pools: dict = {}
    original_build, original_pool = experiment.build_estimator, base.pool

    def build(*args, **kwargs):
        est = original_build(*args, **kwargs)
        built.append(est)
        return est

    def pool(parts, stage_weights=None):
        est = original_pool(parts, stage_weights)
        n = sum(lw.size for lw, _, _ in parts)
        lam = (
            np.array([lw.size for lw, _, _ in parts], float) / n
            if stage_weights is None
            else np.asarray(stage_weights, float)
        )
        pools[(est.n, est.n_failures, round(est.log_mu_hat, 9))] = [
            {
                "n": int(lw.size),
                "lam": float(lam_k),
                "log_terms": (lw[f] + math.log(lam_k * n / lw.size)).tolist(),
            }
            for (lw, f, _), lam_k in zip(parts, lam, strict=True)
        ]
        return est

    skipped: list = []
    original_start = fallback.PlainFallback._start

    def start(self):
        if self.before is not None and not self.before.interval_backed:
            skipped.append(True)
            return None
        return original_start(self)

    experiment.build_estimator, base.pool = build, pool
    if skip_plain:
        fallback.PlainFallback._start = start
    try:
        cfg = config_from_args(build_parser("run").parse_args(["run", "--scenario", scenario, "--seed", str(seed)]))
        problem = problem_for(cfg)
        truth = float(problem.exact_log_p)
        final = experiment.Experiment(cfg, problem=problem).run().final
    finally:
        experiment.build_estimator, base.pool = original_build, original_pool
        fallback.PlainFallback._start = original_start
    e = final.estimate
    fb = built[0]
    retried = getattr(fb, "retry", None) is not None
    answered = "plain-skipped" if skipped else "plain" if e.plain_mc else ("retry" if retried else "first")
    lo, hi = e.shown_log_ci
    key = (e.n, e.n_failures, round(e.log_mu_hat, 9))
    return {
        "seed": seed,
        "truth": truth,
        "log_mu": e.log_mu_hat,
        "lo": lo,
        "hi": hi,
        "backed": bool(e.interval_backed),
        "holds": bool(e.interval_backed and lo <= truth <= hi),
        "side": "" if lo <= truth <= hi else ("high" if lo > truth else "low"),
        "verdict": e.verdict,
        "answered": answered,
        "first_verdict": None if getattr(fb, "first", None) is None else fb.first.verdict,
        "ess": e.ess,
        "khat": e.khat,
        "n": e.n,
        "nf": e.n_failures,
        "rel_half_width": e.rel_half_width,
        "sims": int(final.n_simulations),
        "parts": pools.get(key),
    }


def tail_table(ks: list[float], sizes: list[int], reps: int, share: float = 0.4, seed: int = 3) -> list[float]:
    """For each tail shape k in ``ks``: the largest over ``sizes`` of the 97.5 % quantile of -z, z = (log mu_hat - log
    mu) / (se / mu_hat), the studentised log-mean of N terms 1[fail] w with P(fail) = ``share`` and w generalized
    Pareto with shape k (exponential at k = 0), ``reps`` replications each: the multiplier an upper end needs to hold
    mu in 97.5 % of runs (the table of :data:`pemviz.core.confidence.TAIL_QUANTILES`)."""
    rng = np.random.default_rng(seed)
    table = []
    for k in ks:
        worst = 0.0
        for n in sizes:
            nf = rng.binomial(n, share, size=reps)
            z = np.empty(reps)
            for i in range(reps):
                u = rng.random(nf[i])
                w = np.expm1(-k * np.log(u)) / k if k > 0 else -np.log(u)
                m = w.sum() / n
                var = (np.sum(w * w) - n * m * m) / (n - 1)
                z[i] = (math.log(m) - math.log(share / (1.0 - k))) / (math.sqrt(var / n) / m)
            worst = max(worst, float(-np.quantile(z, 0.025)))
        table.append(round(worst, 2))
        print(f"k {k:.2f}: {worst:.2f}", flush=True)
    return table


def interval_now(row: dict, tail: bool = True) -> tuple[float, float] | None:
    """The interval the current :func:`pemviz.core.estimate.estimate` prints from a row's recorded terms (natural
    logs), with ``tail`` False the symmetric log-scale t interval of before, or None: plain Monte Carlo (its
    Clopper-Pearson interval does not change) or no terms."""
    from pemviz.core.confidence import log_mean_interval
    from pemviz.core.diagnostics import pareto_khat

    if row["parts"] is None or row["answered"] in ("plain", "plain-skipped"):
        return None
    n = sum(p["n"] for p in row["parts"])
    log_y = np.full(n, -np.inf)
    terms = np.concatenate([np.asarray(p["log_terms"], dtype=np.float64) for p in row["parts"]])
    log_y[: terms.size] = terms
    _, lo, hi = log_mean_interval(log_y, pareto_khat(log_y) if tail else math.nan)
    return min(lo, 0.0), min(hi, 0.0)


def summary(rows: list[dict]) -> None:
    """Coverage by step as recorded and with the current interval, the misses one by one."""
    print(f"runs {len(rows)}, intervals holding {sum(r['holds'] for r in rows)}/{sum(r['backed'] for r in rows)}")
    now: dict[int, bool] = {}
    old: dict[int, bool] = {}
    for r in rows:
        for held, tail in ((now, True), (old, False)):
            ci = interval_now(r, tail)
            held[r["seed"]] = r["holds"] if ci is None else bool(r["backed"] and ci[0] <= r["truth"] <= ci[1])
    for step in ("first", "retry", "plain", "plain-skipped"):
        sub = [r for r in rows if r["answered"] == step]
        if sub:
            print(
                f"  {step}: {len(sub)} runs, {sum(r['backed'] for r in sub)} intervals, {sum(r['holds'] for r in sub)}"
                f" holding as recorded, {sum(old[r['seed']] for r in sub)} with the symmetric one, "
                f"{sum(now[r['seed']] for r in sub)} with the current one"
            )
    print("misses: seed answered side ratio ess khat failures n rel.half-width(recorded) held-now")
    for r in rows:
        if r["backed"] and not (old[r["seed"]] and now[r["seed"]]):
            print(
                f"{r['seed']} {r['answered']} {r['side']} {math.exp(r['log_mu'] - r['truth']):.3f} {r['ess']:.1f} "
                f"{r['khat']:.2f} {r['nf']} {r['n']} {r['rel_half_width']:.3f} {now[r['seed']]}"
            )
    widths = [
        (math.exp(ci[1] - r["log_mu"]) - math.exp(ci[0] - r["log_mu"])) / 2.0
        for r in rows
        if (ci := interval_now(r)) is not None
    ]
    before = [
        (math.exp(ci[1] - r["log_mu"]) - math.exp(ci[0] - r["log_mu"])) / 2.0
        for r in rows
        if (ci := interval_now(r, tail=False)) is not None
    ]
    if widths:
        print(f"median relative half-width: symmetric {np.median(before):.3f}, current {np.median(widths):.3f}")
    ratios = [math.exp(r["log_mu"] - r["truth"]) for r in rows]
    print(f"median relative error {np.median(np.abs(np.array(ratios) - 1.0)):.4f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=200)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--scenario", default="crowd")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--skip-plain", action="store_true", help="stop where plain Monte Carlo would be drawn")
    ap.add_argument("--summary", type=Path)
    ap.add_argument("--table", action="store_true", help="print the tail quantiles of the interval's upper end")
    a = ap.parse_args(argv)
    if a.table:
        print(tail_table([round(0.1 * i, 1) for i in range(10)], [500, 2000, 8000], 20000))
        return 0
    if a.summary is not None:
        summary([json.loads(line) for line in a.summary.read_text().splitlines() if line.strip()])
        return 0
    from pemviz.engine.resources import torch_threads

    with torch_threads(1, blas=1):  # one torch thread: a second only adds synchronisation on 2 cores
        for seed in range(a.first_seed, a.first_seed + a.seeds):
            row = one_run(seed, a.scenario, a.skip_plain)
            print(
                f"seed {seed}: {row['answered']} x{math.exp(row['log_mu'] - row['truth']):.3f} {row['verdict']} "
                f"{'holds' if row['holds'] else 'MISS ' + row['side']}",
                flush=True,
            )
            if a.out is not None:
                with a.out.open("a") as f:
                    f.write(json.dumps(row) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
