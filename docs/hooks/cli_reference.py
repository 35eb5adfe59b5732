"""MkDocs hook: renders ``pemviz --help`` and every sub-command's help into ``cli.md`` at build time, and the choices
of a setting where a page asks for them.

The marker ``<!-- pemviz-cli -->`` is replaced with one section per command, each the exact text ``argparse`` prints,
so the reference never drifts from the code. ``<!-- pemviz-choices NAME -->`` is replaced with a list of the choices
of setting NAME (:data:`pemviz.settings.SETTINGS`; ``preset``: :data:`pemviz.presets.PRESET_HELP`), each with the words
the panel's hint and ``pemviz run --help`` give it.
"""

from __future__ import annotations

import argparse
import os
import re

MARKER = "<!-- pemviz-cli -->"
CHOICES = re.compile(r"<!-- pemviz-choices ([a-z_]+) -->")


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


def choices_markdown(name: str) -> str:
    """``- **classic**: the worst step's margin alone`` for each choice of setting ``name`` (or of ``preset``)."""
    from pemviz.presets import PRESET_HELP
    from pemviz.settings import SETTINGS

    pairs = PRESET_HELP.items() if name == "preset" else SETTINGS[name].choice_help
    return "\n".join(f"- **{value}**: {what}" for value, what in pairs)


def on_page_markdown(markdown: str, page, config, files) -> str:
    """MkDocs' page hook: the page's Markdown with its CLI and choices markers replaced (``page``, ``config`` and
    ``files`` are MkDocs' objects, unused)."""
    if MARKER in markdown:
        markdown = markdown.replace(MARKER, cli_markdown())
    return CHOICES.sub(lambda m: choices_markdown(m.group(1)), markdown)
