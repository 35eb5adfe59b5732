"""scripts/import_cycles.py: no import circle among pemviz's modules, and the script finds the circles it should."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from conftest import REPO, load_script

SCRIPT = REPO / "scripts" / "import_cycles.py"


def package(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = root / "pkg" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root / "pkg"


def test_pemviz_has_no_import_circle_of_any_kind():
    out = subprocess.run([sys.executable, str(SCRIPT), "--strict"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "0 circles among module-level imports" in out.stdout
    assert "0 circles among all imports, TYPE_CHECKING ones included" in out.stdout


def test_a_module_level_circle_is_found_and_fails(tmp_path, capsys):
    ic = load_script(SCRIPT)
    root = package(
        tmp_path,
        {
            "__init__.py": "",
            "a.py": "from pkg import b\n",
            "b.py": "import pkg.sub.c\n",
            "sub/__init__.py": "",
            "sub/c.py": "from ..a import thing\n",  # relative: pkg.a
            "d.py": "import os\nfrom pkg.a import x\n",  # imports into the circle, not part of it
        },
    )
    assert ic.main(["--root", str(root)]) == 1
    out = capsys.readouterr().out
    assert "1 circle among module-level imports (6 modules" in out
    assert "pkg.a -> pkg.b -> pkg.sub.c -> pkg.a" in out
    assert "pkg.d" not in out


def test_function_level_and_type_checking_circles_are_reported_apart(tmp_path, capsys):
    ic = load_script(SCRIPT)
    root = package(
        tmp_path,
        {
            "__init__.py": "",
            "a.py": "import pkg.b\n",
            "b.py": "def f():\n    from pkg import a\n",
            "c.py": "from typing import TYPE_CHECKING\nimport pkg.d\nif TYPE_CHECKING:\n    from pkg.d import D\n",
            "d.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg.c import C"
            "\nelse:\n    C = None\n",
        },
    )
    graph = ic.build_graph(root)
    assert graph.module_level["pkg.a"] == {"pkg.b"} and graph.function_level["pkg.b"] == {"pkg.a"}
    assert graph.type_checking["pkg.d"] == {"pkg.c"} and not graph.type_checking.get("pkg.c")  # also module-level
    assert ic.main(["--root", str(root)]) == 0  # no circle among module-level imports
    out = capsys.readouterr().out
    assert "0 circles among module-level imports" in out
    assert "1 circle among module- and function-level imports" in out and "pkg.a -> pkg.b -> pkg.a" in out
    assert "2 circles among all imports" in out and "pkg.c -> pkg.d -> pkg.c" in out
    assert ic.main(["--root", str(root), "--strict"]) == 1


def test_a_folder_that_is_no_package_or_does_not_parse_is_refused(tmp_path, capsys):
    ic = load_script(SCRIPT)
    assert ic.main(["--root", str(tmp_path)]) == 2
    assert "is not a package folder" in capsys.readouterr().err
    root = package(tmp_path, {"__init__.py": "", "bad.py": "def (:\n"})
    assert ic.main(["--root", str(root)]) == 2
    assert "bad.py:1" in capsys.readouterr().err


LOWER = ("core", "engine", "estimators", "stl", "pem", "stack")
"""The folders that know no scenario, file, sink, panel or command."""
UPPER = ("scenarios", "io", "sinks", "app", "commands")


def folder_imports(root: Path) -> dict[tuple[str, str], list[str]]:
    """(folder, folder it imports) -> the ``file:line`` of each import statement (lazy, TYPE_CHECKING and indented
    ones included), read from the source of the package at ``root``; a module at the top of the package (the
    config, the settings) counts as a folder of its own."""
    import ast

    found: dict[tuple[str, str], list[str]] = {}
    for f in sorted(root.rglob("*.py")):
        parts = f.relative_to(root).parts
        here = parts[0] if len(parts) > 1 else parts[0].removesuffix(".py")
        if here == "__init__":
            continue
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            for name in names:
                p = name.split(".")
                known = (root / p[1]).is_dir() or (root / f"{p[1]}.py").is_file() if len(p) > 1 else False
                if p[0] == root.name and known and p[1] not in (here, "__init__"):
                    found.setdefault((here, p[1]), []).append(f"{f.relative_to(root)}:{node.lineno}")
    return found


def folder_circles(edges) -> list[set[str]]:
    """The sets of folders that import one another in a circle (strongly connected, more than one)."""
    graph: dict[str, set[str]] = {}
    for a, b in edges:
        graph.setdefault(a, set()).add(b)
    reach = {a: set() for a in graph}
    for a in graph:
        todo = list(graph[a])
        while todo:
            b = todo.pop()
            if b not in reach[a]:
                reach[a].add(b)
                todo.extend(graph.get(b, ()))
    circles = {frozenset({a} | {b for b in reach[a] if a in reach.get(b, ())}) for a in graph if a in reach[a]}
    return [set(c) for c in circles]


def test_the_lower_layers_import_no_scenario_file_sink_panel_or_command():
    found = folder_imports(REPO / "pemviz")
    upward = {k: v for k, v in found.items() if k[0] in LOWER and k[1] in UPPER}
    assert upward == {}, upward


def test_the_folders_import_one_another_in_no_circle():
    assert folder_circles(folder_imports(REPO / "pemviz")) == []


def test_an_upward_import_and_a_folder_circle_are_found(tmp_path):
    root = tmp_path / "pemviz"
    planted = {
        "core/a.py": "def f():\n    from pemviz.sinks import b\n",
        "sinks/b.py": "import pemviz.core.a\n",
        "stl/c.py": "from pemviz.config import X\n",
        "config.py": "from pemviz.stl.c import y\n",
    }
    for name, text in planted.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    found = folder_imports(root)
    assert found == {
        ("core", "sinks"): ["core/a.py:2"],
        ("sinks", "core"): ["sinks/b.py:1"],
        ("stl", "config"): ["stl/c.py:1"],
        ("config", "stl"): ["config.py:1"],
    }
    assert sorted(folder_circles(found), key=sorted) == [{"config", "stl"}, {"core", "sinks"}]
