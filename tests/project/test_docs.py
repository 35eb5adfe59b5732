"""The user guide builds with ``mkdocs build --strict`` and its command-line reference covers every command."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys

import pytest

from conftest import REPO

needs_mkdocs = pytest.mark.skipif(
    importlib.util.find_spec("mkdocs") is None or importlib.util.find_spec("mkdocstrings") is None,
    reason='mkdocs is not installed (pip install -e ".[test]" or ".[docs]")',
)


@needs_mkdocs
def test_user_guide_builds_strict_with_every_command_in_the_cli_reference(tmp_path) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO), "NO_MKDOCS_2_WARNING": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    cli = (tmp_path / "site" / "cli" / "index.html").read_text()
    for command in ("run", "data fetch", "pem train", "pem eval", "serve", "estimate", "validate", "tables"):
        assert f"pemviz {command}" in cli, command
    assert "--grpc-port" in cli and "&lt;!-- pemviz-cli --&gt;" not in cli and "<!-- pemviz-cli -->" not in cli
    assert (
        "Any Python simulator plugs into the sampler"
        in (tmp_path / "site" / "own-simulator" / "index.html").read_text()
    )


NUMBER_WORDS = {
    w: i for i, w in enumerate("zero one two three four five six seven eight nine ten eleven twelve".split())
}
COUNTED = r"(presets?|methods?|scenarios?|scenes?|metrics?|commands?|tests?|skips?|skipped)"


def counts_in_docs() -> list[tuple[str, int, str]]:
    """Every "<number> <noun>" of :data:`COUNTED` in the README and the user guide (the changelog aside): (file, n,
    noun). "one method" in a sentence such as "one method per file" is a count too, and must be true."""
    import re

    pattern = re.compile(rf"\b({'|'.join(NUMBER_WORDS)}|\d+)\s+(?:\w+\s+)?{COUNTED}\b", re.I)
    found = []
    for path in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        if path.name == "changelog.md":
            continue
        for m in pattern.finditer(path.read_text()):
            word = m.group(1).lower()
            found.append((path.name, NUMBER_WORDS.get(word, int(word) if word.isdigit() else -1), m.group(0)))
    return found


def test_every_count_in_the_docs_is_the_code_s_or_absent() -> None:
    """Counts of presets, methods, scenarios (the scenario registry's), metrics and commands agree with the
    registries; counts of tests or skips, which change with every test added, are not written in the docs at all
    (``pytest -rs`` lists skips)."""
    from pemviz.commands import COMMANDS
    from pemviz.presets import PRESETS
    from pemviz.scenarios.registry import registered
    from pemviz.settings import SETTINGS

    truth = {
        "preset": len(PRESETS),
        "method": len(SETTINGS["method"].choices),
        "scenario": len(registered()),
        "scene": len(registered()),
        "metric": len(SETTINGS["metric"].choices),
        "command": len(COMMANDS),
    }
    wrong = []
    for name, n, text in counts_in_docs():
        noun = text.split()[-1].lower().rstrip("s").replace("skipped", "skip")
        if n == 1:  # "one test case", "one method per file": a phrase, not a total
            continue
        if noun in ("test", "skip"):
            wrong.append(f"{name}: {text!r}: a test count goes stale; say how to list them instead")
        elif n != truth[noun]:
            wrong.append(f"{name}: {text!r}, but the code has {truth[noun]}")
    assert not wrong, wrong


def test_the_count_check_finds_a_wrong_count(tmp_path, monkeypatch) -> None:
    """The check above fails on a stale count: a copy of the docs with "16 tests skip" and "4 presets" in it."""
    import shutil

    test_docs = sys.modules[__name__]

    (tmp_path / "docs").mkdir()
    shutil.copy(REPO / "README.md", tmp_path / "README.md")
    (tmp_path / "docs" / "x.md").write_text("Without the files 16 tests skip. There are 4 presets and 7 methods.\n")
    monkeypatch.setattr(test_docs, "REPO", tmp_path)
    with pytest.raises(AssertionError) as err:
        test_docs.test_every_count_in_the_docs_is_the_code_s_or_absent()
    assert "'16 tests skip'" in str(err.value) and "'4 presets', but the code has 5" in str(err.value)
    assert "7 methods" not in str(err.value)


CPU_TORCH = "pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu"
"""The line that installs the CPU build of torch (pip's default on Linux brings CUDA's, several GB)."""


def test_the_install_steps_users_copy_install_the_cpu_torch_and_the_ci_test_command_does_not() -> None:
    """The README's quick start, the guide's Quickstart page and the CI page's job install the CPU build of torch
    before pemviz, on a line of its own, as their first install step; the README's test command (this project's CI
    runs it on machines that reach only the package registry) is left as it is, without the PyTorch index."""
    readme = (REPO / "README.md").read_text()
    quick = re.search(r"## Quick start\n(.*?)\n## ", readme, re.S).group(1)
    steps = re.findall(r"```bash\n(.*?)```", quick, re.S)
    assert steps[0].splitlines() == [CPU_TORCH, "pip install -e . && pemviz run"]
    page = re.search(r"## Install\n(.*?)\n## ", (REPO / "docs" / "quickstart.md").read_text(), re.S).group(1)
    assert re.findall(r"```bash\n(.*?)```", page, re.S)[0].splitlines() == [CPU_TORCH, "pip install -e ."]
    assert "torch==2.13.0 -e" not in page  # no step that pulls CUDA's torch before the CPU one
    test_command = readme.split("<!-- ci: test command -->\n```bash\n", 1)[1].splitlines()[0]
    assert test_command == 'pip install torch==2.13.0 -e ".[test]" && python -m pytest -q -n 2 --dist loadfile'
    job = re.search(r"<!-- ci job -->\n```yaml\n(.*?)```", (REPO / "docs" / "ci.md").read_text(), re.S).group(1)
    install = job.split("- name: Install pemviz", 1)[1].split("- name:", 1)[0]
    assert [line.strip() for line in install.splitlines()[2:4]] == [CPU_TORCH, "pip install -e ."]
    assert "torch==2.13.0 -e" not in job


def test_the_readme_claims_for_the_cut_in_s_default_what_it_prints() -> None:
    """The cut-in's default (its tilt) prints a lower bound, never an interval (no run `reliable`): the README gives its
    figures against the reference it names (7.95e-5) as the Validation page measured them against it (the default
    gap's 20 seeds; the 21 m setting's against its engine-drawn 3.18e-5), counts the lower bounds that held (20 of 20
    at each gap), and claims no interval holding the reference."""
    readme = " ".join((REPO / "README.md").read_text().split())
    cut_in = readme.split("On the cut-in scenario", 1)[1].split("Braking has a tilted proposal", 1)[0]
    assert "intervals that hold" not in cut_in and "of 40 runs" not in cut_in
    assert "a plain Monte Carlo reference of 7.95e-5" in readme
    assert "a run prints no interval: it prints a 95 % lower bound, which held the reference in all 40 runs" in cut_in
    page = " ".join((REPO / "docs" / "validation.md").read_text().split())
    default = page.split("Against the reference 7.95e-5 [7.50e-5, 8.41e-5]", 1)[1].split(" verdicts ", 1)[0]
    said = r"median relative error (0\.\d+),.* (\d+) of 20 within x2, the printed 95 % lower bound holding in (\d+) "
    found = re.search(said, default)
    assert found is not None, default
    error, within, held = float(found[1]), int(found[2]), int(found[3])
    assert f"({error:.2f} over 20 seeds, {'all 20' if within == 20 else f'{within} of them'} within x2;" in cut_in
    rows = (REPO / "docs" / "validation.md").read_text().splitlines()
    head = "| cut-in at 21 m (3.18e-5, the engine's)"
    (at_21,) = [r for r in rows if r.startswith(head) and "| default: its tilt |" in r]
    assert held == 20 and "| 20 |" in at_21 and "none printed (lower bounds 20/20)" in at_21
