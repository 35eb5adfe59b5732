"""``pemviz validate``: the sampler and the baselines against exact failure probabilities.

Each problem of :data:`PROBLEMS` has a known answer: the toy braking model in closed form,
the latched-brake scenario from its deterministic simulator, and the main braking scenario by exact
enumeration of its detection sequences (:mod:`pemviz.truth`). Every method runs on every problem for
several seeds at the same simulation budget (the adaptive sampler's: pretraining + K x N + N_e), and the
table reports, per problem and method: the truth, the median and spread of mu_hat, the median relative
error |mu_hat - truth| / truth, how many seeds are within a factor 2, failures, ESS, simulations, wall time.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np

from pemviz.config import DEFAULT_PRESET, PRESETS, ConfigError, ExperimentConfig
from pemviz.files import check_output_folder, write_text_atomic
from pemviz.resources import cap_jobs
from pemviz.sampling import relative_error

# -- problems with an exact answer ------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExactAnswer:
    """The truth of a problem: ``log_p_fail`` (nats), where it comes from, and a refinement table if any."""

    log_p_fail: float
    source: str
    table: str | None = None
    wall_s: float = 0.0


PROBLEMS: dict[str, str] = {
    "toy": "toy braking (100, 50, 30, p = 0.9): exact 1e-21",
    "toy-1e-30": "toy braking (100, 39, 30, p = 0.999), braking window 10: exact 1e-30",
    "latched": "braking scenario with a latched brake: exact from the deterministic simulator",
    "main": "braking scenario: exact enumeration of detection sequences",
    "toy-1e-3": "toy braking (10, 5, 3, p = 0.9): exact 1e-3 (small; for CI)",
}
"""Problem name -> description."""

DEFAULT_PROBLEMS = ("toy", "toy-1e-30", "latched", "main")

_TOYS = {"toy": (100, 50, 30, 0.9), "toy-1e-30": (100, 39, 30, 0.999), "toy-1e-3": (10, 5, 3, 0.9)}

_problem_cache: dict[tuple[str, str | None], Any] = {}


def build_problem(name: str, pem_path: str | None = None):
    """The :class:`~pemviz.problems.Problem` named ``name`` (cached per process).

    Raises:
        ValueError: for an unknown name (allowed: :data:`PROBLEMS`).
    """
    key = (name, pem_path)
    if key in _problem_cache:
        return _problem_cache[key]
    if name in _TOYS:
        from pemviz.scenarios.toy import ToyParams, toy_problem

        problem = toy_problem(ToyParams(*_TOYS[name]), name=name)
    elif name in ("latched", "main"):
        from pemviz.pem import load_pem
        from pemviz.problems import braking_problem
        from pemviz.scenarios.braking import BrakingParams

        problem = braking_problem(load_pem(pem_path), BrakingParams(latched_brake=name == "latched"), sim="batched")
    else:
        raise ValueError(f"unknown problem {name!r}; use one of {', '.join(PROBLEMS)}")
    _problem_cache[key] = problem
    return problem


def exact_answer(name: str, pem_path: str | None = None, *, progress: Callable[[str], None] | None = None) -> ExactAnswer:
    """The exact p_fail of a problem of :data:`PROBLEMS` (seconds for the toys, ~20 s for ``main``)."""
    from pemviz import truth

    t0 = time.perf_counter()
    if name in _TOYS:
        from pemviz.scenarios.toy import ToyParams

        total, braking, safe, p = _TOYS[name]
        log_p = truth.toy_log_failure_probability(ToyParams(total, braking, safe, p))
        return ExactAnswer(log_p, f"closed form (1 - p)^(braking - safe + 1) = {1 - p:g}^{braking - safe + 1}")
    from pemviz.pem import load_pem
    from pemviz.scenarios.braking import BrakingParams

    pem = load_pem(pem_path)
    if name == "latched":
        lt = truth.latched_log_failure_probability(pem.logit_at_gap, BrakingParams(latched_brake=True))
        return ExactAnswer(
            lt.log_p_fail,
            f"product of (1 - p_PEM) over steps {lt.first_step}..{lt.last_step} (deterministic simulator)",
            wall_s=time.perf_counter() - t0,
        )
    if name == "main":
        def on_result(r) -> None:
            if progress is not None:
                progress(f"  truth: drop threshold {r.log_prune:g} nats -> p_fail {math.exp(r.log_p_fail):.5g} "
                         f"(+ at most {math.exp(r.log_pruned_bound):.2g}), {r.wall_s:.1f} s")  # fmt: skip

        ref = truth.braking_truth(pem.logit_at_gap, BrakingParams(), on_result=on_result)
        status = "converged" if ref.converged else "NOT converged"
        f = ref.final
        return ExactAnswer(
            ref.log_p_fail,
            f"exact enumeration, bracket [{math.exp(f.log_p_fail):.5g}, {math.exp(f.log_p_fail_upper):.5g}] "
            f"(width {f.relative_width:.2%}, {status})",
            ref.table(),
            time.perf_counter() - t0,
        )
    raise ValueError(f"unknown problem {name!r}; use one of {', '.join(PROBLEMS)}")


# -- one run ----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunRecord:
    """One method on one problem for one seed: the final estimate and what it cost.

    ``curves``: the proposal curve q(detect | d) after every stage, float64 [stages, G] (adaptive only, when
    asked for); ``gammas``: gamma_kappa per CE stage.
    """

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
    """The estimate's 95 % interval as natural logs (:attr:`pemviz.sampling.Estimate.log_ci`)."""
    log_ci_hi: float = 0.0
    khat: float = math.nan
    verdict: str = "unreliable"
    reason: str = ""


@dataclass(frozen=True)
class Job:
    """What a worker runs: a problem, a method label and the config fields, one seed."""

    problem: str
    method: str
    fields: tuple[tuple[str, Any], ...]
    seed: int
    keep_curves: bool = False
    pem_path: str | None = None


def run_job(job: Job) -> RunRecord:
    """Run one :class:`Job` (in this process) and summarise it."""
    import torch

    from pemviz.engine import Experiment, RunFinished

    torch.set_num_threads(1)
    problem = build_problem(job.problem, job.pem_path)
    cfg = ExperimentConfig(**dict(job.fields), seed=job.seed)
    t0 = time.perf_counter()
    res = Experiment(cfg, problem=problem).run()
    if not isinstance(res, RunFinished):  # pragma: no cover - no cancel token here
        raise RuntimeError(f"{job.method} on {job.problem} seed {job.seed} did not finish")
    e = res.final.estimate
    curves = np.stack([s.proposal_curve for s in res.stages]) if job.keep_curves and cfg.method == "adaptive" else None
    gammas = tuple(float(s.gamma) for s in res.stages if s.kind == "ce")
    return RunRecord(job.problem, job.method, job.seed, e.log_mu_hat, e.n_failures, e.n, e.ess, e.nll_mean, e.nll_lme,
                     res.final.n_simulations, time.perf_counter() - t0, gammas, curves, *e.log_ci, e.khat, e.verdict,
                     e.reason)  # fmt: skip


RUNS_FILE = "runs.jsonl"
"""Each finished run of ``validate`` / ``tables``, one JSON line, appended as the run ends (``--out``)."""


def job_key(job: Job) -> str:
    """What identifies a run in :data:`RUNS_FILE`: the whole :class:`Job` as canonical JSON."""
    return json.dumps(dataclasses.asdict(job), sort_keys=True, default=str)


def record_to_json(job: Job, rec: RunRecord) -> str:
    """One line of :data:`RUNS_FILE` (non-finite floats as ``NaN`` / ``-Infinity``, as Python's json reads them)."""
    fields = {f.name: getattr(rec, f.name) for f in dataclasses.fields(rec)}
    fields["gammas"] = list(rec.gammas)
    fields["curves"] = None if rec.curves is None else rec.curves.tolist()
    return json.dumps({"job": job_key(job), "record": fields})


def read_finished(path: Path, jobs: Sequence[Job]) -> dict[str, RunRecord]:
    """The records of :data:`RUNS_FILE` at ``path`` that belong to ``jobs``, by :func:`job_key`.

    Lines of other jobs (other settings) are ignored; a torn last line (a killed run) is skipped.
    """
    wanted = {job_key(j) for j in jobs}
    done: dict[str, RunRecord] = {}
    if not path.is_file():
        return done
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            item = json.loads(line)
            if item["job"] not in wanted:
                continue
            fields = dict(item["record"])
            fields["gammas"] = tuple(fields["gammas"])
            fields["curves"] = None if fields["curves"] is None else np.asarray(fields["curves"], dtype=np.float64)
            done[item["job"]] = RunRecord(**fields)
        except (ValueError, KeyError, TypeError):
            continue
    return done


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
    (resume after Ctrl-C, SIGTERM or a crash). ``progress`` shows a bar with the ETA on stderr.
    """
    from tqdm import tqdm

    done = read_finished(runs_file, jobs) if runs_file is not None else {}
    todo = [job for job in jobs if job_key(job) not in done]
    if done:
        print(f"resuming: {len(jobs) - len(todo)} of {len(jobs)} runs already in {runs_file}", file=sys.stderr)
    tty = sys.stderr.isatty()
    bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), unit="run", file=sys.stderr,
               disable=not (progress and tty), dynamic_ncols=True)  # fmt: skip
    t0, n0 = time.perf_counter(), len(jobs) - len(todo)
    log = None
    if runs_file is not None:
        if runs_file.is_file() and runs_file.stat().st_size and not runs_file.read_bytes().endswith(b"\n"):
            runs_file.write_bytes(runs_file.read_bytes().rsplit(b"\n", 1)[0] + b"\n")  # drop a torn last line
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
            print(f"  [{n}/{len(jobs)} runs, {tqdm.format_interval(elapsed)} elapsed, ETA {tqdm.format_interval(eta)}]",
                  file=sys.stderr, flush=True)  # fmt: skip

    try:
        if n_jobs <= 1 or len(todo) <= 1:
            for job in todo:
                finished(job, run_job(job))
        else:
            import multiprocessing as mp

            ctx = mp.get_context("spawn")  # torch and fork do not mix
            with ctx.Pool(min(n_jobs, len(todo))) as pool:
                for job, rec in zip(todo, pool.imap(run_job, todo)):
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
                problem, method, lt, len(rs), float(np.median(logs)), float(logs.min()), float(logs.max()),
                float(np.median([relative_error(x, lt) for x in logs])),
                int(sum(abs(x - lt) <= math.log(2.0) for x in logs)),
                float(np.median([r.n_failures for r in rs])), rs[0].n, float(np.median([r.ess for r in rs])),
                int(np.median([r.n_simulations for r in rs])), float(np.median([r.wall_s for r in rs])),
                sum(r.log_ci_lo <= lt <= r.log_ci_hi for r in rs), sum(r.verdict == "reliable" for r in rs),
            )
        )  # fmt: skip
    return out


COLUMNS = ("problem", "truth", "method", "seeds", "median mu_hat", "min mu_hat", "max mu_hat", "median rel. error",
           "within x2", "95% CI covers", "reliable", "median failures", "median ESS", "simulations",
           "median wall s")  # fmt: skip


def _row(s: Summary) -> list[str]:
    from pemviz.sampling import format_probability as fp

    return [s.problem, fp(s.log_truth), s.method, str(s.n_seeds), fp(s.median_mu_hat), fp(s.min_mu_hat),
            fp(s.max_mu_hat), f"{s.median_rel_error:.3f}", f"{s.within_2x}/{s.n_seeds}", f"{s.covered}/{s.n_seeds}",
            f"{s.reliable}/{s.n_seeds}",
            f"{s.median_failures:g}/{s.n_per_estimate}", f"{s.median_ess:.1f}", f"{s.n_simulations:,}",
            f"{s.median_wall_s:.1f}"]  # fmt: skip


def markdown_table(summaries: Sequence[Summary]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(_row(s)) + " |" for s in summaries]
    return "\n".join(lines)


def csv_text(summaries: Sequence[Summary]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["problem", "log_truth", "truth", "method", "seeds", "median_log_mu_hat", "min_log_mu_hat",
                "max_log_mu_hat", "median_mu_hat", "median_rel_error", "within_2x", "covered", "reliable",
                "median_failures", "n_per_estimate",
                "median_ess", "simulations", "median_wall_s"])  # fmt: skip
    for s in summaries:
        w.writerow([s.problem, repr(s.log_truth), f"{math.exp(s.log_truth):.6g}", s.method, s.n_seeds,
                    repr(s.median_mu_hat), repr(s.min_mu_hat), repr(s.max_mu_hat),
                    f"{math.exp(s.median_mu_hat):.6g}", f"{s.median_rel_error:.6g}", s.within_2x, s.covered, s.reliable,
                    s.median_failures, s.n_per_estimate, f"{s.median_ess:.6g}", s.n_simulations,
                    f"{s.median_wall_s:.3f}"])  # fmt: skip
    return buf.getvalue()


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` (its folder created if needed), never half-written."""
    path.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, text)


def add_sampler_arguments(p: argparse.ArgumentParser) -> None:
    """The sampler sizes shared by ``validate`` and ``tables``: --k, --n, --n-final, --ce-epochs, ..."""
    d = ExperimentConfig()
    p.add_argument("--k", "--stages", dest="n_stages", type=int, default=None, help=f"stages K (default {d.n_stages})")
    p.add_argument("--n", dest="n_per_stage", type=int, default=None, help=f"rollouts per stage N (default {d.n_per_stage})")
    p.add_argument("--n-final", dest="n_final", type=int, default=None, help=f"final rollouts N_e (default {d.n_final})")
    p.add_argument("--ce-epochs", dest="ce_epochs", type=int, default=None, help=f"epochs per stage (default {d.ce_epochs})")
    p.add_argument("--pretrain-epochs", dest="pretrain_epochs", type=int, default=None,
                   help=f"pretraining epochs (default {d.pretrain_epochs})")
    p.add_argument("--pem", default=None, help="PEM weights (default: the shipped one)")


# -- command ------------------------------------------------------------------------------------------------------

BASELINES = ("mc", "naive50", "mixed50")


def _split(text: str, allowed: Iterable[str], what: str) -> tuple[str, ...]:
    from pemviz.commands import UsageError

    items = tuple(x.strip() for x in text.split(",") if x.strip())
    allowed = tuple(allowed)
    bad = [x for x in items if x not in allowed]
    if bad or not items:
        raise UsageError(f"--{what} {text!r}: use a comma-separated list of {', '.join(allowed)}")
    return items


def methods_for(presets: Sequence[str], baselines: Sequence[str], base: dict[str, Any]) -> list[tuple[str, dict]]:
    """(label, config fields) per method: ``adaptive (PRESET)`` for each preset, then the baselines with as
    many rollouts as the first preset's adaptive run simulates (equal budgets)."""
    out = []
    budget = None
    for name in presets:
        fields = {**PRESETS[name], **base}
        budget = budget or ExperimentConfig(**fields).n_simulations
        out.append((f"adaptive ({name})", fields))
    budget = budget or ExperimentConfig(**base).n_simulations
    for m in baselines:
        out.append((m, {**{k: v for k, v in base.items() if k in ("pem", "sim")}, "method": m, "n_per_stage": budget}))
    return out


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "validate",
        help="judge the sampler and the baselines against exact failure probabilities",
        description="Run the adaptive sampler (one or more presets), MC and naive-50 on problems with exact answers "
        "for several seeds at equal simulation budgets; print truth, median and spread of mu_hat, median relative "
        "error, failures, ESS, simulations and wall time.",
    )
    p.add_argument("--problems", default=",".join(DEFAULT_PROBLEMS),
                   help=f"comma-separated, from {', '.join(PROBLEMS)} (default {','.join(DEFAULT_PROBLEMS)})")
    p.add_argument("--presets", default=f"{DEFAULT_PRESET},paper",
                   help=f"adaptive-sampler presets to compare, from {', '.join(PRESETS)} (default {DEFAULT_PRESET},paper)")
    p.add_argument("--baselines", default="mc,naive50", help=f"from {', '.join(BASELINES)} (default mc,naive50)")
    p.add_argument("--seeds", type=int, default=10, help="seeds per problem and method (default 10)")
    add_sampler_arguments(p)
    p.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    p.add_argument(
        "--out", default="validate", metavar="DIR",
        help=f"folder for validate.md, validate.csv and {RUNS_FILE} (each run as it ends; an existing folder resumes: "
        "finished runs are not run again) (default validate)",
    )  # fmt: skip
    p.set_defaults(func=main)  # fmt: skip


def base_fields(args: argparse.Namespace) -> dict[str, Any]:
    """Config fields given on the command line (validated by building a config)."""
    from pemviz.commands import UsageError

    fields = {k: getattr(args, k) for k in ("n_stages", "n_per_stage", "n_final", "ce_epochs", "pretrain_epochs", "pem")
              if getattr(args, k, None) is not None}  # fmt: skip
    try:
        ExperimentConfig(**fields)
    except ConfigError as exc:
        raise UsageError(str(exc)) from None
    return fields


def main(args: argparse.Namespace) -> int:
    from pemviz.commands import UsageError

    problems = _split(args.problems, PROBLEMS, "problems")
    presets = _split(args.presets, PRESETS, "presets") if args.presets.strip() else ()
    baselines = _split(args.baselines, BASELINES, "baselines") if args.baselines.strip() else ()
    if args.seeds < 1 or args.jobs < 1:
        raise UsageError("--seeds and --jobs must be >= 1")
    if args.pem is not None and not Path(args.pem).is_file():
        raise UsageError(f"--pem {args.pem}: no such file")
    out_dir = Path(args.out) if args.out else None
    if out_dir is not None:
        check_output_folder(out_dir, ("validate.md", "validate.csv"))
    base = base_fields(args)
    methods = methods_for(presets, baselines, base)
    if not methods:
        raise UsageError("nothing to run: give --presets and/or --baselines")
    from pemviz.commands import output_folder

    out_dir = output_folder(args.out)

    def say(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    n_jobs = cap_jobs(args.jobs, say)
    t0 = time.perf_counter()
    truths: dict[str, ExactAnswer] = {}
    for name in problems:
        say(f"{name}: {PROBLEMS[name]}")
        truths[name] = exact_answer(name, args.pem, progress=say)
        say(f"  truth {math.exp(truths[name].log_p_fail):.6g} ({truths[name].source})")
    jobs = [Job(pb, label, tuple(sorted(fields.items())), seed, pem_path=args.pem)
            for pb in problems for label, fields in methods for seed in range(args.seeds)]  # fmt: skip
    say(f"{len(jobs)} runs on {n_jobs} process(es)")

    def on_record(r: RunRecord) -> None:
        err = relative_error(r.log_mu_hat, truths[r.problem].log_p_fail)
        from pemviz.sampling import format_probability

        say(f"  {r.problem:9s} {r.method:22s} seed {r.seed}: mu_hat {format_probability(r.log_mu_hat)} "
            f"(rel. error {err:.3f}), {r.n_failures}/{r.n} failures, {r.wall_s:.1f} s")  # fmt: skip

    records = run_jobs(jobs, n_jobs, on_record, runs_file=out_dir / RUNS_FILE, progress=True)
    summaries = summarise(records, truths)
    md = [f"# pemviz validate: {args.seeds} seeds, equal budgets ({summaries[0].n_simulations:,} simulations)", ""]
    for name in problems:
        md.append(f"- **{name}**: {PROBLEMS[name]}; truth {math.exp(truths[name].log_p_fail):.6g}: {truths[name].source}")
    md += ["", markdown_table(summaries), ""]
    for name in problems:
        if truths[name].table:
            md += [f"Refinement of the {name} truth:", "", truths[name].table, ""]
    md.append(f"Total wall time {time.perf_counter() - t0:.0f} s.")
    text = "\n".join(md) + "\n"
    print(text)
    write_atomic(out_dir / "validate.md", text)
    write_atomic(out_dir / "validate.csv", csv_text(summaries))
    say(f"wrote {out_dir / 'validate.md'}, {out_dir / 'validate.csv'} and {out_dir / RUNS_FILE}")
    return 0
