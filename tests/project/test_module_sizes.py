"""Small homes: no module of pemviz over :data:`MAX_LINES` lines, and no class of the panel over
:data:`MAX_METHODS` methods (the panel's session is composed of parts that each own their state)."""

from __future__ import annotations

import ast

from conftest import REPO

MAX_LINES = 600
"""The most lines a module of ``pemviz/`` may have."""

MAX_METHODS = 20
"""The most methods (functions defined in its body) a class of ``pemviz/app`` may have."""


def module_lines() -> dict[str, int]:
    """Lines of every module of ``pemviz/``, by path relative to the repository."""
    return {str(p.relative_to(REPO)): len(p.read_text().splitlines()) for p in sorted((REPO / "pemviz").rglob("*.py"))}


def class_methods(path) -> dict[str, int]:
    """Methods (functions in the class body, properties included) of every class of the module ``path``."""
    tree = ast.parse(path.read_text())
    return {
        node.name: sum(isinstance(b, (ast.FunctionDef, ast.AsyncFunctionDef)) for b in node.body)
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef)
    }


def test_no_module_is_over_600_lines():
    sizes = module_lines()
    assert len(sizes) > 100 and "pemviz/cli.py" in sizes  # the walk finds the package
    assert {path: n for path, n in sizes.items() if n > MAX_LINES} == {}


def test_no_class_of_the_panel_has_over_20_methods():
    counts = {
        f"{p.name}:{name}": n
        for p in sorted((REPO / "pemviz" / "app").glob("*.py"))
        for name, n in class_methods(p).items()
    }
    assert "session.py:Session" in counts
    assert {key: n for key, n in counts.items() if n > MAX_METHODS} == {}


def test_the_counters_count(tmp_path):
    planted = tmp_path / "planted.py"
    planted.write_text("class Big:\n" + "".join(f"    def m{i}(self):\n        return {i}\n" for i in range(21)))
    assert class_methods(planted) == {"Big": 21}
