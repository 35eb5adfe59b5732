"""scripts/import_cycles.py: no import circle among pemviz's modules or folders, the top-level folders in the layer
order (``methods`` one node, its sub-folders included), and the script finds the circles and the imports against the
order it should."""

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


def planted(root: Path, files: dict[str, str]) -> Path:
    """A package ``pemviz`` of ``files`` under ``root`` (its folder returned)."""
    for name, text in files.items():
        (root / "pemviz" / name).parent.mkdir(parents=True, exist_ok=True)
        (root / "pemviz" / name).write_text(text)
    return root / "pemviz"


def test_the_folders_keep_the_layer_order_and_import_one_another_in_no_circle():
    ic = load_script(SCRIPT)
    graph = ic.build_graph(REPO / "pemviz")
    found = ic.folder_imports(graph)
    assert ("estimators", "core") in found and ("commands", "config") in found  # the rule reads the package
    assert ic.folder_rules(graph) == ([], {})


def test_an_upward_import_and_a_folder_circle_are_found(tmp_path):
    ic = load_script(SCRIPT)
    root = planted(
        tmp_path,
        {
            "core/a.py": "def f():\n    from pemviz.sinks import b\n",
            "sinks/b.py": "import pemviz.core.a\n",
            "stl/c.py": "from pemviz.config import X\n",
            "config.py": "from pemviz.stl.c import y\n",
        },
    )
    graph = ic.build_graph(root)
    assert ic.folder_imports(graph) == {
        ("config", "stl"): ["config.py:1"],
        ("core", "sinks"): ["core/a.py:2"],
        ("sinks", "core"): ["sinks/b.py:1"],
        ("stl", "config"): ["stl/c.py:1"],
    }
    circles, against = ic.folder_rules(graph)
    assert circles == [["config", "stl"], ["core", "sinks"]]
    assert against == {("core", "sinks"): ["core/a.py:2"]}  # the core knows no sink, lazily neither


def test_the_methods_folder_is_one_node_so_a_circle_through_a_methods_sub_folder_is_found(tmp_path, capsys):
    ic = load_script(SCRIPT)
    root = planted(
        tmp_path,
        {
            "__init__.py": "",
            # the registry names a method's code by text (a Ref): no edge
            "methods/__init__.py": 'BUILD = "pemviz.estimators.coin:Coin"\n',
            "methods/rows.py": "",
            # a method's sub-folder importing the estimators: an edge of the methods folder itself
            "methods/coin/__init__.py": "from pemviz.methods.rows import setting\n",
            "methods/coin/estimator.py": "from pemviz.estimators.base import Check\n",
            "estimators/base.py": "from pemviz.methods import rows\n",
            "sinks/words.py": "from pemviz.methods.coin.estimator import Coin\n",
        },
    )
    graph = ic.build_graph(root)
    found = ic.folder_imports(graph)
    assert found[("methods", "estimators")] == ["methods/coin/estimator.py:1"]  # the methods folder's, one node
    assert found[("sinks", "methods")] == ["sinks/words.py:1"] and not any("methods/" in a for a, _ in found)
    circles, against = ic.folder_rules(graph)
    assert circles == [["estimators", "methods"]]
    assert against == {("methods", "estimators"): ["methods/coin/estimator.py:1"]}
    assert ic.main(["--root", str(root)]) == 0  # no circle among module-level imports
    assert ic.main(["--root", str(root), "--strict"]) == 1
    out = capsys.readouterr().out
    assert "1 folder circle" in out and "1 folder import against the layer order" in out
    assert "  methods -> estimators (the registry imports nothing of the package above it" in out
    # the registry's text reference alone, with the sub-folder importing nothing above the registry: no rule broken
    (root / "methods" / "coin" / "estimator.py").write_text("")
    assert ic.folder_rules(ic.build_graph(root)) == ([], {})
    assert ic.main(["--root", str(root), "--strict"]) == 0
