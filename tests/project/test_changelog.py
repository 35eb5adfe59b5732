"""CHANGELOG.md follows Keep a Changelog (https://keepachangelog.com): under the unreleased version, each change is one
bullet line of at most 200 characters in one of the subsections Added, Changed, Fixed, Removed; the version header is
``pemviz.__version__``. The measurements live in docs/validation.md and the benchmarks' own output."""

from __future__ import annotations

import re

import pemviz

from conftest import REPO

SECTIONS = ("Added", "Changed", "Fixed", "Removed")
MAX_CHARS = 200


def unreleased_problems(text: str, version: str) -> tuple[list[str], dict[str, int]]:
    """What breaks the rules under ``## VERSION (unreleased)`` in a changelog's ``text``: (problems, entries per
    subsection). A problem is a line that is neither a bullet, a subsection header nor blank, a bullet outside a
    subsection or longer than :data:`MAX_CHARS`, an unknown subsection, or a missing version header."""
    lines = text.splitlines()
    header = f"## {version} (unreleased)"
    if header not in lines:
        return [f"no line {header!r}"], {}
    start = lines.index(header) + 1
    end = next((i for i in range(start, len(lines)) if lines[i].startswith("## ")), len(lines))
    problems: list[str] = []
    counts: dict[str, int] = {}
    section = None
    for number, line in enumerate(lines[start:end], start + 1):
        if not line.strip():
            continue
        if line.startswith("### "):
            section = line[4:].strip()
            if section not in SECTIONS or section in counts:
                problems.append(f"line {number}: subsection {section!r} (one each of {', '.join(SECTIONS)})")
            counts.setdefault(section, 0)
        elif re.match(r"- \S", line):
            if section is None:
                problems.append(f"line {number}: an entry outside a subsection")
            else:
                counts[section] += 1
            if len(line) > MAX_CHARS:
                problems.append(f"line {number}: {len(line)} characters (at most {MAX_CHARS})")
        else:
            problems.append(f"line {number}: not a one-line entry: {line[:60]!r}")
    problems += [f"subsection {name!r} is empty" for name, n in counts.items() if n == 0]
    return problems, counts


def test_every_unreleased_change_is_one_line_in_a_keep_a_changelog_subsection() -> None:
    problems, counts = unreleased_problems((REPO / "CHANGELOG.md").read_text(), pemviz.__version__)
    assert problems == []
    assert set(counts) <= set(SECTIONS) and sum(counts.values()) >= 10


def test_the_checker_finds_each_kind_of_fault() -> None:
    good = (
        "# Changelog\n\n## 1.0 (unreleased)\n\n### Added\n\n- One line.\n\n### Fixed\n\n- Another.\n\n## 0.9\n\n- old\n"
    )
    assert unreleased_problems(good, "1.0") == ([], {"Added": 1, "Fixed": 1})
    assert unreleased_problems(good, "1.1")[0] == ["no line '## 1.1 (unreleased)'"]
    continued = good.replace("- One line.\n", "- One line\n  continued.\n")
    assert unreleased_problems(continued, "1.0")[0] == ["line 8: not a one-line entry: '  continued.'"]
    long = good.replace("- One line.", "- " + "x" * MAX_CHARS)
    assert unreleased_problems(long, "1.0")[0] == [f"line 7: {MAX_CHARS + 2} characters (at most {MAX_CHARS})"]
    outside = good.replace("### Added\n\n", "")
    assert unreleased_problems(outside, "1.0")[0] == ["line 5: an entry outside a subsection"]
    unknown = good.replace("### Fixed", "### Measured")
    assert unreleased_problems(unknown, "1.0")[0] == [
        "line 9: subsection 'Measured' (one each of Added, Changed, " "Fixed, Removed)"
    ]
