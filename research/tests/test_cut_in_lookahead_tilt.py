"""research/cut_in_lookahead_tilt.py, the study of research/cut-in-notes.md's "Approximate zero-variance sampling with a
look-ahead": its beam's events, the options it refuses, its command line, and its cached V. (The committor grid, level
chain and one-car look-ahead it builds on are pemviz's, tested in tests/scenarios/test_cut_in_committor.py.)"""

from __future__ import annotations

import sys

import numpy as np
import pytest
from pemviz.scenarios.cut_in import committor

from conftest import REPO, load_script


@pytest.fixture(scope="module")
def study():
    yield load_script(REPO / "research" / "cut_in_lookahead_tilt.py")
    del sys.modules["cut_in_lookahead_tilt"]


def test_the_beams_events_are_the_grid_branches_they_name(study):
    """A beam representative's children: the central draw, a miss, a range error at the gate (the lean grid's 1e-3
    edge) low and high, and each error at 1.6e-2 low and high; their log probabilities given a detection."""
    self = type("S", (), {"grid": committor.Grid(np.array(committor.GRIDS["lean"])), "dp_mass": 1e-3})()
    ev, log_pe = study.LookAheadTilt.beam_events(self)
    reps = self.grid.reps[ev]
    expected = [
        (0, 0.5, 0.5),
        (1, 0.5, 0.5),
        (0, 1e-3, 0.5),
        (0, 1 - 1e-3, 0.5),
        (0, 1.6e-2, 0.5),
        (0, 1 - 1.6e-2, 0.5),
        (0, 0.5, 1.6e-2),
        (0, 0.5, 1 - 1.6e-2),
    ]
    assert reps == pytest.approx(np.array(expected, dtype=float))
    assert np.exp(log_pe) == pytest.approx([1, 1, 1e-3, 1e-3] + [1.6e-2] * 4)


@pytest.mark.parametrize(
    "options, words",
    [
        (["--window", "10", "5"], "need 0 <= window start < window end <= end <= 100"),
        (["--window", "10", "200"], "need 0 <= window start < window end <= end <= 100"),
        (["--n", "0"], "rollouts >= 1"),
        (["--eps", "0"], "0 < eps <= 1"),
        (["--a", "2"], "0 < a <= 1"),
        (["--beta", "0"], "0 < beta <= 1"),
        (["--chain-effects", "--graded"], "--chain-effects and --beam 0.0 need --dp"),
        (["--beam", "0.25", "--graded"], "--chain-effects and --beam 0.25 need --dp"),
        (["--effect-model", "--dp", "--graded", "--chain-effects"], "--effect-model needs --beam and --chain-effects"),
        (["--beam", "0.25", "--dp", "--graded"], "--beam needs --one-car"),
        (["--dp-mass", "0.7"], "need 0 < dp-mass < 0.5"),
        (["--vy-buckets", "0.3", "-0.3"], "the buckets' bounds ascending"),
        (["--dp"], "--continuous and --dp need --graded"),
        (["--dp", "--graded", "--window", "3", "24"], "--dp needs the window to start at step 5"),
    ],
)
def test_options_the_study_cannot_run_with_stop_it_with_one_line(study, monkeypatch, options, words):
    """Each refusal names the options and what is allowed, before the PEMs are loaded (no traceback)."""
    monkeypatch.setattr(sys, "argv", ["cut_in_lookahead_tilt.py", *options])
    with pytest.raises(SystemExit) as stop:
        study.main()
    message = str(stop.value.code)
    assert words in message and "\n" not in message


def test_the_command_line_takes_every_option_the_docs_commands_use(study, capsys, monkeypatch):
    """--help lists them (the docs' commands run these routes)."""
    monkeypatch.setattr(sys, "argv", ["cut_in_lookahead_tilt.py", "--help"])
    with pytest.raises(SystemExit):
        study.main()
    out = capsys.readouterr().out
    for option in (
        "--n",
        "--graded",
        "--q-model",
        "--grid",
        "--skip-doomed",
        "--mc-failures",
        "--window",
        "--one-car",
        "--check-one-car",
        "--a",
        "--eps",
        "--train-once",
        "--errors",
        "--continuous",
        "--dp",
        "--chain-effects",
        "--beta",
        "--dp-mass",
        "--beam",
        "--effect-model",
    ):
        assert option in out


def test_a_cached_v_gives_the_run_it_was_fitted_for_and_refuses_another_setting(study, capsys, monkeypatch, tmp_path):
    """--v-cache writes the V fitted by --train-once whole; read back, the same seed gives the same estimate; a cache
    fitted with another grid stops the run with one line and leaves the file as it was."""
    cache = tmp_path / "v.pkl"
    base = [
        "cut_in_lookahead_tilt.py",
        "--train-once",
        "5",
        "--v-cache",
        str(cache),
        "--n",
        "40",
        "40",
        "--seeds",
        "1",
        "--one-car",
        "--grid",
        "coarse",
        "--graded",
    ]

    def run(*extra):
        monkeypatch.setattr(sys, "argv", base + list(extra))
        study.main()
        return [line for line in capsys.readouterr().out.splitlines() if line.startswith("  ")]

    fitted = run()
    assert "V trained once" in fitted[0] and cache.exists() and not list(tmp_path.glob("*.part"))
    before = cache.read_bytes()
    again = run()
    assert "V read from" in again[0]
    assert again[1].split("; cost")[0] == fitted[1].split("; cost")[0]  # estimate, interval, ESS and verdict
    with pytest.raises(SystemExit, match="fitted for"):
        run("--grid", "fine")
    assert cache.read_bytes() == before
    cache.write_text("not a pickle")
    with pytest.raises(SystemExit, match="not a V this study wrote"):
        run()
    assert cache.read_text() == "not a pickle"
