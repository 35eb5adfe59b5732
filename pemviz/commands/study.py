"""What the study commands ``validate`` and ``tables`` share: sampler sizes, ``--jobs`` and ``--out``
(:func:`add_study_arguments`), the config fields (:func:`base_fields`), progress lines (:func:`say`), runs resumed
from the output folder (:func:`run_study`) and report files (:func:`write_study`)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pemviz.commands import add_setting, pem_argument, setting_error, split_choices
from pemviz.config import ConfigError, ExperimentConfig
from pemviz.io.files import write_text_atomic

if TYPE_CHECKING:
    from pemviz.studies.validation import Job, RunRecord

SAMPLER_SETTINGS = ("n_stages", "n_per_stage", "n_final", "ce_epochs", "pretrain_epochs", "pem")
"""The settings ``validate`` and ``tables`` take from the command line."""


def add_study_arguments(
    p: argparse.ArgumentParser, name: str, files: str, jobs: int | None, jobs_note: str = ""
) -> None:
    """The arguments ``validate`` and ``tables`` share: the sampler sizes (--k, --n, --n-final, --ce-epochs, ...),
    ``--jobs`` (default ``jobs``; None: every usable CPU, :func:`pemviz.engine.resources.usable_cpus`) and ``--out``
    (default ``name``: the folder of ``files`` and the runs file)."""
    from pemviz.studies.validation import RUNS_FILE

    for setting in SAMPLER_SETTINGS:
        add_setting(p, setting)
    said = "every usable core" if jobs is None else jobs
    p.add_argument("--jobs", type=int, default=jobs, help=f"worker processes (default {said}{jobs_note})")
    p.add_argument(
        "--out",
        default=name,
        metavar="DIR",
        help=f"folder for {files} and {RUNS_FILE} (each run as it ends; an existing folder resumes: finished runs are "
        f"not run again) (default {name})",
    )


def add_presets(p: argparse.ArgumentParser, flag: str, default: str, what: str, note: str = "") -> None:
    """``--FLAG``: comma-separated presets of the adaptive sampler (:data:`pemviz.presets.PRESETS`; ``''``: none),
    read by :func:`presets_of`; ``what`` they are for and a ``note`` after the default, in the help."""
    from pemviz.presets import PRESETS

    p.add_argument(f"--{flag}", default=default, help=f"{what}, from {', '.join(PRESETS)} (default {default}{note})")


def presets_of(text: str, flag: str) -> tuple[str, ...]:
    """The presets of ``--FLAG text`` (:func:`add_presets`) in the order given; ``()`` for ``''``.

    Raises:
        UsageError: a name that is not a preset."""
    from pemviz.presets import PRESETS

    return split_choices(text, PRESETS, flag) if text.strip() else ()


def say(text: str) -> None:
    """A progress line of ``validate`` or ``tables``, on stderr."""
    print(text, file=sys.stderr, flush=True)


def run_study(jobs: Sequence[Job], n_jobs: int, on_record: Callable[[RunRecord], None], out: Path) -> list[RunRecord]:
    """Run a study's ``jobs`` in ``n_jobs`` worker processes with a progress bar, each run appended to the runs file
    in ``out`` as it ends and the runs already there not run again (:func:`pemviz.studies.validation.run_jobs`)."""
    from pemviz.studies.validation import RUNS_FILE, run_jobs

    say(f"{len(jobs)} runs on {n_jobs} process(es)")
    return run_jobs(jobs, n_jobs, on_record, runs_file=out / RUNS_FILE, progress=True)


def write_study(out: Path, name: str, text: str, csv_text: str) -> None:
    """Print a study's report and write it as ``<name>.md`` and ``<name>.csv`` into ``out`` (atomically)."""
    from pemviz.studies.validation import RUNS_FILE

    print(text)
    write_text_atomic(out / f"{name}.md", text)
    write_text_atomic(out / f"{name}.csv", csv_text)
    say(f"wrote {out / f'{name}.md'}, {out / f'{name}.csv'} and {out / RUNS_FILE}")


def base_fields(args: argparse.Namespace) -> dict[str, Any]:
    """Config fields given on the command line (validated by building a config; ``--pem`` by
    :func:`pemviz.commands.pem_argument`).

    Raises:
        UsageError: a value outside its setting's range, or a ``--pem`` that is neither shipped nor a file."""
    fields = {k: getattr(args, k) for k in SAMPLER_SETTINGS if getattr(args, k, None) is not None}
    try:
        ExperimentConfig.of(**fields)
    except ConfigError as exc:
        raise setting_error(exc) from None
    pem_argument(fields.get("pem"))
    return fields
