"""MkDocs hook: renders ``pemviz --help`` and every sub-command's help into ``cli.md`` at build time.

The page holds the marker ``<!-- pemviz-cli -->``; it is replaced with one section per command, each the
exact text ``argparse`` prints, so the reference never drifts from the code.
"""

from __future__ import annotations

import argparse
import os

MARKER = "<!-- pemviz-cli -->"


def _parsers(name: str, parser: argparse.ArgumentParser):
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, child in action.choices.items():
                yield from _parsers(f"{name} {sub}", child)


def cli_markdown() -> str:
    """One ``## pemviz ...`` section per command with its help text in a code block."""
    from pemviz.cli import build_parser

    os.environ["COLUMNS"] = "100"  # argparse wraps at this width
    parts = []
    for name, parser in _parsers("pemviz", build_parser()):
        parser.prog = name
        parts.append(f"## `{name}`\n\n```text\n{parser.format_help().rstrip()}\n```\n")
    return "\n".join(parts)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER in markdown:
        return markdown.replace(MARKER, cli_markdown())
    return markdown
