"""Rarity sweep: every method's relative error at equal budgets on problems with an exact answer from ~1e-3 to ~1e-100.

Problems (each with its exact p_fail):
- ``toy-m<M>-<p>``: toys whose failure needs M misses in a row at a constant p(detect) (closed form (1 - p)^M);
- ``latched<shift>``: the latched-brake braking scenario with the PEM's logit moved by ``shift`` nats
  (``ShiftedPEM`` of ``research/zero_variance.py``; exact from the deterministic simulator);
- ``main<shift>``: the braking scenario itself with the shifted PEM (exact enumeration,
  :func:`pemviz.scenarios.braking.truth.braking_truth`);
- ``cut-in-moderate``: the cut-in scenario of several cars, missed and mislocated, at its moderate setting (no closed
  form: its "exact" p is the plain Monte Carlo reference of 10^7 rollouts,
  :data:`pemviz.scenarios.cut_in.scenario.MONTE_CARLO_REFERENCE`, whose own 95 % interval is +-7 %).

Methods (:func:`methods_at`, a list of (label, config fields); add a line for a new method): the default sampler
``ExperimentConfig.of()`` (2,100 simulations; ``--n-final 100``: 1,200), the ``paper`` preset with its final batch
set to the same budget, adaptive multilevel splitting with budget / 4 particles (when
:data:`pemviz.methods.BUILTIN_METHODS` has ``ams``), plain Monte Carlo with that many rollouts, and the exact
zero-variance sampler q* (``ZeroVarianceDetector`` of ``research/zero_variance.py``) where V is known (toys, latched).

Outputs under ``--out`` (default ``recordings/sweep/``; an existing file is never replaced without ``--overwrite``):
``runs.jsonl`` (one line per run, appended as it ends: ``--resume`` continues a killed sweep), ``sweep.md`` and
``sweep.csv`` (median relative error over the seeds and the simulations each method would need for a 10 % relative
error, ``N (rel. error / 0.1)^2``), ``sweep.png`` (both against log10 p) and ``sweep.rrd`` (the same series in a
rerun recording, on the timeline ``minus_log10_p``).

Usage::

    nice -n 10 python benchmarks/rarity_sweep.py --jobs 2            # full sweep (~30-40 min of CPU)
    python benchmarks/rarity_sweep.py --n-final 100 --jobs 2         # every method at 1,200 simulations (~3.5 min)
    python benchmarks/rarity_sweep.py --quick --out /tmp/sweep       # 3 small problems, 2 seeds (~1-2 min)
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import io
import json
import math
import multiprocessing as mp
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from pemviz.config import ExperimentConfig
from pemviz.core.confidence import clopper_pearson
from pemviz.core.detectors import Detector
from pemviz.core.estimate import relative_error
from pemviz.core.files import atomic_write
from pemviz.core.problems import Problem
from pemviz.engine.events import RunFinished
from pemviz.engine.experiment import Experiment
from pemviz.engine.resources import torch_threads
from pemviz.methods import BUILTIN_METHODS as CONFIG_METHODS
from pemviz.presets import PRESETS
from pemviz.scenarios.braking import truth, truth_known, truth_latched
from pemviz.scenarios.braking.problem import braking_problem
from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.scenarios.cut_in.problem import cut_in_params, cut_in_problem
from pemviz.scenarios.cut_in.scenario import MONTE_CARLO_REFERENCE
from pemviz.scenarios.toy import ToyParams
from pemviz.scenarios.toy.problem import toy_problem
from pemviz.scenarios.toy.simulator import toy_log_failure_probability
from pemviz.studies.validation import all_fields, ams_fields


def _research_module(name: str) -> Any:
    """``research/<name>.py`` loaded by its path (research/ is not a package nor a dependency), kept in sys.modules
    under ``name`` so that its objects pickle to the sweep's worker processes."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().parents[1] / "research" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


_q_star = _research_module("zero_variance")  # the zero-variance sampler q*
ShiftedPEM, ToyValue, ZeroVarianceDetector = _q_star.ShiftedPEM, _q_star.ToyValue, _q_star.ZeroVarianceDetector
draw_fixed, latched_value = _q_star.draw_fixed, _q_star.latched_value
relative_variance, rollouts_for = _q_star.relative_variance, _q_star.rollouts_for

Q_STAR = "q*"
"""The label of the exact zero-variance sampler (not a config: built from the problem's exact V)."""


def methods_at(n_final: int = ExperimentConfig.of().adaptive.n_final) -> list[tuple[str, dict[str, Any] | None]]:
    """(label, ExperimentConfig fields) per method, None for q*, all at the budget of the default sampler with a final
    batch of ``n_final`` rollouts (``n_final = 1000``: 2,100 simulations; 100: 1,200): the ``paper`` preset with its
    final batch set to that budget, Monte Carlo with that many rollouts, adaptive multilevel splitting with
    budget / 4 particles (:func:`pemviz.studies.validation.ams_fields`, when this pemviz has it) and q*.

    Raises:
        ValueError: if ``n_final`` < 1, or the budget is too small for the paper preset's stages.
    """
    if n_final < 1:
        raise ValueError(f"n_final = {n_final} is invalid: must be >= 1")
    budget = ExperimentConfig.of(n_final=n_final).n_simulations
    before_final = ExperimentConfig.of(**{**PRESETS["paper"], "n_final": 1}).n_simulations - 1
    if budget - before_final < 1:
        raise ValueError(f"n_final = {n_final} leaves the paper preset no final batch")
    methods: list[tuple[str, dict[str, Any] | None]] = [
        ("state-ce", {} if n_final == ExperimentConfig.of().adaptive.n_final else {"n_final": n_final}),
        ("paper", {**PRESETS["paper"], "n_final": budget - before_final}),  # 100 pretraining + 10 x 100 + the rest
        ("mc", {"method": "mc", "n_per_stage": budget}),
        (Q_STAR, None),
    ]
    if "ams" in CONFIG_METHODS:  # adaptive multilevel splitting, when this pemviz has it
        methods.insert(2, ("ams", ams_fields(budget)))
    return methods


METHODS = methods_at()
"""The default sweep's methods (:func:`methods_at`), each at 2,100 simulations."""

QUICK_METHODS: list[tuple[str, dict[str, Any] | None]] = [
    ("state-ce (quick)", dict(PRESETS["quick"])),
    ("mc", {"method": "mc", "n_per_stage": ExperimentConfig.of(**PRESETS["quick"]).n_simulations}),
    (Q_STAR, None),
]
"""The methods of ``--quick``: the ``quick`` preset (1,850 simulations), Monte Carlo and q* at its budget."""


# -- problems -------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Spec:
    """A sweep problem, rebuilt in each worker from these fields: ``kind`` toy | latched | main | cut-in; a toy needs
    ``misses`` and ``p_detect``; the braking problems the PEM ``shift`` (nats); the cut-in its rarity ``setting``."""

    name: str
    kind: str
    misses: int = 0
    p_detect: float = 0.0
    shift: float = 0.0
    setting: str = ""


def toy_spec(misses: int, log10_p: float) -> Spec:
    """A toy that fails iff M detections miss in a row, with p(detect) set so that (1 - p)^M = 10^log10_p."""
    p = -math.expm1(log10_p * math.log(10.0) / misses)
    return Spec(f"toy-m{misses}-1e{log10_p:g}", "toy", misses=misses, p_detect=p)


FULL: tuple[Spec, ...] = (
    toy_spec(3, -3),
    toy_spec(10, -10),
    toy_spec(30, -20),
    toy_spec(10, -30),
    toy_spec(100, -50),
    toy_spec(300, -100),
    Spec("latched-6", "latched", shift=-6.0),
    Spec("latched+0", "latched", shift=0.0),
    Spec("latched+8", "latched", shift=8.0),
    Spec("main+0", "main", shift=0.0),
    Spec("main+3", "main", shift=3.0),
    Spec("cut-in-moderate", "cut-in", setting="moderate"),
)
"""The full sweep's problems (log10 p from -1.4 to -100, and the cut-in at -4.1)."""

QUICK: tuple[Spec, ...] = (toy_spec(3, -3), toy_spec(10, -10), Spec("latched-6", "latched", shift=-6.0))
"""The ``--quick`` problems: small and fast."""


def toy_params(spec: Spec) -> ToyParams:
    safe = 2
    braking = safe + spec.misses - 1
    return ToyParams(braking + 5, braking, safe, spec.p_detect)


@cache
def _pem():
    from pemviz.pem import load_pem

    return load_pem()


@cache
def build(spec: Spec) -> tuple[Problem, Detector | None]:
    """The problem of ``spec`` and its q* (None where V is not known), built once per process."""
    if spec.kind == "toy":
        params = toy_params(spec)
        problem = toy_problem(params, name=spec.name)
        return problem, ZeroVarianceDetector(problem.target, ToyValue(params).log_value_next)
    if spec.kind == "cut-in":
        return cut_in_problem(_pem(), cut_in_params(spec.setting)), None
    pem = ShiftedPEM(_pem(), spec.shift)
    if spec.kind == "latched":
        problem = braking_problem(pem, BrakingParams(latched_brake=True))
        value = latched_value(pem.logit_at_gap)
        return problem, ZeroVarianceDetector(problem.target, value.log_value_next)
    return braking_problem(pem, BrakingParams()), None


def exact_log_p(spec: Spec) -> tuple[float, str]:
    """The exact log p_fail (nats) of ``spec`` and where it comes from (``main`` shifts: tens of seconds)."""
    if spec.kind == "toy":
        return toy_log_failure_probability(toy_params(spec)), f"closed form (1 - {spec.p_detect:.6g})^{spec.misses}"
    if spec.kind == "cut-in":
        failures, rollouts = MONTE_CARLO_REFERENCE[spec.setting]
        lo, hi = clopper_pearson(failures, rollouts)
        return (
            math.log(failures / rollouts),
            f"plain Monte Carlo, {failures:,} failures in {rollouts:,} rollouts "
            f"(95 % interval [{lo:.3g}, {hi:.3g}])",
        )
    pem = ShiftedPEM(_pem(), spec.shift)
    if spec.kind == "latched":
        return truth_latched.latched_log_failure_probability(pem.logit_at_gap).log_p_fail, "latched closed form"
    known = truth_known.known_log_failure_probability(pem.logit_at_gap)
    if known is not None:
        return known, "exact enumeration (stored)"
    guess = truth_known.KNOWN_BRAKING_LOG_P["915fec568bb72b65"] - 9.0 * spec.shift  # ~9 nats per nat of shift, measured
    ref = truth.braking_truth(pem.logit_at_gap, BrakingParams(), log_prunes=[guess - 10 - 4 * k for k in range(8)])
    f = ref.final
    return ref.log_p_fail, (
        f"exact enumeration, bracket width {f.relative_width:.2%}" f"{'' if ref.converged else ' (NOT converged)'}"
    )


# -- runs -----------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Job:
    spec: Spec
    method: str
    fields: tuple[tuple[str, Any], ...] | None
    seed: int

    def key(self) -> str:
        fields = self.fields if self.method == Q_STAR else all_fields(self.fields or ())  # defaults filled in
        return json.dumps(
            {"spec": asdict(self.spec), "method": self.method, "fields": fields, "seed": self.seed},
            sort_keys=True,
            default=str,
        )


@dataclass(frozen=True)
class Record:
    problem: str
    method: str
    seed: int
    log_mu_hat: float
    n_failures: int
    n_simulations: int
    wall_s: float


def run_job(job: Job) -> Record:
    """One method on one problem for one seed (in this process)."""
    problem, q_star = build(job.spec)
    t0 = time.perf_counter()
    if job.method == Q_STAR:
        assert q_star is not None
        d = draw_fixed(problem, q_star, dict(job.fields or ())["n"], seed=job.seed)
        e, n_sim = d.estimate, d.estimate.n
    else:
        cfg = ExperimentConfig.of(**dict(job.fields or ()), seed=job.seed)
        with torch_threads(1):
            res = Experiment(cfg, problem=problem).run()
        assert isinstance(res, RunFinished)
        e, n_sim = res.final.estimate, res.final.n_simulations
    return Record(job.spec.name, job.method, job.seed, e.log_mu_hat, e.n_failures, n_sim, time.perf_counter() - t0)


def budget_of(methods: Sequence[tuple[str, dict | None]]) -> int:
    """The simulations of the first method's run: the budget every method of the sweep gets."""
    return ExperimentConfig.of(**(methods[0][1] or {})).n_simulations


def jobs_for(specs: Sequence[Spec], methods: Sequence[tuple[str, dict | None]], n_seeds: int) -> list[Job]:
    """Every (problem, method, seed); q* only where the problem has one, at the first method's budget; on the cut-in
    (several objects a step) not the methods whose fit takes one object a step (the ``paper`` preset)."""
    budget = budget_of(methods)
    out = []
    for spec in specs:
        for label, fields in methods:
            if fields is None and spec.kind in ("main", "cut-in"):
                continue
            cfg = ExperimentConfig.of(**(fields or {}))
            if spec.kind == "cut-in" and not (cfg.weights_until_failure or cfg.adaptive.proposal_window):
                continue  # several objects a step: the paper's fit of whole elite rollouts takes one
            f = (("n", budget),) if fields is None else tuple(sorted(fields.items()))
            out += [Job(spec, label, f, seed) for seed in range(n_seeds)]
    return out


def run_all(jobs: Sequence[Job], runs_file: Path, n_jobs: int, truths: dict[str, float]) -> list[Record]:
    """Run the jobs not yet in ``runs_file``, appending each record as it ends; every job's record, in order.
    ``truths``: problem name -> exact log p_fail, for the progress lines."""
    done: dict[str, Record] = {}
    if runs_file.is_file():
        for line in runs_file.read_text(encoding="utf-8").splitlines():
            try:
                item = json.loads(line)
                done[item["job"]] = Record(**item["record"])
            except (ValueError, KeyError, TypeError):
                continue  # a torn last line
    todo = [j for j in jobs if j.key() not in done]
    print(f"{len(jobs) - len(todo)} of {len(jobs)} runs already in {runs_file}", file=sys.stderr)
    t0 = time.perf_counter()
    with runs_file.open("a", encoding="utf-8") as log:

        def finished(job: Job, rec: Record) -> None:
            done[job.key()] = rec
            log.write(json.dumps({"job": job.key(), "record": asdict(rec)}) + "\n")
            log.flush()
            print(
                f"  [{len(done)}/{len(jobs)}, {time.perf_counter() - t0:.0f} s] {rec.problem} {rec.method} seed "
                f"{rec.seed}: rel. error {relative_error(rec.log_mu_hat, truths[rec.problem]):.3g} "
                f"({rec.wall_s:.1f} s)",
                file=sys.stderr,
                flush=True,
            )

        if n_jobs <= 1:
            for job in todo:
                finished(job, run_job(job))
        else:
            with mp.get_context("spawn").Pool(n_jobs) as pool:  # torch and fork do not mix
                for job, rec in zip(todo, pool.imap(run_job, todo), strict=False):
                    finished(job, rec)
    return [done[j.key()] for j in jobs]


# -- summary --------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Row:
    problem: str
    method: str
    log_truth: float
    n_seeds: int
    median_rel_error: float
    max_rel_error: float
    median_failures: float
    n_simulations: int
    sims_for_10pct: float
    median_wall_s: float

    @property
    def log10_p(self) -> float:
        return self.log_truth / math.log(10.0)


def summarise(records: Sequence[Record], truths: dict[str, float]) -> list[Row]:
    """One row per (problem, method) in first-seen order."""
    groups: dict[tuple[str, str], list[Record]] = {}
    for r in records:
        groups.setdefault((r.problem, r.method), []).append(r)
    rows = []
    for (problem, method), rs in groups.items():
        errs = [relative_error(r.log_mu_hat, truths[problem]) for r in rs]
        n = int(np.median([r.n_simulations for r in rs]))
        med = float(np.median(errs))
        rows.append(
            Row(
                problem,
                method,
                truths[problem],
                len(rs),
                med,
                float(max(errs)),
                float(np.median([r.n_failures for r in rs])),
                n,
                rollouts_for(med, n),
                float(np.median([r.wall_s for r in rs])),
            )
        )
    return rows


def _sims(x: float) -> str:
    return "inf" if not math.isfinite(x) else "< 1" if x < 1.0 else f"{x:.3g}"


def markdown(rows: Sequence[Row], n_seeds: int) -> str:
    head = (
        "| problem | log10 p | method | seeds | median rel. error | max rel. error | median failures | simulations "
        "| simulations for 10 % | median wall s |\n|---|---:|---|---:|---:|---:|---:|---:|---:|---:|"
    )
    lines = [
        f"{r.problem} | {r.log10_p:.2f} | {r.method} | {r.n_seeds} | {r.median_rel_error:.3g} | "
        f"{r.max_rel_error:.3g} | {r.median_failures:g} | {r.n_simulations:,} | {_sims(r.sims_for_10pct)} | "
        f"{r.median_wall_s:.2f}"
        for r in rows
    ]
    note = (
        f"\n\nMedian over {n_seeds} seeds. Simulations for 10 %: N (median rel. error / 0.1)^2, the budget a "
        "method would need if its error fell as 1 / sqrt(N) (a method that found no failure has rel. error 1).\n"
    )
    return head + "\n" + "\n".join(f"| {line} |" for line in lines) + note


def to_csv(rows: Sequence[Row]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(
        [
            "problem",
            "log_truth",
            "log10_p",
            "method",
            "seeds",
            "median_rel_error",
            "max_rel_error",
            "median_failures",
            "n_simulations",
            "sims_for_10pct",
            "median_wall_s",
        ]
    )
    for r in rows:
        w.writerow(
            [
                r.problem,
                repr(r.log_truth),
                f"{r.log10_p:.6g}",
                r.method,
                r.n_seeds,
                f"{r.median_rel_error:.6g}",
                f"{r.max_rel_error:.6g}",
                r.median_failures,
                r.n_simulations,
                f"{r.sims_for_10pct:.6g}",
                f"{r.median_wall_s:.3f}",
            ]
        )
    return buf.getvalue()


FLOOR = 1e-16
"""Relative errors below this (q*: float64 rounding) are drawn at it on the log axes."""


def series(rows: Sequence[Row]) -> dict[str, list[tuple[float, float, float]]]:
    """method -> [(log10 p, median rel. error, simulations for 10 %)] sorted by log10 p."""
    out: dict[str, list[tuple[float, float, float]]] = {}
    for r in rows:
        out.setdefault(r.method, []).append((r.log10_p, max(r.median_rel_error, FLOOR), r.sims_for_10pct))
    return {m: sorted(v) for m, v in out.items()}


def write_png(path: str, rows: Sequence[Row], n_seeds: int, budget: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 4.5))
    for method, pts in series(rows).items():
        x = [p[0] for p in pts]
        ax1.plot(x, [p[1] for p in pts], "o-", label=method)
        finite = [(p[0], p[2]) for p in pts if math.isfinite(p[2]) and p[2] >= 1.0]
        if finite:
            ax2.plot(*zip(*finite, strict=False), "o-", label=method)
    ax1.set(
        yscale="log",
        xlabel="log10 p (exact)",
        ylabel="median relative error",
        title=f"relative error at {budget:,} simulations, {n_seeds} seeds",
    )
    ax1.axhline(0.1, color="grey", lw=0.8, ls="--")
    ax2.set(
        yscale="log",
        xlabel="log10 p (exact)",
        ylabel="simulations for 10 % relative error",
        title="N (median rel. error / 0.1)^2 (q*: below 1)",
    )
    for ax in (ax1, ax2):
        ax.invert_xaxis()
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, format="png", dpi=110)
    plt.close(fig)


def write_rrd(path: str, rows: Sequence[Row], table_md: str) -> None:
    """The same series as the PNG as log10 values on the sequence timeline ``minus_log10_p`` (rounded)."""
    import rerun as rr

    rec = rr.RecordingStream("pemviz-rarity-sweep")
    rec.save(path)
    rec.log("sweep/table", rr.TextDocument(table_md, media_type=rr.MediaType.MARKDOWN), static=True)
    for method, pts in series(rows).items():
        part = rr.escape_entity_path_part(method)
        for name in ("log10_median_rel_error", "log10_sims_for_10pct"):
            rec.log(f"sweep/{name}/{part}", rr.SeriesLines(names=method), static=True)
        for log10_p, err, sims in pts:
            rec.set_time("minus_log10_p", sequence=int(round(-log10_p)))
            rec.log(f"sweep/log10_median_rel_error/{part}", rr.Scalars(math.log10(err)))
            if math.isfinite(sims) and sims >= 1.0:
                rec.log(f"sweep/log10_sims_for_10pct/{part}", rr.Scalars(math.log10(sims)))
    rec.flush()
    rec.disconnect()


# -- how far from q*: the relative variance of the default sampler --------------------------------------------------


def relative_variances(name: str, n_seeds: int) -> tuple[float, list[float]]:
    """Var(w 1[fail]) / mu^2 per rollout of the default sampler's final batch (N_e rollouts from its last proposal,
    the defensive mixture included) on the named problem of :data:`pemviz.scenarios.problems.PROBLEMS`, one per seed,
    with the exact mu; returns (log mu, [relative variance per seed]). q* has 0, plain Monte Carlo (1 - mu) / mu."""
    from pemviz.engine.events import RolloutsSampled
    from pemviz.scenarios.problems import build_problem

    problem = build_problem(name)
    assert problem.exact_log_p is not None
    out = []
    for seed in range(n_seeds):
        finals: list[RolloutsSampled] = []

        def keep(event: object) -> None:
            if isinstance(event, RolloutsSampled) and event.kind == "final":
                finals.append(event)  # noqa: B023 (the run below calls it within the iteration)

        with torch_threads(1):
            Experiment(ExperimentConfig.of(seed=seed), [keep], problem=problem).run()
        (final,) = finals
        out.append(relative_variance(final.log_weight, final.failed, problem.exact_log_p))
    return problem.exact_log_p, out


def relative_variance_table(names: Sequence[str], n_seeds: int) -> str:
    """Markdown: per problem, the default sampler's median relative variance per rollout over the seeds and the
    rollouts it would need for a 10 % relative standard error (relative variance / 0.01), against Monte Carlo's."""
    lines = [
        "| problem | p | seeds | rel. variance per rollout (median) | min - max | rollouts for 10 % | "
        "Monte Carlo's rel. variance | q*'s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name in names:
        log_mu, rv = relative_variances(name, n_seeds)
        med = float(np.median(rv))
        mc = -math.expm1(log_mu) / math.exp(log_mu)
        lines.append(
            f"| {name} | {math.exp(log_mu):.4g} | {n_seeds} | {med:.3g} | {min(rv):.3g} - {max(rv):.3g} | "
            f"{med / 0.01:.3g} | {mc:.3g} | 0 |"
        )
    return "\n".join(lines) + "\n"


# -- command line ---------------------------------------------------------------------------------------------------

OUTPUTS = ("sweep.md", "sweep.csv", "sweep.png", "sweep.rrd")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="recordings/sweep", help="output folder (default %(default)s)")
    ap.add_argument("--quick", action="store_true", help="3 small problems, 2 seeds, the quick preset (~1-2 min)")
    ap.add_argument("--seeds", type=int, default=None, help="seeds per method and problem (default 10; quick 2)")
    ap.add_argument("--problems", default=None, help="comma-separated problem names (default: all of the mode)")
    ap.add_argument("--methods", default=None, help="comma-separated method labels (default: all)")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    ap.add_argument(
        "--n-final",
        type=int,
        default=None,
        metavar="N_E",
        help="the default sampler's final batch, which sets every method's budget (default 1000: 2,100 "
        "simulations; 100: 1,200)",
    )
    ap.add_argument("--overwrite", action="store_true", help="replace existing outputs (and start runs.jsonl anew)")
    ap.add_argument("--resume", action="store_true", help="keep the runs already in OUT/runs.jsonl")
    ap.add_argument(
        "--relative-variance",
        metavar="PROBLEMS",
        default=None,
        help="instead: the default sampler's relative variance per rollout on these named problems "
        "(comma-separated, e.g. toy,latched,main), printed as a table",
    )
    args = ap.parse_args(argv)
    if args.relative_variance:
        from pemviz.scenarios.problems import PROBLEMS

        names = args.relative_variance.split(",")
        if any(n not in PROBLEMS for n in names):
            print(
                f"rarity_sweep: unknown problem in {args.relative_variance!r}; use some of {', '.join(PROBLEMS)}",
                file=sys.stderr,
            )
            return 2
        print(relative_variance_table(names, args.seeds or 10))
        return 0

    specs = QUICK if args.quick else FULL
    if args.n_final is not None and (args.quick or args.n_final < 1):
        print("rarity_sweep: --n-final must be >= 1, and cannot go with --quick", file=sys.stderr)
        return 2
    methods = QUICK_METHODS if args.quick else methods_at(args.n_final) if args.n_final is not None else METHODS
    n_seeds = args.seeds if args.seeds is not None else (2 if args.quick else 10)
    if n_seeds < 1 or args.jobs < 1:
        print("rarity_sweep: --seeds and --jobs must be >= 1", file=sys.stderr)
        return 2
    if args.problems:
        names = args.problems.split(",")
        unknown = [n for n in names if n not in {s.name for s in specs}]
        if unknown:
            print(
                f"rarity_sweep: unknown problem {unknown[0]!r}; use some of {', '.join(s.name for s in specs)}",
                file=sys.stderr,
            )
            return 2
        specs = tuple(s for s in specs if s.name in names)
    if args.methods:
        labels = args.methods.split(",")
        unknown = [m for m in labels if m not in {m for m, _ in methods}]
        if unknown:
            print(
                f"rarity_sweep: unknown method {unknown[0]!r}; use some of {', '.join(m for m, _ in methods)}",
                file=sys.stderr,
            )
            return 2
        methods = [m for m in methods if m[0] in labels]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    runs_file = out / "runs.jsonl"
    existing = [out / n for n in OUTPUTS if (out / n).exists()]
    if runs_file.exists() and not args.resume:
        existing.append(runs_file)
    if existing and not args.overwrite:
        print(
            f"rarity_sweep: {existing[0]} exists; give --overwrite to replace it"
            f"{' (or --resume to keep its runs)' if existing[0] == runs_file else ''}",
            file=sys.stderr,
        )
        return 2
    if runs_file.exists() and args.overwrite and not args.resume:
        runs_file.unlink()

    t0 = time.perf_counter()
    truths, sources = {}, {}
    for spec in specs:
        truths[spec.name], sources[spec.name] = exact_log_p(spec)
        print(
            f"{spec.name}: exact p_fail = 10^{truths[spec.name] / math.log(10):.3f} ({sources[spec.name]})",
            file=sys.stderr,
            flush=True,
        )
    records = run_all(jobs_for(specs, methods, n_seeds), runs_file, args.jobs, truths)
    rows = summarise(records, truths)
    table = markdown(rows, n_seeds)
    problems_md = "\n".join(f"- **{s.name}**: 10^{truths[s.name] / math.log(10):.3f}, {sources[s.name]}" for s in specs)
    doc = f"# Rarity sweep\n\n{problems_md}\n\n{table}\nWall time {time.perf_counter() - t0:.0f} s.\n"

    def text(content: str) -> Callable[[str], None]:
        return lambda tmp: Path(tmp).write_text(content, encoding="utf-8")

    atomic_write(out / "sweep.md", text(doc), overwrite=args.overwrite)
    atomic_write(out / "sweep.csv", text(to_csv(rows)), overwrite=args.overwrite)
    budget = budget_of(methods)
    atomic_write(out / "sweep.png", lambda tmp: write_png(tmp, rows, n_seeds, budget), overwrite=args.overwrite)
    atomic_write(out / "sweep.rrd", lambda tmp: write_rrd(tmp, rows, table), overwrite=args.overwrite)
    print(doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
