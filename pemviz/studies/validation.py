"""Validation of the estimators against exact failure probabilities: a :class:`Job` is one method on one named
problem (:data:`pemviz.scenarios.problems.PROBLEMS`) for one seed; :func:`run_jobs` runs them in worker processes,
appending each :class:`RunRecord` to ``runs.jsonl`` (so a study resumes); :func:`summarise` makes table rows beside
each problem's truth (:mod:`pemviz.studies.exact_answers`)."""

from __future__ import annotations

import csv
import dataclasses
import functools
import io
import json
import math
import multiprocessing as mp
import os
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from pemviz.config import ExperimentConfig
from pemviz.core.estimate import format_probability, relative_error
from pemviz.core.files import atomic_write
from pemviz.engine.events import RunFinished
from pemviz.engine.experiment import Experiment
from pemviz.engine.resources import torch_threads
from pemviz.methods import BUILTIN_METHODS, DEFAULT_METHOD, SPLITTING_METHOD, records
from pemviz.presets import PRESETS
from pemviz.studies.exact_answers import ExactAnswer, problem_description, validation_problem

DEFAULT_PROBLEMS = ("toy", "toy-1e-30", "latched", "main")
"""The problems ``pemviz validate`` runs by default."""

# -- one run ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunRecord:
    """One method on one problem for one seed: the final estimate and what it cost.

    ``curves``: the proposal curve q(detect | d) after every stage, float64 [stages, G] (adaptive only, when
    asked for); ``gammas``: gamma_kappa per CE stage."""

    problem: str
    method: str
    seed: int
    log_mu_hat: float
    n_failures: int
    n: int
    ess: float
    nll_mean: float
    nll_lme: float
    n_simulations: int
    wall_s: float
    gammas: tuple[float, ...] = ()
    curves: np.ndarray | None = field(default=None, repr=False)
    log_ci_lo: float = -math.inf
    """The estimate's 95 % interval as natural logs (:attr:`pemviz.core.estimate.Estimate.log_ci`)."""
    log_ci_hi: float = 0.0
    khat: float = math.nan
    verdict: str = "unreliable"
    reason: str = ""

    @property
    def says_nothing(self) -> bool:
        """Whether its interval is the trivial [0, 1] (a run that saw no failure and has no bound): it holds every p,
        so it is counted apart, neither holding nor missing one."""
        return self.log_ci_lo == -math.inf and self.log_ci_hi >= 0.0

    def covers(self, log_p: float) -> bool:
        """Whether the 95 % interval holds the probability whose natural log is ``log_p``; never the trivial [0, 1]
        (:attr:`says_nothing`)."""
        return not self.says_nothing and self.log_ci_lo <= log_p <= self.log_ci_hi


@dataclass(frozen=True)
class Job:
    """What a worker runs: a problem, a method label and the config fields, one seed."""

    problem: str
    method: str
    fields: tuple[tuple[str, Any], ...]
    seed: int
    keep_curves: bool = False
    pem_path: str | None = None


def run_job(job: Job, workers: int | None = None) -> RunRecord:
    """Run one :class:`Job` (in this process, its rollouts on ``workers`` processes: None, every usable core) and
    summarise it."""
    problem = validation_problem(job.problem, job.pem_path)
    if dict(job.fields).get("method", DEFAULT_METHOD) not in BUILTIN_METHODS:  # a plugin's method: load it here
        from pemviz.methods import load_method_plugins

        load_method_plugins()
    cfg = ExperimentConfig.of(**dict(job.fields), seed=job.seed)
    if workers is not None and cfg.execution.executor == "local":
        cfg = cfg.replace(workers=workers)
    t0 = time.perf_counter()
    with torch_threads(1, blas=1):  # runs go side by side: a BLAS thread each
        res = Experiment(cfg, problem=problem).run()
    if not isinstance(res, RunFinished):  # pragma: no cover - no cancel token here
        raise RuntimeError(f"{job.method} on {job.problem} seed {job.seed} did not finish")
    e = res.final.estimate
    curves = (
        np.stack([s.proposal_curve for s in res.stages])
        if job.keep_curves and cfg.method_record.proposal_curves
        else None
    )
    gammas = tuple(float(s.gamma) for s in res.stages if s.kind == "ce")
    return RunRecord(
        job.problem,
        job.method,
        job.seed,
        e.log_mu_hat,
        e.n_failures,
        e.n,
        e.ess,
        e.nll_mean,
        e.nll_lme,
        res.final.n_simulations,
        time.perf_counter() - t0,
        gammas,
        curves,
        *e.log_ci,
        e.khat,
        e.verdict,
        e.reason,
    )


RUNS_FILE = "runs.jsonl"
"""Each finished run of ``validate`` / ``tables``, one JSON line, appended as the run ends (``--out``)."""


def all_fields(fields: Sequence[tuple[str, Any]]) -> list[tuple[str, Any]]:
    """Every field of the config that ``fields`` (name, value pairs) set, defaults filled in, but the seed, sorted by
    name: what a run depends on, whichever defaults the running pemviz has.

    Raises:
        ConfigError: ``fields`` not a valid config."""
    config = ExperimentConfig.of(**dict(fields)).flat()
    return sorted((k, v) for k, v in config.items() if k != "seed")


def job_key(job: Job) -> str:
    """What identifies a run in :data:`RUNS_FILE`: the whole :class:`Job` as canonical JSON, its config with every
    default filled in (:func:`all_fields`), so that a study resumed by a pemviz whose defaults have changed runs
    its jobs again instead of reusing their records."""
    return json.dumps({**dataclasses.asdict(job), "fields": all_fields(job.fields)}, sort_keys=True, default=str)


def record_to_json(job: Job, rec: RunRecord) -> str:
    """One line of :data:`RUNS_FILE` (non-finite floats as ``NaN`` / ``-Infinity``, as Python's json reads them)."""
    fields = {f.name: getattr(rec, f.name) for f in dataclasses.fields(rec)}
    fields["gammas"] = list(rec.gammas)
    fields["curves"] = None if rec.curves is None else rec.curves.tolist()
    return json.dumps({"job": job_key(job), "record": fields})


def read_records(path: Path) -> list[tuple[str, RunRecord]]:
    """Every record of the :data:`RUNS_FILE` at ``path``, in file order, each with its :func:`job_key`; none when
    the file does not exist. Lines that do not parse (a torn last line of a killed run, a foreign or non-UTF-8
    line) are skipped."""
    out: list[tuple[str, RunRecord]] = []
    if not path.is_file():
        return out
    for line in path.read_bytes().splitlines():
        try:
            item = json.loads(line.decode("utf-8"))
            fields = dict(item["record"])
            fields["gammas"] = tuple(fields["gammas"])
            fields["curves"] = None if fields["curves"] is None else np.asarray(fields["curves"], dtype=np.float64)
            out.append((str(item["job"]), RunRecord(**fields)))
        except (ValueError, KeyError, TypeError):
            continue
    return out


def read_finished(path: Path, jobs: Sequence[Job]) -> dict[str, RunRecord]:
    """The records of :data:`RUNS_FILE` at ``path`` that belong to ``jobs``, by :func:`job_key`
    (:func:`read_records`); lines of other jobs (other settings) are ignored."""
    wanted = {job_key(j) for j in jobs}
    return {key: rec for key, rec in read_records(path) if key in wanted}


def run_jobs(
    jobs: Sequence[Job],
    n_jobs: int = 1,
    on_record: Callable[[RunRecord], None] | None = None,
    *,
    runs_file: Path | None = None,
    progress: bool = False,
) -> list[RunRecord]:
    """Run jobs in order (``n_jobs`` = 1) or in ``n_jobs`` worker processes; results in the jobs' order.

    With ``runs_file``, every run is appended to it as it ends and runs already there are not run again
    (resume after Ctrl-C, SIGTERM or a crash). ``progress`` shows a bar with the ETA on stderr."""
    done = read_finished(runs_file, jobs) if runs_file is not None else {}
    todo = [job for job in jobs if job_key(job) not in done]
    if done:
        print(f"resuming: {len(jobs) - len(todo)} of {len(jobs)} runs already in {runs_file}", file=sys.stderr)
    tty = sys.stderr.isatty()
    bar = tqdm(
        total=len(jobs),
        initial=len(jobs) - len(todo),
        unit="run",
        file=sys.stderr,
        disable=not (progress and tty),
        dynamic_ncols=True,
    )
    t0, n0 = time.perf_counter(), len(jobs) - len(todo)
    log = None
    if runs_file is not None:
        data = runs_file.read_bytes() if runs_file.is_file() else b""
        if data and not data.endswith(b"\n"):
            kept = data.rsplit(b"\n", 1)[0] + b"\n"  # drop a torn last line, the rest intact

            def write(tmp: str) -> None:
                Path(tmp).write_bytes(kept)

            atomic_write(runs_file, write)
        log = runs_file.open("a", encoding="utf-8")

    def finished(job: Job, rec: RunRecord) -> None:
        done[job_key(job)] = rec
        if log is not None:
            log.write(record_to_json(job, rec) + "\n")
            log.flush()
            os.fsync(log.fileno())
        if on_record is not None:
            with bar.external_write_mode():
                on_record(rec)
        bar.update(1)
        if progress and not tty:  # a log, not a terminal: the bar's counts and ETA as a line
            n, elapsed = len(done), time.perf_counter() - t0
            eta = elapsed / (n - n0) * (len(jobs) - n)
            print(
                f"  [{n}/{len(jobs)} runs, {tqdm.format_interval(elapsed)} elapsed, ETA {tqdm.format_interval(eta)}]",
                file=sys.stderr,
                flush=True,
            )

    try:
        if n_jobs <= 1 or len(todo) <= 1:
            for job in todo:
                finished(job, run_job(job))
        else:
            ctx = mp.get_context("spawn")  # torch and fork do not mix
            with ctx.Pool(min(n_jobs, len(todo))) as pool:
                one_each = functools.partial(run_job, workers=1)  # the seeds share the cores, not each run
                for job, rec in zip(todo, pool.imap(one_each, todo), strict=False):
                    finished(job, rec)
    finally:
        bar.close()
        if log is not None:
            log.close()
    return [done[job_key(job)] for job in jobs]


# -- summary ------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Summary:
    """One table row: a method on a problem over its seeds."""

    problem: str
    method: str
    log_truth: float
    n_seeds: int
    median_mu_hat: float
    min_mu_hat: float
    max_mu_hat: float
    median_rel_error: float
    within_2x: int
    median_failures: float
    n_per_estimate: int
    median_ess: float
    n_simulations: int
    median_wall_s: float
    covered: int
    """Seeds whose 95 % interval holds the exact answer."""
    reliable: int
    """Seeds whose verdict is ``reliable``."""
    said_nothing: int = 0
    """Seeds whose interval is the trivial [0, 1] (no failure, no bound): not among :attr:`covered`."""


def summarise(records: Iterable[RunRecord], truths: dict[str, ExactAnswer]) -> list[Summary]:
    """Group records by (problem, method), keeping first-seen order."""
    groups: dict[tuple[str, str], list[RunRecord]] = {}
    for r in records:
        groups.setdefault((r.problem, r.method), []).append(r)
    out = []
    for (problem, method), rs in groups.items():
        lt = truths[problem].log_p_fail
        logs = np.array([r.log_mu_hat for r in rs])
        out.append(
            Summary(
                problem,
                method,
                lt,
                len(rs),
                float(np.median(logs)),
                float(logs.min()),
                float(logs.max()),
                float(np.median([relative_error(x, lt) for x in logs])),
                int(sum(abs(x - lt) <= math.log(2.0) for x in logs)),
                float(np.median([r.n_failures for r in rs])),
                rs[0].n,
                float(np.median([r.ess for r in rs])),
                int(np.median([r.n_simulations for r in rs])),
                float(np.median([r.wall_s for r in rs])),
                sum(r.covers(lt) for r in rs),
                sum(r.verdict == "reliable" for r in rs),
                sum(r.says_nothing for r in rs),
            )
        )
    return out


COLUMNS = (
    "problem",
    "truth",
    "method",
    "seeds",
    "median mu_hat",
    "min mu_hat",
    "max mu_hat",
    "median rel. error",
    "within x2",
    "95% CI covers",
    "reliable",
    "median failures",
    "median ESS",
    "simulations",
    "median wall s",
)


def _row(s: Summary) -> list[str]:
    fp = format_probability
    return [
        s.problem,
        fp(s.log_truth),
        s.method,
        str(s.n_seeds),
        fp(s.median_mu_hat),
        fp(s.min_mu_hat),
        fp(s.max_mu_hat),
        f"{s.median_rel_error:.3f}",
        f"{s.within_2x}/{s.n_seeds}",
        f"{s.covered}/{s.n_seeds}" + (f" ({s.said_nothing} no failure: [0, 1])" if s.said_nothing else ""),
        f"{s.reliable}/{s.n_seeds}",
        f"{s.median_failures:g}/{s.n_per_estimate}",
        f"{s.median_ess:.1f}",
        f"{s.n_simulations:,}",
        f"{s.median_wall_s:.1f}",
    ]


def markdown_table(summaries: Sequence[Summary]) -> str:
    """The summaries as a Markdown table, columns :data:`COLUMNS`."""
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(_row(s)) + " |" for s in summaries]
    return "\n".join(lines)


def csv_text(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    r"""``header`` and ``rows`` as CSV text (the ``csv`` module's dialect: ``\r\n`` line ends)."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue()


def summaries_csv(summaries: Sequence[Summary]) -> str:
    """The summaries as CSV text, logs in nats beside the probabilities."""
    header = (
        "problem log_truth truth method seeds median_log_mu_hat min_log_mu_hat max_log_mu_hat median_mu_hat "
        "median_rel_error within_2x covered reliable median_failures n_per_estimate median_ess simulations "
        "median_wall_s said_nothing"
    ).split()
    return csv_text(
        header,
        (
            [
                s.problem,
                repr(s.log_truth),
                f"{math.exp(s.log_truth):.6g}",
                s.method,
                s.n_seeds,
                repr(s.median_mu_hat),
                repr(s.min_mu_hat),
                repr(s.max_mu_hat),
                f"{math.exp(s.median_mu_hat):.6g}",
                f"{s.median_rel_error:.6g}",
                s.within_2x,
                s.covered,
                s.reliable,
                s.median_failures,
                s.n_per_estimate,
                f"{s.median_ess:.6g}",
                s.n_simulations,
                f"{s.median_wall_s:.3f}",
                s.said_nothing,
            ]
            for s in summaries
        ),
    )


def report(
    problems: Sequence[str], truths: dict[str, ExactAnswer], summaries: Sequence[Summary], n_seeds: int, wall_s: float
) -> str:
    """The Markdown report of ``pemviz validate`` (``validate.md``): each problem's truth and where it comes from,
    the table of :func:`markdown_table`, the refinement tables of the enumerated truths, the wall time (seconds)."""
    md = [f"# pemviz validate: {n_seeds} seeds, equal budgets ({summaries[0].n_simulations:,} simulations)", ""]
    for name in problems:
        truth = truths[name]
        md.append(f"- **{name}**: {problem_description(name)}; truth {math.exp(truth.log_p_fail):.6g}: {truth.source}")
    md += ["", markdown_table(summaries), ""]
    for name in problems:
        table = truths[name].table
        if table:
            md += [f"Refinement of the {name} truth:", "", table, ""]
    md.append(f"Total wall time {wall_s:.0f} s.")
    return "\n".join(md) + "\n"


# -- methods at equal budgets -------------------------------------------------------------------------------------

BASELINES = tuple(r.name for r in records() if r.name in BUILTIN_METHODS and r.baseline)
"""The baseline methods a study can compare the adaptive sampler with."""


AMS_SHARE = 4
"""AMS at a budget of B rollouts: N = B / 4 particles, k = N / 10 killed per iteration (:func:`ams_fields`)."""


def ams_fields(budget: int) -> dict[str, Any]:
    """Config fields of adaptive multilevel splitting at a budget of ``budget`` rollouts: N = budget /
    :data:`AMS_SHARE` particles and k = N / 10; the continuations add 0 to 3.2 N rollout-equivalents
    (docs/validation.md), and a table reports the run's own count."""
    n = max(2, budget // AMS_SHARE)
    return {"method": SPLITTING_METHOD, "n_per_stage": n, "ams_killed": max(1, n // 10)}


def methods_for(presets: Sequence[str], baselines: Sequence[str], base: dict[str, Any]) -> list[tuple[str, dict]]:
    """(label, config fields) per method: ``adaptive (PRESET)`` per preset, then the baselines at the first preset's
    simulations (ams: :func:`ams_fields`); the presets run their stages alone (``plain_fallback`` = 0) so budgets
    stay equal."""
    out = []
    budget = None
    for name in presets:
        fields = {**PRESETS[name], "plain_fallback": 0, **base}
        budget = budget or ExperimentConfig.of(**fields).n_simulations
        out.append((f"adaptive ({name})", fields))
    budget = budget or ExperimentConfig.of(**base).n_simulations
    for m in baselines:
        own = ams_fields(budget) if m == SPLITTING_METHOD else {"method": m, "n_per_stage": budget}
        out.append((m, {**{k: v for k, v in base.items() if k in ("pem", "sim")}, **own}))
    return out


def study_jobs(
    problems: Sequence[str], methods: Sequence[tuple[str, dict]], n_seeds: int, pem_path: str | None = None
) -> list[Job]:
    """Every (problem, method, seed) of a study as a :class:`Job`, seeds 0..n_seeds-1; ``methods`` as
    :func:`methods_for` returns them."""
    return [
        Job(pb, label, tuple(sorted(fields.items())), seed, pem_path=pem_path)
        for pb in problems
        for label, fields in methods
        for seed in range(n_seeds)
    ]
