"""One meaning per word in a run's console output (docs/concepts.md#words): contact is one distance, the one the
impact-speed line states, and no severity row repeats the word with another; ``not reached`` only where no rollout
reached the level; the ``why:`` line's log p says the steps it sums, apart from the NLL column's."""

from __future__ import annotations

import re

import pytest
from pemviz.cli import main

LEVEL = re.compile(r"^  (gap|clearance) < (-?[\d.]+) m(.*?)\s{2,}(.*)$")
CONTACT = re.compile(r"contact: (gap|clearance) <= (-?[\d.]+) m")


def _console(capsys, *args: str) -> str:
    assert main(["run", "--no-record", "--seed", "0", *args]) == 0
    return capsys.readouterr().out


def _check(text: str, signal: str, contact_m: float) -> None:
    """The phrases that contradicted each other before are gone from ``text``."""
    found = CONTACT.search(text)
    assert found is not None and found.group(1) == signal and float(found.group(2)) == contact_m, text
    levels = [m for m in map(LEVEL.match, text.splitlines()) if m]
    assert len(levels) >= 3, text
    # contact: one distance, the impact line's; every other mention of the word states no other distance
    assert all(float(m.group(2)) == contact_m for m in CONTACT.finditer(text)), text
    assert not re.search(r"\(contact\)|contact \((gap|clearance) <", text), text
    for m in levels:
        tail, rest = m.group(3), m.group(4)
        assert tail in ("", ", the spec's margin") and "contact" not in tail, m.group(0)
        if "not reached" in rest:
            assert "(0 of " in rest, m.group(0)  # not reached: no rollout reached it
        if "reached by" in rest and not rest.startswith("not"):
            assert "not estimated" in rest and "lower bound" in rest, m.group(0)
    for why in (line for line in text.splitlines() if line.startswith("why: ")):
        assert re.match(
            r"why: the most likely failure \(stage \d+; over all \d+ steps: log-probability of its "
            r"detections -?[\d.]+ nats",
            why,
        ), why


def test_braking_console_uses_one_meaning_per_word(capsys):
    text = _console(capsys)
    _check(text, "gap", 0.7)
    assert "\n  gap < 0.5 m                   reached by " in text
    assert "\n  gap < 0 m                     not reached by this run (0 of 1,800" in text
    assert "contact: gap <= 0.7 m" in text and text.count("contact: gap <=") == 1


@pytest.mark.slow
def test_cut_in_console_uses_one_meaning_per_word(capsys):
    text = _console(capsys, "--scenario", "cut-in", "--n", "600")  # the default tilt, a twelfth of its rollouts
    _check(text, "clearance", 0.0)
    assert "why: the most likely failure (stage " in text
    assert "\n  clearance < 0 m  " in text and "(contact)" not in text
