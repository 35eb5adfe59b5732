"""The console output the README and the user guide quote, made by the current code: each quoted block names the
command that prints it, this script runs every such command, says which blocks no longer match what the command
prints, and with ``--write`` replaces them with what it prints now.

A quoted block is a fenced ``text`` block right after a marker line naming its command::

    <!-- quoted: pemviz run --scenario crossing --no-record --seed 0 -->
    ```text
    mu_hat = 2.844e-04, 95% CI [2.32e-04, 3.45e-04], ...
    ```

The block matches the output when, whitespace collapsed (a block may wrap a long line) and times masked (a number of
seconds, milliseconds or minutes, which differ from machine to machine), its text appears in the output, in order,
``...`` standing for any elided text. Every other number must be the same: the seed contract makes a run the same bits
on every machine. ``tests/project/test_quoted_outputs.py`` runs the same check in the test command.

The screenshots of ``assets/screenshots/`` are made the same way, by the commands of one table
(``SCREENSHOTS`` in ``benchmarks/screenshots.py``); ``--screenshots`` runs them all and rewrites
``assets/screenshots/MANIFEST.md`` (each image's command, commit and date). It needs Debian's ``chromium`` and takes
about 5 min on 2 cores; ``tests/project/test_screenshot_manifest.py`` checks the table and makes the cheapest two.

Usage::

    python benchmarks/docs_assets.py            # which quoted blocks are stale (exit 1 if any)
    python benchmarks/docs_assets.py --write    # rewrite the stale ones from the commands' output, in their shape
    python benchmarks/docs_assets.py --screenshots                  # remake every screenshot and the manifest
    python benchmarks/docs_assets.py --screenshots --only panel_cut_in.png viser_panel  # the entries making these
    python benchmarks/docs_assets.py --write --screenshots          # both: every asset of the docs
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import shlex
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

MARKER = re.compile(r"^<!-- quoted: (pemviz .+?) -->\s*$")
TIME = re.compile(r"~?\d[\d.,]*\s?(?:ms|s|min|h)\b")
"""A duration (``5.8 s``, ``~0.23 ms``, ``~4.3 min``): masked before comparing."""


@dataclass(frozen=True)
class Block:
    """A quoted block: its file, the line numbers of its text (first, end; 0-based, end exclusive), its command, its
    lines."""

    path: Path
    first: int
    end: int
    command: str
    lines: tuple[str, ...]


def documents() -> list[Path]:
    """The README and every page of the user guide."""
    return [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def quoted_blocks(path: Path) -> list[Block]:
    """The quoted blocks of ``path``.

    Raises:
        ValueError: a marker not followed by a fenced text block (file and line in the message).
    """
    lines = path.read_text().splitlines()
    out = []
    for i, line in enumerate(lines):
        m = MARKER.match(line)
        if not m:
            continue
        if i + 1 >= len(lines) or lines[i + 1].strip() != "```text":
            raise ValueError(f"{path.name}:{i + 1}: a quoted marker must be followed by a ```text block")
        end = next((j for j in range(i + 2, len(lines)) if lines[j].strip() == "```"), None)
        if end is None:
            raise ValueError(f"{path.name}:{i + 2}: the quoted block is not closed")
        out.append(Block(path, i + 2, end, m.group(1), tuple(lines[i + 2 : end])))
    return out


def run(command: str) -> str:
    """What ``command`` (``pemviz ...``) prints, stdout then stderr, run in this process."""
    from pemviz.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main(shlex.split(command)[1:])
        except SystemExit:
            pass
    return out.getvalue() + err.getvalue()


def normal(text: str) -> str:
    """Whitespace collapsed and durations masked."""
    return " ".join(TIME.sub("<time>", text).split())


def matches(block_lines: tuple[str, ...] | list[str], output: str) -> bool:
    """Whether the block's text appears in ``output`` (module docstring)."""
    text, where = normal("\n".join(block_lines)), normal(output)
    at = 0
    for part in (p.strip() for p in text.split("...")):
        if not part:
            continue
        found = where.find(part, at)
        if found < 0:
            return False
        at = found + len(part)
    return True


NUMBER = re.compile(r"[-+]?\d[\d,]*(?:\.\d+)?(?:e[-+]?\d+)?%?")
"""A number as printed (``3.548e-04``, ``1,000``, ``88.7``, ``95%``): what a stale block differs in."""


def shape(text: str) -> str:
    """``text`` normalised (:func:`normal`) with every number replaced by ``#``: what a line of a stale block still
    shares with the output line it stands for."""
    return NUMBER.sub("#", normal(text))


def fresh_lines(block: Block, output: str) -> list[str] | None:
    """The block rewritten from ``output``, in its own shape: each of its lines (with the lines that continue it, where
    the block wrapped a long line) replaced by the output line it stands for, the next one whose text begins as it
    does but for its numbers (:func:`shape`); a line the block elided (``...`` at its end) cut after as many words,
    the ``...`` kept; a wrapped line wrapped again at the block's width. None where a line of the block stands for no
    line of the output (the block must then be rewritten by hand)."""
    out_lines = output.splitlines()
    lines, result, cursor, i = block.lines, [], 0, 0
    while i < len(lines):
        if not lines[i].strip():
            result.append(lines[i])
            i += 1
            continue
        head = lines[i].split("...")[0]
        j = next((j for j in range(cursor, len(out_lines)) if shape(out_lines[j]).startswith(shape(head))), None)
        if j is None or not shape(head):
            return None
        o, joined, k = out_lines[j], lines[i], i + 1
        while (  # the block's next lines, while they go on with the same output line (a wrapped line)
            k < len(lines)
            and "..." not in joined
            and lines[k].strip()
            and len(shape(o)) > len(shape(joined))
            and shape(o).startswith(shape(joined + " " + lines[k].split("...")[0]))
        ):
            joined, k = joined + " " + lines[k], k + 1
        new = o
        if "..." in joined:  # elided after as many words as the block kept
            words = list(re.finditer(r"\S+", o))
            kept = len(joined.split("...")[0].split())
            new = o[: words[kept - 1].end()] + " ..." if 0 < kept <= len(words) else o
        if k - i > 1:
            width = max(len(x) for x in lines[i:k])
            result += textwrap.wrap(new, width, break_on_hyphens=False, break_long_words=False)
        else:
            result.append(new)
        cursor, i = j + 1, k
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--write", action="store_true", help="rewrite the stale blocks")
    ap.add_argument(
        "--screenshots",
        action="store_true",
        help="remake the screenshots of benchmarks/screenshots.py's table and their manifest "
        "(the quoted blocks too only with --write)",
    )
    ap.add_argument(
        "--only",
        nargs="+",
        metavar="NAME",
        default=None,
        help="with --screenshots: only the entries that make these images",
    )
    a = ap.parse_args(argv)
    if a.only and not a.screenshots:
        ap.error("--only needs --screenshots")
    if a.screenshots:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from screenshots import regenerate

        shots = regenerate(a.only)
        return max(shots, main(["--write"]) if a.write else 0)
    outputs: dict[str, str] = {}
    stale = unwritten = 0
    for path in documents():
        blocks = quoted_blocks(path)
        lines = path.read_text().splitlines()
        for block in reversed(blocks):  # from the end: a rewrite keeps the earlier blocks' line numbers
            output = outputs.setdefault(block.command, run(block.command))
            if matches(block.lines, output):
                print(f"ok     {path.relative_to(REPO)}:{block.first}: {block.command}")
                continue
            stale += 1
            print(f"stale  {path.relative_to(REPO)}:{block.first}: {block.command}")
            if a.write:
                fresh = fresh_lines(block, output)
                if fresh is None or not matches(fresh, output):
                    print("       not rewritten: a line of it stands for no line of the output; edit it by hand")
                    unwritten += 1
                    continue
                lines[block.first : block.end] = fresh
        if a.write and blocks:
            path.write_text("\n".join(lines) + "\n")
    return 1 if (stale and not a.write) or unwritten else 0


if __name__ == "__main__":
    raise SystemExit(main())
