"""pemviz: estimate the probability of rare safety failures of a perception-driven controller with a perception
error model (PEM) and adaptive importance sampling, recorded for rerun and shown in a browser panel.

The command line ``pemviz run | serve | pem | data | estimate | validate | tables``. Each sub-command lives in ``pemviz/commands/<name>.py`` and exposes ``register(subparsers)``, which adds
its parser and sets ``func(args) -> int`` as the parser default.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from pemviz import __version__
from pemviz.commands import UsageError

COMMAND_MODULES = (
    "pemviz.commands.run",
    "pemviz.commands.data",
    "pemviz.commands.pem",
    "pemviz.commands.serve",
    "pemviz.commands.estimate",
    "pemviz.commands.validate",
    "pemviz.commands.tables",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pemviz",
        description=__doc__.split("\n\n")[0].replace("\n", " "),
        epilog="`pemviz COMMAND --help` describes a command; the user guide is in docs/ (mkdocs serve).",
    )
    parser.add_argument("--version", action="version", version=f"pemviz {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (UsageError, ValueError, FileNotFoundError) as exc:  # bad input: one line, no traceback
        if os.environ.get("PEMVIZ_DEBUG"):
            raise
        print(f"pemviz {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
