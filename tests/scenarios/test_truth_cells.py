"""The cell miss bound (pemviz.scenarios.braking.truth_cells) against independent truth: the true one-step map of the
scenario at random states and integrals, the integral of random rollouts, the least number of misses over every
detection sequence of the last steps, and the latched scenario's closed form."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from pemviz.scenarios.braking import truth
from pemviz.scenarios.braking.simulator import BrakingParams, braking_step, lead_speeds
from pemviz.scenarios.braking.truth import BrakingStart, MissBound, braking_exact
from pemviz.scenarios.braking.truth_cells import (
    CellMissBound,
    cell_miss_bound,
    integral_range,
    speed_lipschitz,
    speed_ranges,
)
from pemviz.scenarios.braking.truth_latched import latched_log_failure_probability


def test_speed_ranges_hold_every_next_speed_of_the_cell():
    p = BrakingParams(crash_gap_m=0.5)
    edges = np.linspace(0.0, 9.0, 121)
    i_lo, i_hi = integral_range(p, 0.0, 9.0)
    rng = np.random.default_rng(0)
    n = 200_000
    cell = rng.integers(0, edges.size - 1, n)
    v = edges[cell] + rng.random(n) * (edges[cell + 1] - edges[cell])
    cell[:120], v[:120] = np.arange(120), edges[:120]  # the cells' lower edges themselves
    cell[120:240], v[120:240] = np.arange(120), edges[1:121]  # and their upper edges
    integral = rng.uniform(i_lo, i_hi, n)
    gap = rng.uniform(p.contact_gap_m + 1e-6, p.braking_distance_m - 1e-6, n)
    for pending, detected in itertools.product((False, True), repeat=2):
        lo, hi, b2 = speed_ranges(p, edges, i_lo, i_hi, pending, detected)
        _, v2, _, b_next = braking_step(p, 0.0, gap, v, integral, np.full(n, pending), np.full(n, detected))
        assert np.all(v2 >= lo[cell]) and np.all(v2 <= hi[cell])
        assert np.all(b_next == b2)
        # and the range is tight: no wider than the samples' spread plus the Lipschitz margin and a cell's worth
        assert np.max(hi - lo) < 0.2


def test_speed_lipschitz_bounds_the_slopes_of_the_true_step():
    p = BrakingParams()
    v = np.linspace(0.0, 9.0, 90_001)
    gap = np.full(v.size, 5.0)
    L = speed_lipschitz(p, 9.0)
    for integral in (-2.7, 0.0, 6.0, 13.5):
        for pending, detected in itertools.product((False, True), repeat=2):
            v2 = braking_step(p, 0.0, gap, v, np.full(v.size, integral), np.full(v.size, pending), np.array(detected))[
                1
            ]
            assert np.max(np.abs(np.diff(v2) / np.diff(v))) <= L
    assert 1.0 < L < 20.0


def test_integral_range_holds_the_integral_of_random_rollouts():
    p = BrakingParams()
    lo, hi = integral_range(p, 0.0, 9.0)
    assert (lo, hi) == pytest.approx((-2.7, 13.5))
    rng = np.random.default_rng(2)
    n = 5000
    vl = lead_speeds(p)
    g, v, i, b = np.full(n, p.gap0_m), np.full(n, p.ego_speed0_mps), np.zeros(n), np.zeros(n, bool)
    for t in range(p.n_steps):
        g, v, i, b = braking_step(p, vl[t], g, v, i, b, rng.random(n) < rng.random())
        assert np.all(v <= 9.0) and np.all((i >= lo) & (i <= hi))
    with pytest.raises(ValueError, match="unbounded"):
        integral_range(BrakingParams(integral_leak=1.0), 0.0, 9.0)


def _least_misses(p: BrakingParams, step: int, g, v, i, b) -> np.ndarray:
    """The least number of misses (inside the braking distance, before the crash) with which each state at ``step``
    crashes, over every detection sequence to the end of the episode; ``NO_CRASH`` where none crashes. int [N]."""
    k = p.n_steps - 1 - step
    seqs = np.array(list(itertools.product((False, True), repeat=k)))  # [2^k, k]
    m, n = seqs.shape[0], g.size
    G, V, Integ, B = (np.repeat(x, m) for x in (g, v, i, b))
    D = np.tile(seqs, (n, 1))
    misses, crashed = np.zeros(n * m, np.int64), np.zeros(n * m, bool)
    vl = lead_speeds(p)
    for s in range(k):
        live = ~crashed
        misses += live & ~D[:, s] & (G < p.braking_distance_m)
        G, V, Integ, B = braking_step(p, vl[step + s], G, V, Integ, B, D[:, s])
        crashed |= live & (G < p.crash_gap_m)
    return np.where(crashed, misses, MissBound.NO_CRASH).reshape(n, m).min(axis=1)


@pytest.fixture(scope="module")
def last_steps():
    """2,000 random states (gap 0.71-4 m, speed 0-8 m/s, integral in its range, either brake command) 8 steps before
    the end of the episode."""
    rng = np.random.default_rng(0)
    n, k = 2000, 8
    p = BrakingParams()
    step = p.n_steps - 1 - k
    lo, hi = integral_range(p, 0.0, 9.5)
    states = (rng.uniform(0.71, 4.0, n), rng.uniform(0.0, 8.0, n), rng.uniform(lo, hi, n), rng.random(n) < 0.5)
    return step, states


@pytest.mark.parametrize("crash_gap", [0.5, 0.0, 1.0])
def test_cell_bound_never_exceeds_the_least_misses_of_any_detection_sequence(last_steps, crash_gap):
    step, (g, v, i, b) = last_steps
    p = BrakingParams(crash_gap_m=crash_gap)
    exact = _least_misses(p, step, g, v, i, b)
    assert (exact == 0).sum() >= 5 and ((exact > 0) & (exact < MissBound.NO_CRASH)).sum() >= 25  # contact: 7 and 30
    bound = cell_miss_bound(p, BrakingStart(step, 4.0, 8.0, 0.0, False), n_gap=400, n_speed=200)
    got = bound(step, g, v, b)
    assert np.all(got <= exact)
    assert np.mean(got == exact) > 0.8  # and it is tight on most states


def test_the_node_bound_breaks_below_the_contact_gap_and_the_cell_bound_does_not(last_steps, monkeypatch):
    # why the cell bound exists: at 0.5 m the node table (miss_bound) asks more misses than some states need
    step, (g, v, i, b) = last_steps
    p = BrakingParams(crash_gap_m=0.5)
    exact = _least_misses(p, step, g, v, i, b)
    monkeypatch.setattr(truth, "MISS_BOUND_MIN_GAP_M", 0.0)
    node = truth.miss_bound(p, BrakingStart(step, 4.0, 8.0, 0.0, False), 201)
    assert (node(step, g, v, b) > exact).sum() > 5
    with pytest.raises(ValueError, match="use cell_miss_bound"):
        monkeypatch.setattr(truth, "MISS_BOUND_MIN_GAP_M", 1.0)
        truth.miss_bound(p, truth.branching_start(p))


def test_exact_bound_takes_the_cell_bound_below_1_m():
    p = BrakingParams(crash_gap_m=0.5)
    b = truth.exact_bound(p, truth.branching_start(p), 41)
    assert isinstance(b, CellMissBound) and b.table.shape[2:] == (200, 40)
    p1 = BrakingParams(crash_gap_m=1.0)
    assert isinstance(truth.exact_bound(p1, truth.branching_start(p1), 41), MissBound)


def test_a_contact_state_is_decided_by_the_gap_it_still_moves():
    p = BrakingParams(crash_gap_m=0.5)
    start = truth.branching_start(p)
    bound = cell_miss_bound(p, start, n_gap=100, n_speed=40)
    # at or below the contact gap the ego stops after moving v dt: 0.6 - 3 * 0.05 = 0.45 < 0.5 crashes
    got = bound(60, np.array([0.6, 0.6, 0.3]), np.array([3.0, 1.0, 0.0]), np.array([False, True, False]))
    assert got.tolist() == [0, MissBound.NO_CRASH, 0]
    with pytest.raises(ValueError, match="above the grid"):
        bound(60, np.array([5.0]), np.array([9.9]), np.array([False]))
    with pytest.raises(ValueError, match="before the table"):
        bound(start.step - 1, np.array([5.0]), np.array([5.0]), np.array([False]))


def test_enumeration_on_the_cell_bound_agrees_with_the_latched_closed_form():
    pem = pytest.importorskip("pemviz.pem").load_pem()
    p = BrakingParams(latched_brake=True, crash_gap_m=0.5)
    lt = latched_log_failure_probability(pem.logit_at_gap, p)
    ex = braking_exact(pem.logit_at_gap, p, log_prune=lt.log_p_fail - 30.0, bound_grid=81)
    assert ex.relative_width < 1e-6
    assert ex.log_p_fail == pytest.approx(lt.log_p_fail, abs=1e-9)
