"""The files a ``pemviz run`` will write, planned and checked once from its arguments before any work
(:func:`plan_outputs`); nothing is created here."""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pemviz.commands import UsageError, check_save_path
from pemviz.io.files import check_output_folder, check_output_path

if TYPE_CHECKING:
    from pemviz.config import ExperimentConfig


@dataclass(frozen=True)
class RunOutputs:
    """Every file a run writes, by the flag that asks for it (None: not asked).

    Attributes:
        recording: the ``.rrd`` recording when it goes to a file (``--save``, or the default under ``recordings/``).
        rollouts: the rollout file (``--save-rollouts``; its sidecar and proposal checkpoint beside it).
        json, junit, report: ``--json``, ``--junit`` and ``--report`` (the report's Markdown twin beside it).
        overwrite: ``--overwrite``: existing files may be replaced."""

    recording: Path | None = None
    rollouts: Path | None = None
    json: Path | None = None
    junit: Path | None = None
    report: Path | None = None
    overwrite: bool = False

    @property
    def result_files(self) -> tuple[Path | None, Path | None, Path | None]:
        """``(--json, --junit, --report)``."""
        return self.json, self.junit, self.report

    @property
    def asks_results(self) -> bool:
        """Whether a result file is asked for (``--json``, ``--junit``, ``--report``)."""
        return any(path is not None for path in self.result_files)

    def named(self) -> list[tuple[str, Path]]:
        """Every file, with the flag that writes it: the recording and its result document, the rollout file, its
        sidecar and its proposal checkpoint, the result files and the report's Markdown twin."""
        from pemviz.io.result import result_beside
        from pemviz.io.rollout_format import proposal_path, sidecar_path

        named: list[tuple[str, Path]] = []
        if self.recording is not None:
            named += [("--save", self.recording), ("--save (its result document)", result_beside(self.recording))]
        if self.rollouts is not None:
            named += [
                ("--save-rollouts", self.rollouts),
                ("--save-rollouts (its sidecar)", sidecar_path(self.rollouts)),
                ("--save-rollouts (its proposal checkpoint)", proposal_path(self.rollouts)),
            ]
        named += [
            (flag, path)
            for flag, path in zip(("--json", "--junit", "--report"), self.result_files, strict=True)
            if path is not None
        ]
        if self.report is not None:
            from pemviz.sinks.report import markdown_twin  # the report's module only for a report

            named.append(("--report (its Markdown twin)", markdown_twin(self.report)))
        return named

    def unwritten(self, rollouts: bool = True) -> str:
        """``not written: r.parquet (--save-rollouts), r.json (--json)``: the outputs asked for that a run interrupted
        in its stages does not write (the rollout file too, unless ``rollouts`` is False: it kept its last finished
        stage); empty when none was asked."""
        asked = [
            (self.rollouts if rollouts else None, "--save-rollouts"),
            *zip(self.result_files, ("--json", "--junit", "--report"), strict=True),
        ]
        names = [f"{path} ({flag})" for path, flag in asked if path is not None]
        return f"not written: {', '.join(names)}" if names else ""


def plan_outputs(
    args: argparse.Namespace, cfg: ExperimentConfig, target: str, default_recording: Path | None
) -> RunOutputs:
    """Every file the run of ``args`` will write, each checked before any work (nothing is created).

    Args:
        args: ``pemviz run``'s arguments.
        cfg: the run's :class:`pemviz.config.ExperimentConfig`.
        target: where the recording goes (``save``, ``stdout``, ``connect``, ``serve``, ``no-record``).
        default_recording: the recording's path under ``recordings/`` when ``--save`` names none.
    Raises:
        UsageError: one line naming the flag and the file: an unwritable path, ``--junit`` without ``--require``,
            ``--save-rollouts`` for a method without importance weights, two outputs naming one file."""
    overwrite = bool(args.overwrite)
    recording = _recording(args, target, default_recording, overwrite)
    rollouts = None
    if args.save_rollouts is not None:
        from pemviz.io.rollout_writer import check_rollouts_path

        if not cfg.method_record.weighted:
            raise UsageError(
                f"--save-rollouts: method {cfg.method} estimates without importance weights; its "
                "rollouts cannot be estimated from again (use an importance-sampling method)"
            )
        rollouts = _checked(
            lambda: check_rollouts_path(args.save_rollouts, overwrite=overwrite, what="--save-rollouts")
        )
    report = getattr(args, "report_path", None)
    if report is not None:
        from pemviz.sinks.report import check_report_paths

        report = _checked(lambda: check_report_paths(report, "--report", overwrite=overwrite))
    if args.junit_path is not None and cfg.stop.require is None:
        raise UsageError(
            "--junit writes a requirement as a test case: give one with --require, e.g. --require 'p < 1e-9'"
        )
    found = {
        flag: None
        if value is None
        else _checked(lambda v=value, s=suffix, f=flag: check_output_path(v, s, f, overwrite=overwrite))
        for flag, value, suffix in (("--json", args.json_path, ".json"), ("--junit", args.junit_path, ".xml"))
    }
    outputs = RunOutputs(recording, rollouts, found["--json"], found["--junit"], report, overwrite)
    check_distinct(outputs)
    return outputs


def check_distinct(outputs: RunOutputs) -> None:
    """Refuse two outputs of one run that name the same file (e.g. ``--save-rollouts b.parquet``, whose sidecar is
    ``b.rollouts.json``, with ``--json b.rollouts.json``): the second would replace the first at the end of the run.

    Raises:
        UsageError: naming both flags and the file."""
    seen: dict[Path, str] = {}
    for flag, path in outputs.named():
        key = Path(os.path.abspath(path))
        if key in seen:
            raise UsageError(f"{flag} and {seen[key]} both write {path}: give each output its own name")
        seen[key] = flag


def _recording(args: argparse.Namespace, target: str, default: Path | None, overwrite: bool) -> Path | None:
    """The recording's file and its result document's, checked; None unless the recording goes to a file."""
    if target != "save":
        return None
    from pemviz.io.result import result_beside  # the recording's result document, written beside it at the end

    if args.save is None:  # recordings/ is made once every check has passed
        assert default is not None
        _checked(
            lambda: check_output_folder(default.parent, (default.name, result_beside(default).name), "recording folder")
        )
        return default
    path = check_save_path(Path(args.save), overwrite)
    _checked(
        lambda: check_output_path(
            result_beside(path), ".json", "--save (the recording's result document)", overwrite=overwrite
        )
    )
    return path


def _checked(check: Any) -> Any:
    """``check()``, its ValueError as a UsageError (one line)."""
    try:
        return check()
    except ValueError as exc:
        raise UsageError(str(exc)) from None
