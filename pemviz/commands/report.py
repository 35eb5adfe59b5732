"""``pemviz report RUN``: a safety-case report of a run, one self-contained HTML page and its Markdown twin, from
the run's result document (:mod:`pemviz.sinks.report`): ``--json RESULT.json``, or the ``run.result.json`` a
recording run writes beside ``run.rrd``. ``pemviz run --report PAGE.html`` writes the same page at the end of a run."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pemviz.commands import UsageError, add_command
from pemviz.io.result import RESULT_BESIDE_SUFFIX, RESULT_FORMAT, result_beside
from pemviz.sinks.report import check_report_paths, write_report

REQUIRED = ("format", "scenario", "method", "seed", "estimate", "n_simulations")
"""The fields a result document must have for a report (the rest is shown where present)."""


DESCRIPTION = """
Write a safety-case report of a run from its result document (pemviz run --json RESULT.json, or the one a run writes
beside its recording: give the recording RUN.rrd): one self-contained HTML page, readable offline, and its Markdown
twin (PAGE.md).
"""
"""``pemviz report --help``'s description."""


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``pemviz report`` and its flags to the sub-command parsers ``sub``."""
    p = add_command(sub, "report", DESCRIPTION)
    p.add_argument("result", metavar="RUN", help="the run's result document (pemviz run --json), or its recording")
    p.add_argument(
        "--out", metavar="PAGE.html", help="where the page goes (default: RUN.html beside the source; its twin PAGE.md)"
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing page and its twin")
    p.set_defaults(func=main)


def read_result(path: Path) -> dict:
    """The result document at ``path``.

    Raises:
        UsageError: not a readable JSON file, or not a pemviz result document (one line saying what it is)."""
    if not path.exists():
        raise UsageError(f"{path}: no such file")
    if path.is_dir():
        raise UsageError(f"{path}: a folder; give a result document (RESULT.json) or a saved recording (RUN.rrd)")
    if path.suffix == ".rrd":
        beside = result_beside(path)
        if not beside.exists():
            raise UsageError(
                f"{path}: a recording without its result document beside it ({beside.name}): a run "
                "stopped before its estimate, or a recording pemviz did not save; report a finished "
                "run's recording, or the JSON of pemviz run --json RESULT.json"
            )
        return read_result(beside)
    if path.suffix == ".parquet":
        raise UsageError(
            f"{path}: a rollout file, not a result document; `pemviz report` reads the JSON that "
            "`pemviz run --json RESULT.json` writes, or a saved recording (or give --report PAGE.html "
            "to pemviz run)"
        )
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise UsageError(f"{path}: not a readable JSON file ({exc})") from None
    if not isinstance(doc, dict) or doc.get("format") != RESULT_FORMAT:
        raise UsageError(
            f"{path}: not a pemviz result document (format {RESULT_FORMAT!r}); write one with "
            "pemviz run --json RESULT.json"
        )
    missing = [k for k in REQUIRED if k not in doc]
    if missing or not isinstance(doc.get("estimate"), dict):
        raise UsageError(f"{path}: a result document without {', '.join(missing) or 'an estimate'}")
    return doc


def main(args: argparse.Namespace) -> int:
    """``pemviz report``: write a run's HTML page and its Markdown twin from its result document or recording.

    Returns:
        The exit status, 0.

    Raises:
        UsageError: a page or twin that cannot be written (or exists without ``--overwrite``), or a result document
            that lacks a field."""
    src = Path(args.result)
    doc = read_result(src)
    name = src.name[: -len(RESULT_BESIDE_SUFFIX)] if src.name.endswith(RESULT_BESIDE_SUFFIX) else src.stem
    out = Path(args.out) if args.out is not None else src.with_name(name + ".html")
    flag = "--out" if args.out is not None else "the report (named after its result; --out names another)"
    try:
        check_report_paths(out, flag, overwrite=args.overwrite)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    try:
        page, twin = write_report(out, doc, overwrite=args.overwrite)
    except KeyError as exc:
        raise UsageError(f"{src}: a result document without the field {exc}") from None
    print(f"report: {page} (and {twin})", file=sys.stderr)
    return 0
