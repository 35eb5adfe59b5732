"""docs/layout.md names every module of the package, and the rule that reads it finds a module it does not name."""

from __future__ import annotations

import re
from pathlib import PurePosixPath

from conftest import REPO


def unnamed(text: str, modules: list[PurePosixPath]) -> list[str]:
    """The modules (``pemviz/a/b.py``) that ``text`` does not name. A module is named by its path from the package
    or from one of its folders with at least one folder in it (``pemviz/a/b.py``, ``a/b.py``), or, in a table row
    whose first cell names one of its folders (`` `pemviz/a/` ``), by its file name (``b.py``); a package's
    ``__init__.py`` by its folder (`` `pemviz/a/` ``)."""
    rows = [line for line in text.splitlines() if line.startswith("|")]
    missing = []
    for module in modules:
        parts = module.parts
        if module.name == "__init__.py":
            folder = "/".join(parts[:-1])
            if f"`{folder}/`" not in text and f"{folder}/__init__.py" not in text:
                missing.append(str(module))
            continue
        tails = ["/".join(parts[k:]) for k in range(len(parts) - 1)]
        if any(re.search(r"(?<![\w/])" + re.escape(tail) + r"\b", text) for tail in tails):
            continue
        folders = ["/".join(parts[:k]) + "/" for k in range(2, len(parts))]
        file_named = re.compile(r"[ `(]" + re.escape(module.name) + r"\b")
        if not any(
            any(f"`{folder}`" in row.split("|")[1] for folder in folders) and file_named.search(row) for row in rows
        ):
            missing.append(str(module))
    return missing


def test_docs_layout_names_every_module():
    modules = sorted(PurePosixPath(p.relative_to(REPO).as_posix()) for p in (REPO / "pemviz").rglob("*.py"))
    assert len(modules) > 100
    missing = unnamed((REPO / "docs" / "layout.md").read_text(encoding="utf-8"), modules)
    assert missing == [], f"docs/layout.md does not name {', '.join(missing)}"


def test_the_rule_finds_a_module_the_page_does_not_name():
    page = (
        "| module | what |\n|---|---|\n"
        "| `pemviz/io/files.py` | output paths |\n"
        "| `pemviz/pem/` | PEMs; `training.py` trains them |\n"
        "Prose names `scenarios/toy/odd.py` too.\n"
    )
    modules = [
        PurePosixPath(p)
        for p in (
            "pemviz/io/files.py",  # by its path
            "pemviz/pem/training.py",  # by its file name in its folder's row
            "pemviz/pem/__init__.py",  # by its folder
            "pemviz/scenarios/toy/odd.py",  # by its path from the package's folder
            "pemviz/io/result.py",  # not named: its folder's row is not there
            "pemviz/pem/trees.py",  # not named in its folder's row
            "pemviz/stl/files.py",  # another folder's file of a named name
            "pemviz/io/__init__.py",  # its folder is not named as a folder
        )
    ]
    assert unnamed(page, modules) == [
        "pemviz/io/result.py",
        "pemviz/pem/trees.py",
        "pemviz/stl/files.py",
        "pemviz/io/__init__.py",
    ]
