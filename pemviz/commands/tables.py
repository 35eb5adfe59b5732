"""``pemviz tables``: the paper's Tables II and III with repetitions, honest error bars and the exact answer, into
``tables.md``, ``tables.csv`` and ``tables.rrd``; the work is :mod:`pemviz.studies.paper_tables`'s."""

from __future__ import annotations

import argparse
import math
import time

from pemviz.commands import UsageError, add_command, output_folder
from pemviz.commands.study import add_presets, add_study_arguments, base_fields, presets_of, run_study, say, write_study
from pemviz.core.estimate import format_probability
from pemviz.engine.resources import cap_jobs
from pemviz.io.files import check_output_folder
from pemviz.scenarios.problems import PROBLEMS, build_problem
from pemviz.studies.exact_answers import ExactAnswer, exact_answer
from pemviz.studies.paper_tables import (
    records_by_row,
    report,
    row_specs,
    rows_csv,
    table_jobs,
    tables_rows,
    write_recording,
)
from pemviz.studies.validation import RunRecord

DESCRIPTION = """
Table II (MC, naive-50, adaptive) and Table III (robustness metrics) with repetitions, mean +- standard error,
failures, NLL, ESS and the exact p_fail; Markdown, CSV and a rerun recording of every repetition's proposal curves
(Fig. 4).
"""
"""``pemviz tables --help``'s description."""


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``pemviz tables`` and its flags to the sub-command parsers ``sub``."""
    p = add_command(sub, "tables", DESCRIPTION)
    p.add_argument("--problem", default="main", help=f"one of {', '.join(PROBLEMS)} (default main)")
    p.add_argument("--reps", type=int, default=10, help="repetitions per row (default 10)")
    add_presets(p, "extra", "paper,authors-code", "extra adaptive rows with these presets", "; '' for none")
    p.add_argument("--mc-large", type=int, default=10000, help="rollouts of the large MC row (default 10000)")
    p.add_argument("--naive-large", type=int, default=1000, help="rollouts of the large naive-50 row (default 1000)")
    add_study_arguments(p, "tables", "tables.md, tables.csv, tables.rrd", 2, ": the CI machine's cores")
    p.add_argument("--no-record", action="store_true", help="write no recording")
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    """``pemviz tables``: the paper's tables (repetitions of each row against the exact answer) into ``--out``.

    Returns:
        The exit status, 0.

    Raises:
        UsageError: an unknown problem or preset, ``--reps`` < 2, a count < 1, or an output folder that cannot be used.
    """
    if args.problem not in PROBLEMS:
        raise UsageError(f"--problem {args.problem!r}: use one of {', '.join(PROBLEMS)}")
    extra = presets_of(args.extra, "extra")
    if args.reps < 2:
        raise UsageError("--reps must be >= 2 (the standard error needs two repetitions)")
    if args.jobs < 1 or args.mc_large < 1 or args.naive_large < 1:
        raise UsageError("--jobs, --mc-large and --naive-large must be >= 1")
    out = check_output_folder(args.out, ("tables.md", "tables.csv", "tables.rrd"))
    base = base_fields(args)
    out = output_folder(out)

    n_jobs = cap_jobs(args.jobs, say)

    t0 = time.perf_counter()
    say(f"{args.problem}: {PROBLEMS[args.problem]}")
    truth: ExactAnswer = exact_answer(args.problem, args.pem, progress=say)
    say(f"  exact p_fail {math.exp(truth.log_p_fail):.6g} ({truth.source})")
    specs = row_specs(base, extra, args.mc_large, args.naive_large)
    jobs = table_jobs(args.problem, specs, args.reps, args.pem)

    def on_record(r: RunRecord) -> None:
        say(
            f"  {r.method:28s} rep {r.seed}: mu_hat {format_probability(r.log_mu_hat)} {r.n_failures}/{r.n} failures "
            f"{r.wall_s:.1f} s"
        )

    done = run_study(jobs, n_jobs, on_record, out)
    by_label = records_by_row(specs, done)
    rows_all = tables_rows(specs, by_label, truth.log_p_fail, extra)
    text = report(args.problem, args.reps, base, truth, rows_all, n_jobs, time.perf_counter() - t0)
    write_study(out, "tables", text, rows_csv(rows_all))
    if not args.no_record:
        problem = build_problem(args.problem, args.pem)
        write_recording(out / "tables.rrd", specs, by_label, problem.curve_grid, problem.target_curve(), text)
        say(f"wrote {out / 'tables.rrd'}")
    return 0
