"""The OpenTURNS benchmark's limit state g(u) (benchmarks/openturns_braking.py) is pemviz's braking job.

Rollouts drawn by pemviz itself from the PEM, and the wrapper given the same uniforms, must agree bit for bit:
detections, observations, log-probabilities and classic robustness. Needs no openturns.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from pemviz.scenarios.braking.batched import simulate_batched
from pemviz.scenarios.problems import build_problem

from conftest import load_script

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "openturns_braking.py"


bench = load_script(_PATH)


def test_module_imports_without_openturns():
    source = _PATH.read_text()
    assert "\nimport openturns" not in source and "\nfrom openturns" not in source


@pytest.mark.parametrize("seed", [0, 1])
def test_wrapper_matches_pemviz_rollouts_bit_for_bit(seed):
    pb = build_problem("main")
    n = 4000
    # simulate_batched with the PEM as sampler: rollout i at step t uses the (t * n + i)-th uniform of the stream,
    # i.e. rng.random((T, n))[t, i] (pemviz/scenarios/braking/batched.py, module docstring; one chunk since n <= 8192).
    batch = simulate_batched(None, n, pb.target, pb.target, np.random.default_rng(seed))
    u = np.random.default_rng(seed).random((bench.T, n)).T
    mine = bench.rollouts(u, pb)
    assert np.array_equal(mine.detected, batch.detected)
    assert np.array_equal(mine.observations, batch.observations)
    assert np.array_equal(mine.log_p, batch.log_p)
    g = bench.limit_state(u, pb)
    r = pb.robustness(batch, "classic")
    assert g.shape == (n,) and g.dtype == np.float64
    assert np.array_equal(g, r)
    # the sample is not trivial: most rollouts brake in time (g ~ 4.09 m), some missed at least once
    assert 3.0 < np.median(g) < 4.2 and (~batch.detected[:, :40]).any()


def test_forced_misses_crash_and_forced_detections_do_not():
    pb = build_problem("main")
    g = bench.limit_state(np.vstack([np.ones(bench.T), np.zeros(bench.T)]), pb)
    assert g[0] < 0.0  # u = 1: never detected, the ego drives into the stopped lead (gap < 2 m)
    assert g[1] > 2.0  # u = 0: always detected, the ego stops more than 4 m behind the lead
    assert not bench.rollouts(np.ones((1, bench.T)), pb).detected.any()
    assert bench.rollouts(np.zeros((1, bench.T)), pb).detected.all()


def test_inputs_outside_the_cube_are_defined():
    pb = build_problem("main")
    below, above = np.full((1, bench.T), -0.5), np.full((1, bench.T), 1.5)
    assert np.array_equal(bench.limit_state(below, pb), bench.limit_state(np.zeros((1, bench.T)), pb))
    assert np.array_equal(bench.limit_state(above, pb), bench.limit_state(np.ones((1, bench.T)), pb))


def test_summary_counts_failed_runs_as_zero():
    p = 2e-15
    runs = [bench.Run("x", 10, s, "ok", mu, 100, 1.0) for s, mu in enumerate([p, 1.5 * p, 4 * p])]
    runs.append(bench.Run("x", 10, 3, "stalled", float("nan"), 500, 300.0, error="stalled"))
    runs[2].last_threshold_m = 0.86  # returned P(g < 0.86 m): stopped short of the failure level
    s = bench.summarise(runs, p)
    assert s["runs"] == "3/0/0/1"
    assert s["short"] == 1
    assert s["within_x2"] == 2
    assert s["median_rel_error"] == pytest.approx(0.75)  # errors 0, 0.5, 3, 1
    assert s["mean_evaluations"] == 200
    assert s["relvar_x_evals"] == pytest.approx(np.var([1.0, 1.5, 4.0], ddof=1) * 200)


def test_missing_openturns_gives_one_line(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "openturns", None)  # import openturns -> ImportError
    assert bench.main(["--methods", "subset", "--seeds", "1", "--budgets", "2100"]) == 1
    err = capsys.readouterr().err
    assert err.strip() == bench.OT_MISSING
