"""Static checks in the test command: ruff's lint (pycodestyle, pyflakes, bugbear, import sorting, pyupgrade; lines
<= 120) over every Python folder and its docstring rules over the package, mypy over the whole package (``pemviz``:
the settings in ``pyproject.toml``). Each check is first shown to fail on a file with a planted fault, so a check that
cannot fail (a missing tool, a configuration that selects nothing) fails here."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
FOLDERS = ("pemviz", "tests", "benchmarks", "scripts", "research")


def _tool(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, capture_output=True, text=True, timeout=600)


def test_ruff_flags_a_planted_fault_and_passes_the_tree(tmp_path):
    bad = tmp_path / "bad.py"
    # an unused import, a mutable default, an undocumented public function, an Args: section that misses ``b``
    bad.write_text(
        "import os\n\n\ndef f(xs=[]):\n    return xs\n\n\n"
        'def g(a, b):\n    """Sum.\n\n    Args:\n        a: one.\n    """\n    return a + b\n'
    )
    planted = _tool("ruff", "check", "--config", str(REPO / "pyproject.toml"), str(bad))
    assert planted.returncode == 1, planted.stdout
    assert all(code in planted.stdout for code in ("F401", "B006", "D103", "D417")), planted.stdout
    tree = _tool("ruff", "check", *FOLDERS)
    assert tree.returncode == 0, tree.stdout[-4000:]


@pytest.mark.slow
def test_mypy_flags_a_planted_fault_and_passes_the_package(tmp_path):
    """One mypy run (its start-up and the stubs it reads are most of its time) over the package and a file with a
    planted fault: the fault is the one error found, in the planted file, and every module of the package is checked."""
    bad = tmp_path / "bad.py"
    bad.write_text("def f(x: int) -> str:\n    return x\n")
    cache = str(tmp_path / "mypy-cache")  # cold, as CI's clean clone: a cache of an earlier run names its own bad.py
    run = _tool("mypy", "--config-file", str(REPO / "pyproject.toml"), "--cache-dir", cache, "pemviz", str(bad))
    assert run.returncode == 1 and "Found 1 error in 1 file" in run.stdout, run.stdout[-4000:]
    errors = [line for line in run.stdout.splitlines() if ": error:" in line]
    assert len(errors) == 1 and errors[0].startswith(str(bad)), run.stdout[-4000:]
    assert "Incompatible return value type" in errors[0], errors
    checked = int(run.stdout.split("(checked ")[1].split()[0])
    assert checked == len(list((REPO / "pemviz").rglob("*.py"))) + 1, run.stdout  # every module and the planted file


STRICT = ("pemviz.config", "pemviz.methods.*", "pemviz.engine.*", "pemviz.sinks.*")
"""The packages mypy checks strictly: every function annotated (``disallow_untyped_defs``), its body checked."""


def test_the_config_methods_engine_and_sinks_are_checked_strictly():
    """pyproject.toml keeps the strict override over :data:`STRICT` that the mypy test above runs under."""
    import tomllib

    overrides = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["mypy"]["overrides"]
    strict = [o for o in overrides if o.get("disallow_untyped_defs") and o.get("check_untyped_defs")]
    assert strict and set(STRICT) <= set(strict[0]["module"]), overrides


MAX_FMT_SKIPS = 20
"""The most ``# fmt: skip`` markers the tree may keep, each with its reason on the line before."""


def test_ruff_format_flags_an_unformatted_file_and_passes_the_tree(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("x = {  'a':1 }\n")
    planted = _tool("ruff", "format", "--check", "--config", str(REPO / "pyproject.toml"), str(bad))
    assert planted.returncode == 1 and "Would reformat" in planted.stdout, planted.stdout
    tree = _tool("ruff", "format", "--check", *FOLDERS)
    assert tree.returncode == 0, tree.stdout[-4000:]


def test_few_formatter_escapes_remain_each_with_its_reason():
    """The formatter is run, not dodged: at most :data:`MAX_FMT_SKIPS` ``# fmt: skip`` markers (and no ``# fmt: off``),
    each followed on its line by a comment that says why (``# fmt: skip  # a table, one row a line``)."""
    import re

    marker = re.compile(r"#\s*fmt:\s*(skip|off)")
    found, bare = 0, []
    for folder in FOLDERS:
        for path in sorted((REPO / folder).rglob("*.py")):
            if path.name == "test_static_checks.py":
                continue
            for i, line in enumerate(path.read_text().splitlines(), 1):
                m = marker.search(line)
                if m:
                    found += 1
                    if m.group(1) == "off" or not re.match(r"\s*#\s*\w", line[m.end() :]):
                        bare.append(f"{path.relative_to(REPO)}:{i}")
    assert found <= MAX_FMT_SKIPS and bare == [], (found, bare)
