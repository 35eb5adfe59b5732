"""``pemviz tables``: the paper's Tables II and III with repetitions, honest error bars and the exact answer.

Table II: MC_100, MC_10000, naive-50_100, naive-50_1000 and adaptive_100 (the paper's
settings), plus the adaptive sampler under other presets (``--extra``: the authors' code, pemviz's
improvements). Table III: the adaptive sampler with each robustness metric (classic, AGM, smooth-cumulative).
Every row: R repetitions (seeds 0..R-1), mu_hat as mean +- standard error std/sqrt(R) (the authors divided
by R), failures, NLL (mean over failing rollouts, and -log-mean-exp), ESS, the exact p_fail and the ratio.

Writes ``tables.md``, ``tables.csv`` and ``tables.rrd`` into ``--out``: the recording holds every
repetition's per-stage proposal curve q(detect | d) (``curves/<row>/rep_RR/stage_KK`` on the ``gap_mm``
timeline) and the paper's Fig. 4: the curves at stage kappa = 3 averaged over repetitions, per metric
(``fig4/<metric>``; ``fig4/<preset>/<metric>`` for the ``--extra`` presets), beside the PEM's p(detect | d)
(``fig4/pem``). A :class:`~pemviz.sampling.StateProposal`'s curve holds its other inputs at the start state.
"""

from __future__ import annotations

import argparse
import csv
import io
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pemviz.commands.validate import (
    PROBLEMS,
    RUNS_FILE,
    ExactAnswer,
    Job,
    RunRecord,
    _split,
    base_fields,
    build_problem,
    exact_answer,
    run_jobs,
    add_sampler_arguments,
    write_atomic,
)
from pemviz.config import METRICS, PRESETS, ExperimentConfig
from pemviz.files import check_output_folder
from pemviz.resources import cap_jobs
from pemviz.sampling import format_probability

FIG4_STAGE = 3
"""The paper's Fig. 4 shows the proposal after stage kappa = 3."""

PEM_RGBA = (30, 30, 30, 255)
METRIC_RGBA = {"classic": (40, 110, 230, 255), "agm": (230, 120, 30, 255), "smooth-cumulative": (40, 170, 80, 255)}


def stage_colour(stage: int, n_stages: int) -> tuple[int, int, int, int]:
    """Blue (early) to orange (late) for the proposal curves of stages 0..n_stages."""
    f = stage / max(1, n_stages)
    return (int(40 + 215 * f), int(110 + 40 * f), int(230 - 200 * f), 255)


@dataclass(frozen=True)
class RowSpec:
    """One table row: its label, the table it belongs to and the config fields of its runs."""

    table: str
    label: str
    fields: tuple[tuple[str, Any], ...]


@dataclass(frozen=True)
class Row:
    """A row's numbers over its repetitions (logs in nats)."""

    table: str
    label: str
    reps: int
    log_mean: float
    log_se: float
    mean_failures: float
    n: int
    nll_mean: float
    nll_lme: float
    ess: float
    log_truth: float
    wall_s: float
    covered: int = 0
    """Repetitions whose 95 % interval holds the exact answer."""
    reliable: int = 0
    """Repetitions whose verdict is ``reliable``."""


def log_mean_and_se(logs: Sequence[float]) -> tuple[float, float]:
    """log of the mean and of the standard error std/sqrt(n) (std with n - 1) of values given as logs.

    Exact for values far below float64's range: everything is scaled by the largest value first.
    """
    x = np.asarray(logs, dtype=np.float64)
    n = x.size
    m = float(np.max(x))
    if m == -math.inf:
        return -math.inf, -math.inf
    v = np.exp(x - m)
    mean = float(v.mean())
    sd = float(v.std(ddof=1)) if n > 1 else 0.0
    return m + math.log(mean), (m + math.log(sd / math.sqrt(n)) if sd > 0 else -math.inf)


def summarise_row(spec: RowSpec, records: Sequence[RunRecord], log_truth: float) -> Row:
    log_mean, log_se = log_mean_and_se([r.log_mu_hat for r in records])
    nll = [r.nll_mean for r in records if r.n_failures > 0]
    lme = [r.nll_lme for r in records if r.n_failures > 0]
    return Row(
        spec.table, spec.label, len(records), log_mean, log_se, float(np.mean([r.n_failures for r in records])),
        records[0].n, float(np.mean(nll)) if nll else math.nan, float(np.mean(lme)) if lme else math.nan,
        float(np.mean([r.ess for r in records])), log_truth, float(np.sum([r.wall_s for r in records])),
        sum(r.log_ci_lo <= log_truth <= r.log_ci_hi for r in records), sum(r.verdict == "reliable" for r in records),
    )  # fmt: skip


def row_specs(base: dict[str, Any], extra: Sequence[str], mc_large: int, naive_large: int) -> list[RowSpec]:
    """Table II then Table III (the classic row of Table III is Table II's adaptive_N row)."""
    n = ExperimentConfig(**base).n_per_stage
    sim = {k: v for k, v in base.items() if k in ("pem",)}
    specs = [
        RowSpec("II", f"MC_{n}", tuple(sorted({**sim, "method": "mc", "n_per_stage": n}.items()))),
        RowSpec("II", f"MC_{mc_large}", tuple(sorted({**sim, "method": "mc", "n_per_stage": mc_large}.items()))),
        RowSpec("II", f"naive-50_{n}", tuple(sorted({**sim, "method": "naive50", "n_per_stage": n}.items()))),
        RowSpec("II", f"naive-50_{naive_large}",
                tuple(sorted({**sim, "method": "naive50", "n_per_stage": naive_large}.items()))),
        RowSpec("II", f"adaptive_{n}", tuple(sorted(base.items()))),
    ]  # fmt: skip
    for name in extra:
        specs.append(RowSpec("II", f"adaptive_{n} ({name})", tuple(sorted({**PRESETS[name], **base}.items()))))
    for metric in METRICS:
        if metric != "classic":
            specs.append(RowSpec("III", f"r_{metric}", tuple(sorted({**base, "metric": metric}.items()))))
    for name in extra:
        for metric in METRICS:
            if metric != "classic":
                fields = {**PRESETS[name], **base, "metric": metric}
                specs.append(RowSpec("III", f"r_{metric} ({name})", tuple(sorted(fields.items()))))
    return specs


def _fmt_row(r: Row) -> list[str]:
    ratio = "-" if r.log_mean == -math.inf else f"{math.exp(r.log_mean - r.log_truth):.3g}"
    se = "" if r.log_se == -math.inf else f" (+-{format_probability(r.log_se, 2)})"
    nll = "-" if math.isnan(r.nll_mean) else f"{r.nll_mean:.1f}"
    lme = "-" if math.isnan(r.nll_lme) else f"{r.nll_lme:.1f}"
    return [r.label, f"{format_probability(r.log_mean, 3)}{se}", f"{r.mean_failures:.1f}/{r.n}", nll, lme,
            f"{r.ess:.1f}", format_probability(r.log_truth, 4), ratio, f"{r.covered}/{r.reps}",
            f"{r.reliable}/{r.reps}"]  # fmt: skip


HEADER = ("method", "mu_hat (+- s.e.)", "failures", "NLL mean", "NLL -log-mean-exp", "ESS", "exact p_fail",
          "mean / exact", "95% CI covers", "reliable")  # fmt: skip


def markdown(rows: Sequence[Row], table: str) -> str:
    lines = ["| " + " | ".join(HEADER) + " |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    lines += ["| " + " | ".join(_fmt_row(r)) + " |" for r in rows if r.table == table]
    return "\n".join(lines)


def csv_text(rows: Sequence[Row]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["table", "method", "reps", "mu_hat_mean", "mu_hat_se", "log_mu_hat_mean", "log_mu_hat_se",
                "mean_failures", "n", "nll_mean", "nll_log_mean_exp", "ess", "exact_p_fail", "log_exact_p_fail",
                "wall_s", "covered", "reliable"])  # fmt: skip
    for r in rows:
        w.writerow([r.table, r.label, r.reps, format_probability(r.log_mean, 6), format_probability(r.log_se, 6),
                    repr(r.log_mean), repr(r.log_se), r.mean_failures, r.n, r.nll_mean, r.nll_lme, r.ess,
                    format_probability(r.log_truth, 6), repr(r.log_truth), f"{r.wall_s:.2f}", r.covered,
                    r.reliable])  # fmt: skip
    return buf.getvalue()


def write_recording(path: Path, specs: Sequence[RowSpec], records: dict[str, list[RunRecord]], grid: np.ndarray,
                    pem_curve: np.ndarray, description: str) -> None:  # fmt: skip
    """Every adaptive repetition's per-stage proposal curves and Fig. 4 into a rerun file (atomic)."""
    import rerun as rr

    from pemviz.files import write_rrd

    gap_mm = rr.TimeColumn("gap_mm", sequence=np.round(grid * 1000).astype(np.int64))
    write_rrd(path, lambda stream: _log_tables(stream, gap_mm, specs, records, pem_curve, description),
              app_id="pemviz-tables")


def _log_tables(stream, gap_mm, specs, records, pem_curve, description) -> None:  # type: ignore[no-untyped-def]
    import rerun as rr

    def curve(entity: str, values: np.ndarray, colour, name: str) -> None:
        stream.log(entity, rr.SeriesLines(colors=[colour], names=[name], widths=[2.0]), static=True)
        stream.send_columns(entity, indexes=[gap_mm], columns=rr.Scalars.columns(scalars=np.asarray(values, float)))

    stream.log("description", rr.TextDocument(description, media_type=rr.MediaType.MARKDOWN), static=True)
    curve("fig4/pem", pem_curve, PEM_RGBA, "PEM p(detect | d)")
    for spec in specs:
        recs = [r for r in records[spec.label] if r.curves is not None]
        if not recs:
            continue
        key = spec.label.replace(" ", "_").replace("(", "").replace(")", "")
        for r in recs:
            n_stages = r.curves.shape[0] - 1
            for k, c in enumerate(r.curves):
                curve(f"curves/{key}/rep_{r.seed:02d}/stage_{k:02d}", c, stage_colour(k, n_stages),
                      f"{spec.label} rep {r.seed} stage {k}")  # fmt: skip
        metric = dict(spec.fields).get("metric", "classic")
        preset = spec.label[spec.label.index("(") + 1 : -1] if spec.label.endswith(")") else None
        if spec.label.startswith(("adaptive", "r_")) and all(r.curves.shape[0] > FIG4_STAGE for r in recs):
            mean = np.mean([r.curves[FIG4_STAGE] for r in recs], axis=0)
            where = f"fig4/{metric}" if preset is None else f"fig4/{preset}/{metric}"
            curve(where, mean, METRIC_RGBA.get(metric, (120, 120, 120, 255)),
                  f"{metric}{'' if preset is None else f' ({preset})'}: mean q(detect | d) at stage {FIG4_STAGE} "
                  f"over {len(recs)} repetitions")  # fmt: skip


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "tables",
        help="reproduce the paper's Tables II and III with repetitions and the exact answer",
        description="Table II (MC, naive-50, adaptive) and Table III (robustness metrics) with repetitions, "
        "mean +- standard error, failures, NLL, ESS and the exact p_fail; Markdown, CSV and a rerun recording "
        "of every repetition's proposal curves (Fig. 4).",
    )
    p.add_argument("--problem", default="main", help=f"one of {', '.join(PROBLEMS)} (default main)")
    p.add_argument("--reps", type=int, default=10, help="repetitions per row (default 10)")
    p.add_argument("--extra", default="paper,authors-code",
                   help=f"extra adaptive rows with these presets, from {', '.join(PRESETS)} "
                        "(default paper,authors-code; '' for none)")
    p.add_argument("--mc-large", type=int, default=10000, help="rollouts of the large MC row (default 10000)")
    p.add_argument("--naive-large", type=int, default=1000, help="rollouts of the large naive-50 row (default 1000)")
    add_sampler_arguments(p)
    p.add_argument("--jobs", type=int, default=2, help="worker processes (default 2: the CI machine's cores)")
    p.add_argument(
        "--out", default="tables", metavar="DIR",
        help=f"folder for tables.md, tables.csv, tables.rrd and {RUNS_FILE} (each run as it ends; an existing folder "
        "resumes: finished runs are not run again) (default tables)",
    )  # fmt: skip
    p.add_argument("--no-record", action="store_true", help="write no recording")
    p.set_defaults(func=main)  # fmt: skip


def main(args: argparse.Namespace) -> int:
    from pemviz.commands import UsageError

    if args.problem not in PROBLEMS:
        raise UsageError(f"--problem {args.problem!r}: use one of {', '.join(PROBLEMS)}")
    extra = _split(args.extra, PRESETS, "extra") if args.extra.strip() else ()
    if args.reps < 2:
        raise UsageError("--reps must be >= 2 (the standard error needs two repetitions)")
    if args.jobs < 1 or args.mc_large < 1 or args.naive_large < 1:
        raise UsageError("--jobs, --mc-large and --naive-large must be >= 1")
    if args.pem is not None and not Path(args.pem).is_file():
        raise UsageError(f"--pem {args.pem}: no such file")
    out = check_output_folder(args.out, ("tables.md", "tables.csv", "tables.rrd"))
    base = base_fields(args)
    from pemviz.commands import output_folder

    out = output_folder(out)

    def say(text: str) -> None:
        print(text, file=sys.stderr, flush=True)

    n_jobs = cap_jobs(args.jobs, say)

    t0 = time.perf_counter()
    say(f"{args.problem}: {PROBLEMS[args.problem]}")
    truth: ExactAnswer = exact_answer(args.problem, args.pem, progress=say)
    say(f"  exact p_fail {math.exp(truth.log_p_fail):.6g} ({truth.source})")
    specs = row_specs(base, extra, args.mc_large, args.naive_large)
    jobs = [Job(args.problem, s.label, s.fields, seed, keep_curves=True, pem_path=args.pem)
            for s in specs for seed in range(args.reps)]  # fmt: skip
    say(f"{len(jobs)} runs on {n_jobs} process(es)")

    def on_record(r: RunRecord) -> None:
        say(f"  {r.method:28s} rep {r.seed}: mu_hat {format_probability(r.log_mu_hat)} {r.n_failures}/{r.n} failures "
            f"{r.wall_s:.1f} s")  # fmt: skip

    # the slow (adaptive) runs first so that two workers finish together
    order = sorted(range(len(jobs)), key=lambda i: dict(jobs[i].fields).get("method", "adaptive") != "adaptive")
    done = run_jobs([jobs[i] for i in order], n_jobs, on_record, runs_file=out / RUNS_FILE, progress=True)
    by_label: dict[str, list[RunRecord]] = {s.label: [] for s in specs}
    for r in sorted(done, key=lambda r: r.seed):
        by_label[r.method].append(r)
    rows = [summarise_row(s, by_label[s.label], truth.log_p_fail) for s in specs]
    # Table III's classic rows are Table II's adaptive rows (same settings, same seeds)
    table3 = []
    for suffix in ("", *(f" ({name})" for name in extra)):
        classic = next(r for r in rows if r.table == "II" and r.label == f"{specs[4].label}{suffix}")
        table3.append(Row("III", f"r_classic{suffix}", *[getattr(classic, f) for f in list(Row.__dataclass_fields__)[2:]]))
        table3 += [r for r in rows if r.table == "III" and r.label.endswith(suffix) and (suffix or "(" not in r.label)]
    rows_all = [r for r in rows if r.table == "II"] + table3
    wall = time.perf_counter() - t0
    cfg = ExperimentConfig(**base)
    text = "\n".join([
        f"# pemviz tables: {PROBLEMS[args.problem]}",
        "",
        f"{args.reps} repetitions per row (seeds 0..{args.reps - 1}); mu_hat is the mean over repetitions +- the "
        f"standard error std/sqrt({args.reps}); failures and ESS are means over repetitions; NLL is over failing "
        f"rollouts (nats), averaged over repetitions. Adaptive: K = {cfg.n_stages}, N = {cfg.n_per_stage}, "
        f"N_e = {cfg.n_final}, sigma = {cfg.quantile_level}, alpha = {cfg.smoothing}, {cfg.ce_epochs} epochs per stage.",
        f"Exact p_fail {format_probability(truth.log_p_fail, 5)}: {truth.source}.",
        "",
        "## Table II: methods (metric: classic)",
        "",
        markdown(rows_all, "II"),
        "",
        "## Table III: robustness metrics (adaptive; paper settings, then each --extra preset)",
        "",
        markdown(rows_all, "III"),
        "",
        *(["## Exact answer: refinement", "", truth.table, ""] if truth.table else []),
        f"Wall time {wall:.0f} s on {n_jobs} process(es).",
    ]) + "\n"  # fmt: skip
    print(text)
    write_atomic(out / "tables.md", text)
    write_atomic(out / "tables.csv", csv_text(rows_all))
    say(f"wrote {out / 'tables.md'}, {out / 'tables.csv'} and {out / RUNS_FILE}")
    if not args.no_record:
        problem = build_problem(args.problem, args.pem)
        write_recording(out / "tables.rrd", specs, by_label, problem.curve_grid, problem.target_curve(), text)
        say(f"wrote {out / 'tables.rrd'}")
    return 0
