"""A study: adaptive multilevel splitting from R independent replicas, with a 95 % interval from their spread.

Each replica is one whole splitting run from streams of its own, as ``pemviz run --method ams --ams-replicas R`` runs
them (:func:`pemviz.estimators.ams.replica_streams`: replica 0 is the run ``--seed s`` makes with one replica). The
estimate is the replicas' mean p_bar (a replica that dies out counts 0), unbiased as each p_hat_r is (Brehier,
Gazeau, Goudenege, Lelievre & Rousset, Ann. Appl. Probab. 26(6), 2016); its interval and verdict are pemviz's
(:func:`pemviz.estimators.ams.replicas_interval`, after Cerou, Guyader, Lelievre & Pommier, J. Chem. Phys. 134, 2011).

Intervals compared (:func:`intervals`; their coverage measured by ``--coverage`` on scenes with an exact answer):

- ``t``: Student-t on p_bar, ``p_bar -+ t_{R-1} s / sqrt(R)`` (a lower end <= 0 backs no interval: a bound only);
- ``log-t`` (chosen, pemviz's: it always backs an interval and covers best, below): the same relative half-width on
  the log scale (delta method), ``p_bar exp(-+ t_{R-1} s / (sqrt(R) p_bar))``, always positive;
- ``boot-t``: a bootstrap-t (studentised) interval of the mean, 2,000 resamples of the R replicas;
- ``pemviz`` (what ``--ams-replicas`` prints; files that keep each replica's ``ess``): log-t with p_bar's relative
  variance at least the replicas' own genealogies', sum_r p_r^2 v_r / (R p_bar)^2.

Measured (docs/validation.md, "Splitting with independent replicas"): the delta-method interval holds the exact
answer in 93 % of 1,050 runs (toy-1e-3 and the crowd, R = 4 and 8), Student-t on p_bar in 82 %, the bootstrap-t in 74
%; at the crossing's 1e-4 rung R = 4 x 400 gives median error 0.17, 9/10 within x2 and 9/10 intervals holding, at
0.38 of plain Monte Carlo's cost (one replica's cost v p / (1 - p) = 0.39 whatever R): the rung's cost target (0.2)
is not met. At the 1e-5 rung (seeds 1-10) median error 0.26, 9/10 within x2, 9/10 intervals holding (10/10 with
pemviz's floor from the replicas' own genealogy variances, ``pemviz`` in the table), 0.093 of plain Monte Carlo's
cost (0.066 whatever R) against 0.05 ("Splitting with independent replicas at the crossing's 1e-5 and 1e-6 rungs");
at R = 8 over seeds 1-20 median 0.172, 20/20 within x2, 18/20 intervals holding, none ``reliable`` outside x2, 0.081
of plain Monte Carlo's cost, about 17 CPU seconds a replica ("Splitting from 8 replicas at the crossing's 1e-5 rung,
20 seeds"). ``--first-replica F`` runs replicas F..R-1 only (a replica's streams depend on (seed, r) alone).

Commands (one process at a time on the shared machine; each appends one JSON line per replica to ``--out``, and
``--summary`` / ``--coverage`` print the tables from such files)::

    nice -n 10 python research/ams_replicas.py --scenario crossing --param brake_ttc_s=1.5 --n 400 --killed 40 \
        --replicas 4 --seeds 1 2 3 4 5 6 7 8 9 10 --out /tmp/rep-crossing-400.jsonl
    nice -n 10 python research/ams_replicas.py --scenario crossing --param brake_mps2=9.5 --param brake_ttc_s=2.0 \
        --n 400 --killed 40 --replicas 4 --seeds $(seq 1 10) --out /tmp/rep-1e-5.jsonl
    nice -n 10 python research/ams_replicas.py --scenario crossing --param brake_ttc_s=1.5 --n 200 --killed 20 \
        --replicas 8 --seeds 1 2 3 4 5 6 7 8 9 10 --out /tmp/rep-crossing-200.jsonl
    nice -n 10 python research/ams_replicas.py --problem crowd --n 200 --killed 20 --replicas 8 \
        --seeds $(seq 1 100) --out /tmp/rep-crowd-200.jsonl
    nice -n 10 python research/ams_replicas.py --problem crowd --n 400 --killed 40 --replicas 4 \
        --seeds $(seq 1 100) --out /tmp/rep-crowd-400.jsonl
    nice -n 10 python research/ams_replicas.py --problem toy-1e-3 --score robustness --n 100 --killed 10 \
        --replicas 8 --seeds $(seq 1 200) --out /tmp/rep-toy-100.jsonl
    nice -n 10 python research/ams_replicas.py --scenario cut-in --n 200 --killed 20 --replicas 4 --seeds 1
    python research/ams_replicas.py --summary /tmp/rep-crossing-400.jsonl --reference 1.294e-4 --replicas 4 1
    python research/ams_replicas.py --coverage /tmp/rep-crowd-200.jsonl --exact 3.39835e-5 --replicas 4 8
    python -m pytest research/tests/test_ams_replicas.py
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pemviz.core.problems import Problem
from pemviz.estimators.ams import Splitting, replicas_interval, run_ams
from scipy import stats

LEVEL = 0.95
BOOT = 2_000


@dataclass(frozen=True)
class Replica:
    """One replica's outcome: p_hat (0 after an extinction or with no failure), its rollout-equivalents (the
    look-ahead's steps included), its failures and the verdict splitting gave it alone."""

    seed: int
    r: int
    n: int
    p_hat: float
    cost: int
    failures: int
    verdict: str
    ess: float = math.nan
    """The replica's own ESS, 1 / its relative variance from its genealogy (:func:`pemviz.estimators.ams.ams_estimate`;
    nan in files written before it was kept)."""
    cpu_s: float = math.nan
    """The replica's CPU seconds in its process (``time.process_time``; nan in files written before it was kept)."""
    wall_s: float = math.nan
    """Its wall seconds (nan in files written before it was kept)."""


def replica(
    problem: Problem, n: int, killed: int, seed: int, r: int, score: str = "robustness", max_iterations: int = 100_000
) -> tuple[Replica, Splitting]:
    """Run replica r of ``seed`` (N particles, k killed, ranked by the ``ams_score`` named ``score``) to its end, as
    ``--method ams --ams-replicas R`` runs it (:func:`pemviz.estimators.ams.run_ams`)."""
    cpu, wall = time.process_time(), time.perf_counter()
    sp = run_ams(problem, n, killed, seed, max_iterations, score, replica=r)
    e = sp.estimate()
    p = math.exp(e.log_mu_hat) if e.log_mu_hat > -math.inf else 0.0
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    return Replica(seed, r, n, p, sp.n_simulations, e.n_failures, e.verdict, e.ess, round(cpu, 2), round(wall, 2)), sp


def own_variances(run: list[Replica]) -> np.ndarray | None:
    """Each replica's own relative variance 1 / ESS (its genealogy's; 0 with no failure), float64 [R]; None when a
    file predates it."""
    ess = np.array([x.ess for x in run])
    return None if np.isnan(ess).any() else np.where(ess > 0, 1.0 / np.where(ess > 0, ess, 1.0), 0.0)


def intervals(
    p: np.ndarray, rng: np.random.Generator | None = None, v: np.ndarray | None = None
) -> dict[str, tuple[float, float]]:
    """The 95 % intervals of the mean of replicas ``p`` float64 [R] (module docstring), each (low, high) in
    probability (low may be <= 0 for ``t``: no interval, an upper bound); with the replicas' own relative variances
    ``v`` [R] also ``pemviz``'s (the log-t one no narrower than their genealogies say). Needs R >= 2."""
    r = p.size
    mean, sd = float(p.mean()), float(p.std(ddof=1))
    t = float(stats.t.ppf(0.5 + LEVEL / 2.0, r - 1))
    se = sd / math.sqrt(r)
    out = {"t": (mean - t * se, mean + t * se)}
    lo, hi = replicas_interval(p)[0]
    out["log-t"] = (math.exp(lo), math.exp(hi)) if mean > 0 else (0.0, 0.0)
    if v is not None:
        lo, hi = replicas_interval(p, v)[0]
        out["pemviz"] = (math.exp(lo), math.exp(hi)) if mean > 0 else (0.0, 0.0)
    rng = rng or np.random.default_rng(0)
    b = p[rng.integers(r, size=(BOOT, r))]
    bse = b.std(axis=1, ddof=1) / math.sqrt(r)
    ok = bse > 0
    z = (b.mean(axis=1)[ok] - mean) / bse[ok]
    if se > 0 and z.size > 10:
        lo_q, hi_q = np.quantile(z, [0.5 + LEVEL / 2.0, 0.5 - LEVEL / 2.0])
        out["boot-t"] = (mean - float(lo_q) * se, mean - float(hi_q) * se)
    else:
        out["boot-t"] = (mean, mean)
    return out


def load(paths: list[str]) -> list[Replica]:
    """The replicas of JSON-lines files ``paths`` (as ``--out`` writes them)."""
    return [Replica(**json.loads(line)) for path in paths for line in Path(path).read_text().splitlines() if line]


def groups(reps: list[Replica], size: int, by_seed: bool) -> list[list[Replica]]:
    """Runs of ``size`` replicas: per seed its replicas 0..size-1 (``by_seed``), or consecutive disjoint groups of
    one pool (the coverage study's: one seed's many replicas)."""
    if by_seed:
        seeds = sorted({x.seed for x in reps})
        per = {s: sorted((x for x in reps if x.seed == s), key=lambda x: x.r) for s in seeds}
        return [per[s][:size] for s in seeds if len(per[s]) >= size]
    pool = sorted(reps, key=lambda x: (x.seed, x.r))
    return [pool[i : i + size] for i in range(0, len(pool) - size + 1, size)]


def table(runs: list[list[Replica]], p_true: float, show: bool = True) -> dict[str, float]:
    """Per run (a group of replicas) its p_bar and intervals against ``p_true``; returns the study's row."""
    errors, within, cost = [], 0, []
    held = {"t": 0, "log-t": 0, "boot-t": 0, "pemviz": 0}
    printed = dict.fromkeys(held, 0)
    reliable_out = reliable = reliable_held = 0
    for i, run in enumerate(runs):
        p = np.array([x.p_hat for x in run])
        mean = float(p.mean())
        ratio = mean / p_true
        errors.append(abs(ratio - 1.0))
        within += 0.5 <= ratio <= 2.0
        cost.append(sum(x.cost for x in run))
        if p.size < 2:  # one replica: the method's own run, its own verdict (its interval is not kept)
            reliable += run[0].verdict == "reliable"
            reliable_out += run[0].verdict == "reliable" and not 0.5 <= ratio <= 2.0
            continue
        ivs = intervals(p, np.random.default_rng(i), own_variances(run))
        for name, (lo, hi) in ivs.items():
            backed = lo > 0 and hi > lo
            printed[name] += backed
            held[name] += backed and lo <= p_true <= hi
        said = replicas_interval(p, own_variances(run))[1]
        reliable += said == "reliable"
        reliable_out += said == "reliable" and not 0.5 <= ratio <= 2.0
        lo, hi = ivs.get("pemviz", ivs["log-t"])
        reliable_held += said == "reliable" and lo <= p_true <= hi
        if show:
            lo, hi = ivs.get("pemviz", ivs["log-t"])
            print(
                f"seed {run[0].seed}: p_bar {mean:.3e} (x{ratio:.2f}) [{lo:.3e}, {hi:.3e}] {said}; replicas/p "
                + " ".join(f"{x.p_hat / p_true:.2f}" for x in run)
                + f"; cost {cost[-1]:,}"
            )
    m = float(np.median(errors))
    plain = (0.6745 / m) ** 2 * (1.0 - p_true) / p_true if m > 0 else math.inf
    each = np.array([x.p_hat / p_true for run in runs for x in run])
    v = float(np.mean(np.square(each - 1.0)))  # one replica's relative variance, about the reference
    per = float(np.mean([x.cost for run in runs for x in run]))
    row = {
        "runs": len(runs),
        "median": m,
        "within": within,
        "reliable": reliable,
        "reliable_out": reliable_out,
        "cost": float(np.mean(cost)),
        "plain": plain,
        "ratio": float(np.mean(cost)) / plain,
        **{f"held {k}": held[k] for k in held},
        **{f"printed {k}": printed[k] for k in printed},
        "mean ratio": float(np.mean([sum(x.p_hat for x in r) / len(r) for r in runs])) / p_true,
        "v": v,
        "work ratio": per * v * p_true / (1.0 - p_true),
        "single median": float(np.median(np.abs(each - 1.0))),
        "single within": int(np.count_nonzero((each >= 0.5) & (each <= 2.0))),
        "single reliable out": sum(
            x.verdict == "reliable" and not 0.5 <= x.p_hat / p_true <= 2.0 for r in runs for x in r
        ),
    }
    print(
        f"R = {len(runs[0])} x N = {runs[0][0].n}, {len(runs)} runs: median rel. error {m:.3f}; within x2 {within}/"
        f"{len(runs)}; intervals holding (held/printed) t {held['t']}/{printed['t']}, log-t {held['log-t']}/"
        f"{printed['log-t']}, boot-t {held['boot-t']}/{printed['boot-t']}, pemviz {held['pemviz']}/"
        f"{printed['pemviz']}; reliable {reliable} (holding p {reliable_held}), outside x2 "
        f"{reliable_out}; cost {row['cost']:,.0f}; plain MC for that error {plain:,.0f}; ratio {row['ratio']:.3f}; "
        f"mean p_bar/p {row['mean ratio']:.3f}"
    )
    print(
        f"  each replica alone ({each.size}): median rel. error {row['single median']:.3f}; within x2 "
        f"{row['single within']}/{each.size}; reliable outside x2 {row['single reliable out']}; relative variance "
        f"{v:.3f}; cost {per:,.0f}; its cost over plain MC's at any error, cost v p / (1 - p): {row['work ratio']:.3f}"
    )
    cpu = np.array([x.cpu_s for run in runs for x in run])
    wall = np.array([x.wall_s for run in runs for x in run])
    timed = ~np.isnan(cpu)
    row["nan"] = int(np.count_nonzero(np.isnan([x.p_hat for run in runs for x in run])))
    if timed.any():
        row["cpu_s"], row["wall_s"] = float(np.median(cpu[timed])), float(np.median(wall[timed]))
        print(
            f"  time ({int(timed.sum())} replicas timed): CPU s a replica median {row['cpu_s']:.1f} (range "
            f"{cpu[timed].min():.1f}-{cpu[timed].max():.1f}), wall s median {row['wall_s']:.1f}; a run of "
            f"{len(runs[0])}: CPU about {len(runs[0]) * row['cpu_s']:.0f} s; nan estimates {row['nan']}"
        )
    return row


def problem_named(scenario: str | None, problem: str | None, params: list[str]) -> Problem:
    """A scene's problem as ``pemviz run --scenario S --param ...`` builds it, or a named toy (``build_problem``)."""
    if problem is not None:
        from pemviz.scenarios.problems import build_problem

        return build_problem(problem)
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args
    from pemviz.scenarios.registry import problem_for

    flags = [f for p in params for f in ("--param", p)]
    return problem_for(config_from_args(build_parser("run").parse_args(["run", "--scenario", scenario, *flags])))


def main(argv: list[str] | None = None) -> None:
    """Run replicas (``--out``), or print a study's table (``--summary``: runs by seed; ``--coverage``: disjoint
    groups of one pool, against ``--exact``)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scenario", default="crossing")
    ap.add_argument("--problem", help="a named toy problem instead (build_problem), e.g. crowd, toy-1e-3")
    ap.add_argument("--param", action="append", default=[])
    ap.add_argument("--score", default="lookahead")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 11)))
    ap.add_argument("--n", type=int, default=400)
    ap.add_argument("--killed", type=int, default=40)
    ap.add_argument("--replicas", type=int, nargs="+", default=[4])
    ap.add_argument("--first-replica", type=int, default=0)
    ap.add_argument("--out")
    ap.add_argument("--summary", nargs="+")
    ap.add_argument("--coverage", nargs="+")
    ap.add_argument("--reference", type=float)
    ap.add_argument("--exact", type=float)
    a = ap.parse_args(argv)
    if a.summary or a.coverage:
        reps = load(a.summary or a.coverage)
        for size in a.replicas:
            table(groups(reps, size, by_seed=bool(a.summary)), a.reference or a.exact, show=bool(a.summary))
        return
    pb = problem_named(None if a.problem else a.scenario, a.problem, a.param)
    for seed in a.seeds:
        for r in range(a.first_replica, a.replicas[0]):
            rep, _ = replica(pb, a.n, a.killed, seed, r, a.score)
            line = json.dumps(rep.__dict__)
            print(line, flush=True)
            if a.out:
                with open(a.out, "a") as f:
                    f.write(line + "\n")


if __name__ == "__main__":
    main()
