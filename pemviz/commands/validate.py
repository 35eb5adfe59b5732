"""``pemviz validate``: the sampler and the baselines against exact failure probabilities, several seeds each at equal
simulation budgets (:mod:`pemviz.studies.validation`)."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from pemviz.commands import UsageError, add_command, output_folder, split_choices
from pemviz.commands.study import add_presets, add_study_arguments, base_fields, presets_of, run_study, say, write_study
from pemviz.core.estimate import format_probability, relative_error
from pemviz.engine.resources import cap_jobs, usable_cpus
from pemviz.io.files import check_output_folder
from pemviz.presets import DEFAULT_PRESET
from pemviz.scenarios.problems import PROBLEMS
from pemviz.studies.exact_answers import ExactAnswer, exact_answer, problem_description, validation_problems
from pemviz.studies.validation import (
    BASELINES,
    DEFAULT_PROBLEMS,
    RunRecord,
    methods_for,
    report,
    study_jobs,
    summaries_csv,
    summarise,
)

DESCRIPTION = """
Run the adaptive sampler (one or more presets), MC, naive-50 and AMS on problems with exact answers for several
seeds at equal simulation budgets; print truth, median and spread of mu_hat, median relative error, failures, ESS,
simulations and wall time.
"""
"""``pemviz validate --help``'s description."""


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``pemviz validate`` and its flags to the sub-command parsers ``sub``."""
    p = add_command(sub, "validate", DESCRIPTION)
    p.add_argument(
        "--problems",
        default=",".join(DEFAULT_PROBLEMS),
        help=f"comma-separated, from {', '.join(PROBLEMS)} or a registered scenario with an exact answer "
        f"(default {','.join(DEFAULT_PROBLEMS)})",
    )
    add_presets(p, "presets", f"{DEFAULT_PRESET},paper", "adaptive-sampler presets to compare")
    p.add_argument(
        "--baselines",
        default="mc,naive50,ams",
        help=f"from {', '.join(BASELINES)} or a plugin's method (PEMVIZ_METHODS) (default mc,naive50,ams; "
        "ams: adaptive multilevel splitting, N = budget / 4 particles)",
    )
    p.add_argument("--seeds", type=int, default=10, help="seeds per problem and method (default 10)")
    add_study_arguments(p, "validate", "validate.md, validate.csv", None, ": one seed's run each")
    p.set_defaults(func=main)


def _without_exact(name: str) -> str | None:
    """Why ``name`` is not a problem ``pemviz validate`` can run, where it is a registered scenario without an exact
    answer (None otherwise)."""
    from pemviz.scenarios import registry

    if name not in registry.registered():
        return None
    return (
        f"the {name} scenario has no exact answer to compare with (its Scenario record's exact=True and its problem's "
        f"exact_log_p); check it against plain Monte Carlo instead: pemviz run --scenario {name} --method mc"
    )


def main(args: argparse.Namespace) -> int:
    """``pemviz validate``: every method's seeds on every problem with an exact answer, summarised against it.

    Returns:
        The exit status, 0.

    Raises:
        UsageError: an unknown problem, preset or baseline, nothing to run, ``--seeds`` or ``--jobs`` < 1, or an output
            folder that cannot be used."""
    problems = split_choices(args.problems, validation_problems(), "problems", _without_exact)
    presets = presets_of(args.presets, "presets")
    from pemviz.methods import BUILTIN_METHODS, method_names

    others = tuple(m for m in method_names() if m not in BUILTIN_METHODS)  # plugins' methods
    baselines = split_choices(args.baselines, (*BASELINES, *others), "baselines") if args.baselines.strip() else ()
    if args.seeds < 1 or (args.jobs is not None and args.jobs < 1):
        raise UsageError("--seeds and --jobs must be >= 1")
    out_dir = Path(args.out) if args.out else None
    if out_dir is not None:
        check_output_folder(out_dir, ("validate.md", "validate.csv"))
    base = base_fields(args)
    methods = methods_for(presets, baselines, base)
    if not methods:
        raise UsageError("nothing to run: give --presets and/or --baselines")
    out_dir = output_folder(args.out)

    n_jobs = cap_jobs(args.jobs, say) if args.jobs is not None else usable_cpus()
    t0 = time.perf_counter()
    truths: dict[str, ExactAnswer] = {}
    for name in problems:
        say(f"{name}: {problem_description(name)}")
        truths[name] = exact_answer(name, args.pem, progress=say)
        say(f"  truth {math.exp(truths[name].log_p_fail):.6g} ({truths[name].source})")
    jobs = study_jobs(problems, methods, args.seeds, args.pem)

    def on_record(r: RunRecord) -> None:
        err = relative_error(r.log_mu_hat, truths[r.problem].log_p_fail)
        say(
            f"  {r.problem:9s} {r.method:22s} seed {r.seed}: mu_hat {format_probability(r.log_mu_hat)} "
            f"(rel. error {err:.3f}), {r.n_failures}/{r.n} failures, {r.wall_s:.1f} s"
        )

    records = run_study(jobs, n_jobs, on_record, out_dir)
    summaries = summarise(records, truths)
    text = report(problems, truths, summaries, args.seeds, time.perf_counter() - t0)
    write_study(out_dir, "validate", text, summaries_csv(summaries))
    return 0
