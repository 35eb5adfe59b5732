"""Why not a general rare-event library? pemviz's braking problem given to OpenTURNS as a black-box limit state.

The braking job (``pemviz.scenarios.problems.build_problem("main")``: T = 100 steps of 0.05 s, the shipped PEM as the
camera's detector, failure = the gap drops below 2 m) is written as a limit state g(u) on the unit hypercube U(0, 1)^T:

- step t detects iff ``log u_t <= log_expit(logit p_PEM(state_t))``, i.e. iff u_t <= p_PEM(detect | state_t), in
  log space exactly as pemviz draws its rollouts (:mod:`pemviz.scenarios.braking.batched`), so the same uniforms give
  the same detections bit for bit; u_t <= 0 counts as log u_t = -inf (detect), u_t >= 1 never detects, so g is defined
  on all of R^T (NAIS's Gaussian kernels put points outside the cube, where the input density and so the weight is 0);
- the ego reacts through pemviz's batched twin :class:`pemviz.scenarios.braking.batched.BatchedBraking`;
- g(u) = the classic STL robustness of ``G[0,99](d >= 2)`` of the gap trace (metres), computed by pemviz's own
  :meth:`pemviz.core.problems.Problem.robustness` on a :class:`pemviz.core.rollouts.RolloutBatch`. Failure: g(u) < 0,
  exact probability 1.984e-15 (``problem.exact_log_p``, an enumeration of the detection sequences).

OpenTURNS (https://openturns.github.io/openturns/latest/, version 1.27) then gets the event
``ThresholdEvent(CompositeRandomVector(PythonFunction(g), JointDistribution([Uniform(0, 1)] * 100)), Less(), 0)``
and runs, on each seed (``ot.RandomGenerator.SetSeed``) and evaluation budget:

- ``subset``: ``ot.SubsetSampling``, subset simulation (Au & Beck, "Estimation of small failure probabilities in
  high dimensions by subset simulation", Probabilistic Engineering Mechanics 16(4), 2001) with conditional
  probability p0 = 0.1 and OpenTURNS's component-wise Metropolis in standard normal space;
- ``nais``: ``ot.NAIS``, non-parametric adaptive importance sampling with Gaussian kernels and Silverman's
  bandwidth (Morio & Balesdent, "Estimation of Rare Event Probabilities in Complex Aerospace and Other Systems",
  Woodhead 2015; the improved CE family of Papaioannou, Geyer & Straub, "Improved cross entropy-based importance
  sampling with a flexible mixture model", Reliability Engineering & System Safety 191, 2019), quantile level 0.1.
  OpenTURNS 1.27's NAIS refuses a bounded input distribution ("only adapted to unbounded distribution"), so it gets
  the same event written in standard normal space: z ~ N(0, I_100), g(Phi(z)) (the map SubsetSampling and
  StandardSpaceCrossEntropyImportanceSampling apply themselves);
- ``ce-standard``: ``ot.StandardSpaceCrossEntropyImportanceSampling``, the cross-entropy method (Rubinstein &
  Kroese, "The Cross-Entropy Method", Springer 2004; "Simulation and the Monte Carlo Method", 3rd ed., Wiley 2017)
  with an independent Normal auxiliary density in standard normal space, quantile level 0.1;
- ``ce-physical``: ``ot.PhysicalSpaceCrossEntropyImportanceSampling`` with independent Beta(a_t, b_t) marginals on
  [0, 1] (200 parameters fitted by OpenTURNS's default NLopt LD_LBFGS at each level), quantile level 0.1;

and beside them ``pemviz``: pemviz's default sampler (``ExperimentConfig.of()``: state-dependent CE with K = 10,
N = 100, N_e = 1000 plus pretraining, ~2,100 simulations) on the same seeds.

Budgets: a run at p0 = 0.1 needs ~log(p) / log(0.1) = 15 levels for p = 2e-15, so each OpenTURNS algorithm gets
budget / 15 samples per level (140, 1,400 and 14,000 at 2,100, 21,000 and 210,000); the evaluations it really spent
are counted in the PythonFunction. SubsetSampling draws its level as 10 blocks of N p0 points, one Markov chain step
per block (a block of N points would give chains of length 1). A run is stopped as ``stalled`` when it has spent
``--eval-cap`` times its budget or ``--timeout`` seconds (and killed, as a stall, if it has not returned one minute
later); an exception is recorded as ``crashed``. Crashed and stalled runs count as mu_hat = 0 (relative error 1).

Table, per method and budget over the seeds: runs that returned an estimate > 0 / = 0 / crashed / stalled, the runs
that returned one from a last level above g = 0 ("short": SubsetSampling ends so when no sample lies strictly below
a level, a plateau of the piecewise-constant g), the median relative error |mu_hat / p - 1|, the seeds within a
factor 2 of p, the median of mu_hat / p, the mean evaluations, the median wall time of a run (s), and the relative
variance x evaluations, var(mu_hat) / p^2 x mean evaluations over the runs that returned (the work-normalised
relative variance: lower is better).

    pip install -e ".[bench]"                    # openturns
    python benchmarks/openturns_braking.py       # 10 seeds x 3 budgets x 4 OpenTURNS methods + pemviz; ~1-2 h
    python benchmarks/openturns_braking.py --seeds 3 --budgets 2100 --methods subset,pemviz   # a quick look

It writes ``table.md`` and ``runs.json`` (every run: seed, status, mu_hat, evaluations, levels, wall time, error)
into ``--out`` (default ``benchmarks/out/openturns/``, never committed: the folder gets a ``.gitignore`` of ``*``).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import multiprocessing
import os
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pemviz.core.detectors import action_log_prob
from pemviz.core.problems import Problem
from pemviz.core.rollouts import RolloutBatch
from pemviz.scenarios.braking.batched import BatchedBraking
from pemviz.scenarios.braking.simulator import OBSERVATION_NAMES, BrakingParams
from pemviz.scenarios.problems import build_problem
from scipy.special import log_expit, ndtr

T = 100
"""Steps of a rollout: the dimension of the input u."""
OT_METHODS = ("subset", "nais", "ce-standard", "ce-physical")
METHODS = (*OT_METHODS, "pemviz")
BUDGETS = (2_100, 21_000, 210_000)
RHO = 0.1
"""Conditional probability of subset simulation and quantile level of NAIS / CE."""
LEVELS = 15
"""Levels a p0 = 0.1 run needs for p = 2e-15: ceil(log(p) / log(0.1)); sets the per-level sample size."""
KILL_GRACE_S = 60.0
"""A run that has not returned this long after its --timeout (stuck inside OpenTURNS's C++) is killed."""
OT_MISSING = "openturns is not installed: pip install -e '.[bench]'"


# -- the limit state ---------------------------------------------------------------------------------------------


@functools.cache
def braking() -> Problem:
    """pemviz's braking job with the shipped PEM (built once per process)."""
    return build_problem("main")


def rollouts(u: np.ndarray, problem: Problem | None = None) -> RolloutBatch:
    """The rollouts driven by given uniforms: detect at step t iff log u[:, t] <= log_expit(logit p_PEM(state_t)).

    Args:
        u: float64 [n, T] one uniform per rollout and step (any real: <= 0 detects, >= 1 misses).
        problem: the braking problem (None: :func:`braking`).
    Returns:
        :class:`RolloutBatch` [n, T] with observations (gap m, ego and lead speeds m/s, brake pending), detections,
        and log p = log q = log p_PEM(a_t | s_t) (nats), as :func:`pemviz.scenarios.braking.batched.simulate_batched`
        with the PEM as sampler fills it.
    """
    pb = problem or braking()
    u = np.asarray(u, dtype=np.float64)
    if u.ndim != 2 or u.shape[1] != T:
        raise ValueError(f"rollouts: u must be float64 [n, {T}], got shape {u.shape}")
    n = u.shape[0]
    with np.errstate(divide="ignore"):
        log_u = np.log(np.maximum(u, 0.0))  # log 0 = -inf: u <= 0 always detects
    sim = BatchedBraking(BrakingParams(), n)  # the "main" problem's constants
    obs = np.empty((n, T, len(OBSERVATION_NAMES)))
    detected = np.empty((n, T), dtype=bool)
    log_p = np.empty((n, T))
    for t in range(T):
        o = sim.observation(out=obs[:, t])
        logit = pb.target.detect_logit(o)
        detected[:, t] = log_u[:, t] <= log_expit(logit)
        log_p[:, t] = action_log_prob(logit, detected[:, t])
        sim.step(detected[:, t])
    return RolloutBatch(obs, detected, log_p, log_p.copy(), OBSERVATION_NAMES)


def limit_state(u: np.ndarray, problem: Problem | None = None) -> np.ndarray:
    """g(u): classic robustness of ``G[0,99](d >= 2)`` of the rollouts driven by ``u`` [n, T]; float64 [n] (metres).

    Failure iff g(u) < 0 (the gap drops below 2 m). Pure numpy, pemviz's own simulator and STL code.
    """
    pb = problem or braking()
    return pb.robustness(rollouts(u, pb), "classic")


# -- one run -----------------------------------------------------------------------------------------------------


class Stop(Exception):
    """Raised inside g when a run has spent its evaluation cap or its wall-clock time (a stall)."""


@dataclass
class Counter:
    """Counts evaluations of g and stops a run past ``cap`` evaluations or ``timeout_s`` seconds."""

    cap: int
    timeout_s: float
    normal_input: bool = False
    """The input is z ~ N(0, I_T) and u = Phi(z) (for NAIS, which refuses bounded input distributions)."""
    evaluations: int = 0
    t0: float = 0.0
    stopped: str = ""

    def __call__(self, x: Any) -> np.ndarray:
        """g on an OpenTURNS sample [n, T] -> float64 [n, 1]."""
        u = np.asarray(x, dtype=np.float64)
        if self.normal_input:
            u = ndtr(u)
        elapsed = time.perf_counter() - self.t0
        if self.evaluations + len(u) > self.cap or elapsed > self.timeout_s:
            self.stopped = (
                f"stalled: stopped after {self.evaluations} evaluations, {elapsed:.0f} s "
                f"(cap {self.cap} evaluations, {self.timeout_s:g} s)"
            )
            raise Stop(self.stopped)
        self.evaluations += len(u)
        return limit_state(u)[:, None]


@dataclass
class Run:
    """One run of one method at one budget and seed. ``mu_hat`` is nan unless ``status`` is ok or zero."""

    method: str
    budget: int
    seed: int
    status: str  # ok | zero | crashed | stalled
    mu_hat: float
    evaluations: int
    wall_s: float
    levels: int = 0
    last_threshold_m: float = math.nan
    """The threshold of the last level the run estimated (metres): 0 once it reached the failure level; above 0 when
    it returned P(g < that threshold) instead (SubsetSampling stops so when no sample lies strictly below a level)."""
    error: str = ""


def ot_algorithm(ot: Any, method: str, event: Any, n_level: int) -> Any:
    """The OpenTURNS algorithm of ``method`` on ``event`` with ``n_level`` samples per level."""
    if method == "subset":
        algo = ot.SubsetSampling(event, 2.0, RHO)  # proposal range 2 (the default), p0 = 0.1
        chains = max(1, round(n_level * RHO))
        algo.setBlockSize(chains)  # one Metropolis step of every chain per block
        algo.setMaximumOuterSampling(max(1, round(n_level / chains)))
        return algo
    if method == "nais":
        algo = ot.NAIS(event, RHO)
    elif method == "ce-standard":
        algo = ot.StandardSpaceCrossEntropyImportanceSampling(event, RHO)
    elif method == "ce-physical":
        aux = ot.JointDistribution([ot.Beta(1.0, 1.0, 0.0, 1.0)] * T)  # Beta(1, 1) on [0, 1] = U(0, 1)
        active = [k for t in range(T) for k in (4 * t, 4 * t + 1)]  # (alpha_t, beta_t); a = 0, b = 1 fixed
        bounds = ot.Interval([0.05] * (2 * T), [1000.0] * (2 * T))
        algo = ot.PhysicalSpaceCrossEntropyImportanceSampling(event, aux, active, [1.0] * (2 * T), bounds, RHO)
    else:
        raise ValueError(f"unknown OpenTURNS method {method!r}; use one of {', '.join(OT_METHODS)}")
    algo.setBlockSize(n_level)  # g sees the whole level at once
    algo.setMaximumOuterSampling(1)
    return algo


def run_openturns(method: str, budget: int, seed: int, timeout_s: float, eval_cap: float) -> Run:
    """One OpenTURNS run in this process; exceptions and stalls are recorded, not raised."""
    import openturns as ot

    counter = Counter(cap=int(eval_cap * budget), timeout_s=timeout_s, normal_input=method == "nais")
    g = ot.PythonFunction(T, 1, func_sample=counter)
    law = ot.Normal(T) if counter.normal_input else ot.JointDistribution([ot.Uniform(0.0, 1.0)] * T)
    event = ot.ThresholdEvent(ot.CompositeRandomVector(g, ot.RandomVector(law)), ot.Less(), 0.0)
    ot.RandomGenerator.SetSeed(seed)
    algo = None
    counter.t0 = time.perf_counter()
    try:
        algo = ot_algorithm(ot, method, event, max(2, round(budget / LEVELS)))
        algo.run()
        mu, status, error = float(algo.getResult().getProbabilityEstimate()), "", ""
        status = "ok" if mu > 0.0 else "zero"
    except Exception as exc:  # noqa: BLE001 -- OpenTURNS wraps g's Stop in its own exception types
        mu, status = math.nan, "stalled" if counter.stopped else "crashed"
        error = counter.stopped or (
            f"{type(exc).__name__}: " f"{str(exc).strip().splitlines()[-1] if str(exc).strip() else ''}"
        )
    wall = time.perf_counter() - counter.t0
    levels, last = 0, math.nan
    if status in ("ok", "zero"):
        levels, last = int(algo.getStepsNumber()), float(algo.getThresholdPerStep()[-1])
    return Run(method, budget, seed, status, mu, counter.evaluations, wall, levels, last, error[:300])


def _child(conn: Any, args: tuple) -> None:
    conn.send(asdict(run_openturns(*args)))
    conn.close()


def run_isolated(method: str, budget: int, seed: int, timeout_s: float, eval_cap: float) -> Run:
    """:func:`run_openturns` in a forked child, killed as a stall if it does not return by ``timeout_s`` + 60 s
    (a level's work inside OpenTURNS, e.g. NAIS's kernel mixture, cannot be interrupted from g) or if it dies."""
    ctx = multiprocessing.get_context("fork")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(send, (method, budget, seed, timeout_s, eval_cap)))
    t0 = time.perf_counter()
    proc.start()
    send.close()
    ready = recv.poll(timeout_s + KILL_GRACE_S)
    try:
        out = recv.recv() if ready else None
    except EOFError:  # the child died without an answer
        out = None
    if proc.is_alive():
        proc.kill()
    proc.join()
    if out is not None:
        return Run(**out)
    wall = time.perf_counter() - t0
    why = f"stalled: killed after {wall:.0f} s" if not ready else f"crashed: exit code {proc.exitcode}"
    return Run(method, budget, seed, why.split(":")[0], math.nan, 0, wall, error=why)


def run_pemviz(seed: int) -> Run:
    """pemviz's default sampler (``ExperimentConfig.of(seed=seed)``) on the braking job."""
    from pemviz.config import ExperimentConfig
    from pemviz.engine.events import RunFinished
    from pemviz.engine.experiment import Experiment
    from pemviz.scenarios.problems import problem_for

    cfg = ExperimentConfig.of(seed=seed)
    t0 = time.perf_counter()
    out = Experiment(cfg, problem=problem_for(cfg)).run()
    wall = time.perf_counter() - t0
    if not isinstance(out, RunFinished):
        return Run("pemviz", 0, seed, "crashed", math.nan, 0, wall, error=str(out))
    mu = math.exp(out.final.estimate.log_mu_hat)
    return Run(
        "pemviz",
        out.final.n_simulations,
        seed,
        "ok" if mu > 0 else "zero",
        mu,
        out.final.n_simulations,
        wall,
        cfg.adaptive.n_stages,
        0.0,
    )


# -- the table ---------------------------------------------------------------------------------------------------


def summarise(runs: list[Run], p: float) -> dict[str, Any]:
    """One table row of the runs of one method and budget (see the module docstring)."""
    mus = [r.mu_hat if r.status in ("ok", "zero") else 0.0 for r in runs]
    errors = [abs(m / p - 1.0) for m in mus]
    returned = [r.mu_hat for r in runs if r.status in ("ok", "zero")]
    evals = statistics.fmean(r.evaluations for r in runs)
    relvar = statistics.variance(returned) / p**2 * evals if len(returned) >= 2 else math.nan
    count = {s: sum(r.status == s for r in runs) for s in ("ok", "zero", "crashed", "stalled")}
    return {
        "runs": "/".join(str(count[s]) for s in count),
        "short": sum(r.status in ("ok", "zero") and r.last_threshold_m > 0.0 for r in runs),
        "median_rel_error": statistics.median(errors),
        "within_x2": sum(p / 2 <= m <= 2 * p for m in mus),
        "median_mu_over_p": statistics.median(mus) / p,
        "mean_evaluations": evals,
        "median_wall_s": statistics.median(r.wall_s for r in runs),
        "relvar_x_evals": relvar,
    }


def markdown(rows: list[tuple[str, int, dict[str, Any]]], n_seeds: int, p: float) -> str:
    """The Markdown table of :func:`summarise` rows."""
    head = (
        f"Braking job, p = {p:.4g}, {n_seeds} seeds. runs: estimate > 0 / = 0 / crashed / stalled; short: runs "
        "that returned an estimate from a last level above g = 0 (P(g < that level), not the failure probability). "
        "rel. var x evals measures spread, not bias: read it beside median mu_hat/p.\n\n"
        "| method | budget | runs | short | median rel. error | within x2 | median mu_hat/p | mean evaluations "
        "| median wall s | rel. var x evals |\n|---|---:|---|---:|---:|---:|---:|---:|---:|---:|\n"
    )
    lines = [
        f"| {m} | {b:,} | {s['runs']} | {s['short']} | {s['median_rel_error']:.3g} | {s['within_x2']}/{n_seeds} | "
        f"{s['median_mu_over_p']:.3g} | {s['mean_evaluations']:,.0f} | {s['median_wall_s']:.1f} | "
        f"{s['relvar_x_evals']:.3g} |"
        for m, b, s in rows
    ]
    return head + "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10, help="seeds 0..S-1 (default 10)")
    ap.add_argument("--budgets", default=",".join(map(str, BUDGETS)), help="OpenTURNS evaluation budgets")
    ap.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated, of {', '.join(METHODS)}")
    ap.add_argument("--timeout", type=float, default=300.0, help="wall-clock cap of one run, s (default 300)")
    ap.add_argument("--eval-cap", type=float, default=5.0, help="a run past this x its budget is stalled (default 5)")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "out" / "openturns", help="output folder")
    args = ap.parse_args(argv)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    budgets = [int(b) for b in args.budgets.split(",") if b.strip()]
    if bad := [m for m in methods if m not in METHODS]:
        ap.error(f"unknown method(s) {', '.join(bad)}; use {', '.join(METHODS)}")
    if any(m in OT_METHODS for m in methods):
        try:
            import openturns as ot
        except ImportError:
            print(OT_MISSING, file=sys.stderr)
            return 1
        print(f"openturns {ot.__version__}, numpy {np.__version__}, {os.cpu_count()} cores", flush=True)
    p = math.exp(braking().exact_log_p)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / ".gitignore").write_text("*\n")
    t_start, runs, rows = time.perf_counter(), [], []
    plan = [(m, b) for m in methods if m != "pemviz" for b in budgets] + [("pemviz", 0)] * ("pemviz" in methods)
    for method, budget in plan:
        group = []
        for seed in range(args.seeds):
            r = (
                run_pemviz(seed)
                if method == "pemviz"
                else run_isolated(method, budget, seed, args.timeout, args.eval_cap)
            )
            group.append(r)
            print(
                f"{method:12s} budget {r.budget:>7,} seed {seed}: {r.status:7s} mu_hat/p {r.mu_hat / p:10.4g} "
                f"evaluations {r.evaluations:>9,} levels {r.levels:2d} last level {r.last_threshold_m:6.3f} m "
                f"{r.wall_s:7.1f} s {r.error}",
                flush=True,
            )
        runs += group
        rows.append((method, budget or round(statistics.fmean(r.evaluations for r in group)), summarise(group, p)))
        (args.out / "runs.json").write_text(json.dumps({"p": p, "runs": [asdict(r) for r in runs]}, indent=1))
    table = markdown(rows, args.seeds, p)
    (args.out / "table.md").write_text(table)
    print(f"\n{table}\nwall time {time.perf_counter() - t_start:.0f} s; wrote {args.out}/table.md and runs.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
