"""pemviz.sinks.colours is the one palette: its HTML forms, and no colour written out anywhere else in the package."""

from __future__ import annotations

import re

from pemviz.sinks.colours import BLUE, RED, css, hex_colour, rgba, stage_rgb

from conftest import REPO

COLOUR_LITERAL = re.compile(
    r"#[0-9a-fA-F]{6}\b"  # hex
    r"|\(\s*\d{1,3},\s*\d{1,3},\s*\d{1,3}\s*\)"  # RGB
    r"|\(\s*\d{1,3},\s*\d{1,3},\s*\d{1,3},\s*(?:[6-9]\d|1\d\d|2[0-5]\d)\s*\)"  # RGBA, alpha >= 60
    r"|\"(?:black|white)\""
)


def test_html_and_rerun_forms_of_a_colour():
    assert hex_colour(BLUE) == "#1f6fd1" and hex_colour(RED) == "#d6402b" and hex_colour((0, 0, 0)) == "#000000"
    assert css((31, 111, 209)) == "rgb(31, 111, 209)" and css(BLUE, 0.5) == "rgba(31, 111, 209, 0.5)"
    assert rgba(BLUE) == (31, 111, 209, 255)
    assert stage_rgb(0, 5) == (40, 110, 230) and stage_rgb(9, 5) == (255, 150, 30)  # blue early, orange late


def test_no_colour_is_written_out_outside_the_palette():
    found = []
    for path in sorted((REPO / "pemviz").rglob("*.py")):
        if path.name == "colours.py":
            continue
        for k, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            code = line.split("#", 1)[0] if not re.search(r"#[0-9a-fA-F]{6}\b", line) else line
            if (
                COLOUR_LITERAL.search(code)
                and "linspace" not in code
                and "transpose" not in code
                and "range(" not in code
            ):
                found.append(f"{path.relative_to(REPO)}:{k}: {line.strip()}")
    assert not found, "colours outside pemviz/sinks/colours.py:\n" + "\n".join(found)
