"""The lower layers know no scenario: no scene word in the code of :data:`NEUTRAL_FOLDERS`, and none in their
docstrings or comments but on a line that names it as an example ("e.g." or "for example").

The words (:data:`SCENE_WORDS`) name the built-in scenes and their columns: the braking scene, its gap column, its
lead car, the cut-in. Code is every token but comments and docstrings (identifiers and the other strings), read with
:mod:`tokenize`; docstrings are the string statements of a body (:mod:`ast`).
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from dataclasses import dataclass
from pathlib import Path

import pytest

from conftest import REPO

NEUTRAL_FOLDERS = ("pemviz/core", "pemviz/engine", "pemviz/estimators", "pemviz/sinks", "pemviz/app")
"""The folders (relative to the repository) whose modules must name no scenario; add a folder once it is clean."""

SCENE_WORDS = re.compile(r"braking|gap_m|\blead\b|cut[-_]in|BrakingParams|CutInParams", re.IGNORECASE)
"""The words that name a built-in scene."""

EXAMPLE = re.compile(r"\be\.g\.|\bfor example\b", re.IGNORECASE)
"""A docstring or comment line that names a scene as an example, which is allowed."""

PENDING: dict[str, int] = {}
"""Scene words in code still there on purpose, by module: how many (none). Each count must be exact, so that an entry
is dropped once its words are gone."""


@dataclass(frozen=True)
class Hit:
    """A scene word found: where, and whether in code or in a docstring / comment."""

    path: str
    line: int
    word: str
    in_code: bool
    text: str

    def __str__(self) -> str:
        return (
            f"{self.path}:{self.line}: {self.word!r} in {'code' if self.in_code else 'a docstring or comment'}: "
            f"{self.text.strip()}"
        )


def docstring_lines(tree: ast.AST) -> set[int]:
    """The line numbers of every docstring-like string statement (a string expression in any body)."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if not isinstance(body, list):
            continue
        for statement in body:
            if (
                isinstance(statement, ast.Expr)
                and isinstance(statement.value, ast.Constant)
                and isinstance(statement.value.value, str)
            ):
                lines.update(range(statement.lineno, statement.end_lineno + 1))
    return lines


def scene_words(source: str, path: str = "<source>") -> list[Hit]:
    """Every scene word of a module's source, each at the line it is on."""
    lines = source.splitlines()
    docs = docstring_lines(ast.parse(source))
    hits = []
    for token in tokenize.generate_tokens(io.StringIO(source).readline):
        for k, part in enumerate(token.string.split("\n")):
            line = token.start[0] + k
            for match in SCENE_WORDS.finditer(part):
                in_code = token.type != tokenize.COMMENT and line not in docs
                hits.append(Hit(path, line, match.group(), in_code, lines[line - 1]))
    return hits


def forbidden(hits: list[Hit]) -> list[Hit]:
    """The hits not allowed: every one in code, and in docstrings / comments those on a line without an example."""
    return [h for h in hits if h.in_code or not EXAMPLE.search(h.text)]


def neutral_modules() -> list[Path]:
    return sorted(p for folder in NEUTRAL_FOLDERS for p in (REPO / folder).rglob("*.py"))


def folder_hits() -> list[Hit]:
    return [h for p in neutral_modules() for h in scene_words(p.read_text(), str(p.relative_to(REPO)))]


def test_the_neutral_folders_exist_and_hold_modules():
    for folder in NEUTRAL_FOLDERS:
        assert any((REPO / folder).rglob("*.py")), f"{folder}: no Python module (moved? update NEUTRAL_FOLDERS)"


def test_the_neutral_folders_name_no_scene_in_code():
    code = [h for h in folder_hits() if h.in_code]
    found = [h for h in code if h.path not in PENDING]
    assert not found, "scene words in the code of the neutral folders:\n" + "\n".join(map(str, found))
    counts = {path: sum(h.path == path for h in code) for path in PENDING}
    assert counts == PENDING, f"the pending scene words changed ({counts}, listed {PENDING}): update PENDING"


def test_the_neutral_folders_name_a_scene_in_docstrings_and_comments_only_as_an_example():
    found = [h for h in forbidden(folder_hits()) if not h.in_code]
    assert not found, (
        "scene words in docstrings / comments (name a scene only as an example, 'e.g.' or 'for "
        "example' on the same line):\n" + "\n".join(map(str, found))
    )


PLANTED = '''"""A module of the braking scene."""

LEAD = "lead_speed_mps"  # the lead car's speed


def f(gap_m):
    """The distance, e.g. the braking scenario's gap."""
    x = "a cut-in"
    # for example the Cut_In scene
    return BrakingParams
'''


@pytest.mark.parametrize(
    "source, expected",
    [
        (
            PLANTED,
            [
                (1, "braking", False),
                (3, "LEAD", True),
                (3, "lead", False),
                (6, "gap_m", True),
                (7, "braking", False),
                (8, "cut-in", True),
                (9, "Cut_In", False),
                (10, "Braking", True),
            ],
        ),
        ('"""Plain words: a gap, a leader, mislead, cutting in."""\nclipped = 1  # braked\n', []),
    ],
    ids=["planted", "clean"],
)
def test_the_counter_finds_planted_scene_words_and_only_them(source, expected):
    hits = scene_words(source)
    assert [(h.line, h.word, h.in_code) for h in hits] == expected
    if hits:
        assert [(h.line, h.word) for h in forbidden(hits)] == [
            (1, "braking"),
            (3, "LEAD"),
            (3, "lead"),
            (6, "gap_m"),
            (8, "cut-in"),
            (10, "Braking"),
        ]
