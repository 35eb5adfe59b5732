"""A method is a record, not a name: outside ``pemviz/methods/`` no module spells a built-in method's name as a string
literal (what a method does is its record's: :class:`pemviz.methods.Method`), and only the command line, the panel,
the file readers, the config (which resolves its name once: :attr:`pemviz.config.ExperimentConfig.method_record`) and
the conformance kit (which takes a name from its caller) look a method up by name."""

from __future__ import annotations

import ast
from pathlib import Path

from pemviz.methods import BUILTIN_METHODS

PACKAGE = Path(__file__).resolve().parents[2] / "pemviz"

LOOKUPS = ("get_method", "method_or_none", "registered_name")
"""The registry's functions that take a method's name and return its record."""

MAY_LOOK_UP = ("commands/", "app/", "io/", "config.py", "testing.py", "methods/")
"""Where a name may be looked up (paths under ``pemviz/``): the command line, the panel, the file readers, the config
and the conformance kit, besides the registry itself."""


def _docstrings(tree: ast.AST) -> set[int]:
    kinds = (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)
    return {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, kinds)
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
    }


def scan(package: Path = PACKAGE) -> tuple[list[str], list[str]]:
    """(``path:line name`` of each built-in method's name as a string literal outside ``methods/``, ``path:line
    function`` of each lookup by name where :data:`MAY_LOOK_UP` does not allow it); docstrings are prose."""
    names, literals, lookups = set(BUILTIN_METHODS), [], []
    for path in sorted(package.rglob("*.py")):
        where = path.relative_to(package).as_posix()
        tree = ast.parse(path.read_text(encoding="utf-8"))
        prose = _docstrings(tree)
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Constant)
                and isinstance(node.value, str)
                and node.value in names
                and id(node) not in prose
                and not where.startswith("methods/")
            ):
                literals.append(f"{where}:{node.lineno} {node.value}")
            if isinstance(node, ast.Call) and not where.startswith(MAY_LOOK_UP):
                func = node.func
                name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)
                if name in LOOKUPS:
                    lookups.append(f"{where}:{node.lineno} {name}")
    return literals, lookups


def test_the_builtin_names_are_the_seven_methods():
    assert set(BUILTIN_METHODS) == {"adaptive", "mc", "naive50", "mixed50", "ams", "tilt", "state"}


def test_no_method_name_as_a_literal_and_no_lookup_by_name_outside_their_places():
    literals, lookups = scan()
    assert literals == [], f"built-in method names as string literals outside pemviz/methods/: {literals}"
    assert lookups == [], f"the method registry looked up by name outside {MAY_LOOK_UP}: {lookups}"


def test_the_scan_finds_a_name_and_a_lookup(tmp_path):
    """The scan is not blind: a module that compares a config's method with ``"mc"`` and one that asks the registry by
    name are both found (a docstring naming a method is not)."""
    (tmp_path / "engine").mkdir()
    (tmp_path / "engine" / "bad.py").write_text(
        '"""Runs mc."""\nfrom pemviz.methods import get_method\n\n\ndef plain(config):\n'
        '    return config.method == "mc" or get_method(config.method).plain\n'
    )
    (tmp_path / "commands").mkdir()
    (tmp_path / "commands" / "ok.py").write_text("from pemviz.methods import get_method\n\nget_method(NAME)\n")
    literals, lookups = scan(tmp_path)
    assert literals == ["engine/bad.py:6 mc"]
    assert lookups == ["engine/bad.py:6 get_method"]
