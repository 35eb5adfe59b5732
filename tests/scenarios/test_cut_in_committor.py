"""The cut-in's committor grid and level chain (:mod:`pemviz.scenarios.cut_in.committor`) and its one-car look-ahead
(:mod:`pemviz.scenarios.cut_in.lookahead`), which the cut-in's default tilted proposal and its splitting build on: the
tilt over the cut-in car's uniforms weighs every draw so that each event keeps its PEM probability, whatever the
committor Q it is tilted by (a deliberately poor one here); the levels and the chain against closed forms; the cut-in
car alone drives the ego as the whole twin does. (The study that first used them, research/cut_in_lookahead_tilt.py,
is tested in research/tests/.)"""

from __future__ import annotations

import numpy as np
import pytest
from pemviz.scenarios.cut_in import committor, lookahead


def poor_proposal(grid, p0):
    """The grid's tilted proposal with a random Q (log Q uniform on [-30, 0] per branch): no relation to any failure."""
    log_qb = np.random.default_rng(5).uniform(-30.0, 0.0, size=(p0.size, grid.nbranch))
    return grid.proposal(p0, log_qb, 0.3)


@pytest.mark.parametrize("grid_name", ["fine", "coarse"])
def test_a_tilted_draw_is_weighed_so_that_every_event_keeps_its_pem_probability(grid_name):
    """Uniforms drawn class by class from the proposal and weighed p / q of the class they fall in: E[w] = 1,
    E[w 1{miss}] = 1 - p(detect), and E[w 1{u < m}] = p(detect) m for tail masses m inside bins (so a draw that were
    not uniform in its bin would show), within 5 standard errors of 200,000 draws."""
    grid = committor.Grid(np.array(committor.GRIDS[grid_name]))
    n = 200_000
    p0 = np.full(n, 0.985)
    pc, qc = (a[0] for a in poor_proposal(grid, p0[:1]))
    assert pc.sum() == pytest.approx(1.0) and qc.sum() == pytest.approx(1.0)
    rng = np.random.default_rng(7)
    cum = np.cumsum(qc)
    cls = np.minimum(np.searchsorted(cum, rng.random(n) * cum[-1], side="right"), cum.size - 1)
    u = grid.draw(cls, p0, rng.random((n, 3)))
    assert (u >= 0).all() and (u < 1).all()
    assert np.array_equal(grid.classify(u, p0), cls)
    w = pc[cls] / qc[cls]

    def check(values, expected):
        assert abs(values.mean() - expected) < 5 * values.std() / np.sqrt(n) + 1e-12, expected

    check(w, 1.0)
    check(w * (u[:, 0] > p0), 1.0 - p0[0])
    detected = u[:, 0] <= p0
    for c, mass in [(1, 3e-3), (1, 0.2), (2, 0.05), (2, 7e-4)]:
        check(w * (detected & (u[:, c] < mass)), p0[0] * mass)
        check(w * (detected & (u[:, c] > 1.0 - mass)), p0[0] * mass)


def test_the_tilt_follows_q_and_the_pems_keep_their_share():
    """A class whose Q is e^30 times another's is drawn far more often, and every class keeps at least eps p."""
    grid = committor.Grid(np.array(committor.GRIDS["coarse"]))
    p0 = np.array([0.99])
    log_qb = np.full((1, grid.nbranch), -30.0)
    log_qb[0, 0] = 0.0  # a miss fails: Q = 1
    pc, qc = grid.proposal(p0, log_qb, 0.3)
    assert qc[0, 0] > 0.69 and pc[0, 0] == pytest.approx(0.01)
    assert (qc >= 0.3 * pc - 1e-15).all()


def test_a_continuations_level_counts_the_steps_of_late_braking_it_can_still_take():
    """Level 0 fails; 0.10 m (one step late at the moderate setting) is 1; 0.86 m (on time) 2; capped at LMAX."""
    r = np.array([-0.66, -1e-9, 0.0, 0.10, 0.75, 0.86, 1.62, 100.0])
    assert committor.level(r).tolist() == [0, 0, 1, 1, 1, 2, 3, committor.LMAX]


def test_the_continuous_level_adds_how_deep_inside_the_lane_the_track_followed():
    """L - 1 + depth / lateral step, the depth capped at one step: hand-computed cases (a failing branch stays 0)."""
    lv = np.array([0, 1, 1, 2, 2, 3])
    inside = np.array([-0.1, -0.1, 0.0, -0.3, 0.2, -0.05])
    step = np.array([0.2, 0.2, 0.2, 0.2, 0.2, 0.25])
    assert committor.continuous_level(lv, inside, step) == pytest.approx([0.0, 0.5, 0.0, 2.0, 1.0, 2.2])


@pytest.mark.parametrize("miss_shift, expected", [(-2.0, 1 - 0.9 * 0.8), (-1.0, 0.1 * 0.2), (-0.5, 0.0)])
def test_the_level_chain_gives_the_closed_form_probability_of_enough_misses(miss_shift, expected):
    """Two steps whose only event that moves the continuous level is a miss (p 0.1, then 0.2): from g = 1.5, a miss
    that lowers g by 2 fails alone (1 - 0.9 x 0.8), by 1 needs both (0.1 x 0.2), by 0.5 cannot fail (g stays 0.5)."""
    grid = committor.Grid(np.array(committor.GRIDS["coarse"]))
    effects = {t: {0: np.r_[miss_shift, np.zeros(grid.nbranch - 1)]} for t in range(2)}
    nexts = {t: {0: np.zeros(grid.nbranch, dtype=np.int64)} for t in range(2)}
    chain = committor.LevelChain(grid, (0, 2), {0: 0.9, 1: 0.8}, effects, nexts, 1, 0.01, 6.0)
    assert np.exp(chain.log_u(0, np.array(1.5))) == pytest.approx(expected, abs=1e-12)
    assert np.exp(chain.log_u(2, np.array([0.0, 0.3]))) == pytest.approx([1.0, 0.0], abs=1e-12)


@pytest.mark.parametrize("miss_shift, miss_q, other_q", [(-2.0, 1.0, 0.2), (-1.0, 0.2, 0.0)])
def test_the_chain_gives_each_branch_the_value_of_the_level_its_event_leads_to(miss_shift, miss_q, other_q):
    """--chain-effects: from g = 1.5 at step 0 of the two-step chain above, a miss leads to g = 1.5 + shift and any
    detection keeps g = 1.5, so the branches' Q is U_1 there: 1 and 1 - 0.8 (shift -2: a second miss fails too), or
    0.2 and 0 (shift -1); and sum_c p(c) Q(c) gives back U_0(1.5) (1 - 0.9 x 0.8, or 0.1 x 0.2)."""
    grid = committor.Grid(np.array(committor.GRIDS["lean"]))
    effects = {t: {0: np.r_[miss_shift, np.zeros(grid.nbranch - 1)]} for t in range(2)}
    nexts = {t: {0: np.zeros(grid.nbranch, dtype=np.int64)} for t in range(2)}
    chain = committor.LevelChain(grid, (0, 2), {0: 0.9, 1: 0.8}, effects, nexts, 1, 0.01, 6.0)
    q = np.exp(chain.log_q_branches(0, np.array([1.5]), np.array([0])))
    assert q.shape == (1, grid.nbranch)
    assert q[0, 0] == pytest.approx(miss_q, abs=1e-12) and q[0, 1:] == pytest.approx(other_q, abs=1e-12)
    pc = grid.p_class(np.array([0.9]))
    u0 = (pc * np.exp(grid.class_values(chain.log_q_branches(0, np.array([1.5]), np.array([0]))))).sum()
    assert u0 == pytest.approx(np.exp(chain.log_u(0, np.array(1.5))), abs=1e-12)


def test_a_chain_with_bins_of_g_takes_each_bins_effect_and_the_nearest_where_a_bin_has_none():
    """--beam's cells: a miss lowers g by 0.6 at g >= 1 and by 2 below (bins 1 wide; bins 2-6 have no representative
    and take bin 1's). From g = 1.5, two misses (p 0.1, then 0.2) fail: 0.1 x 0.2; one alone leaves g at 0.9. With
    one bin, the misses' -0.6 each never fail (0.3 left). Regime 1, without any representative, takes the nominal
    regime's (the first cell)."""
    grid = committor.Grid(np.array(committor.GRIDS["lean"]))

    def shift(d):
        return np.r_[d, np.zeros(grid.nbranch - 1)]

    nexts0 = np.zeros(grid.nbranch, dtype=np.int64)
    binned = committor.LevelChain(
        grid,
        (0, 2),
        {0: 0.9, 1: 0.8},
        {t: {1: shift(-0.6), 0: shift(-2.0)} for t in range(2)},
        {t: {1: nexts0, 0: nexts0} for t in range(2)},
        2,
        0.01,
        6.0,
        bin_width=1.0,
    )
    one = committor.LevelChain(
        grid,
        (0, 2),
        {0: 0.9, 1: 0.8},
        {t: {0: shift(-0.6)} for t in range(2)},
        {t: {0: nexts0} for t in range(2)},
        2,
        0.01,
        6.0,
    )
    assert binned.nbins == 7 and binned.nearest_cells([1, 0], 2).tolist() == [[0, 1, 1, 1, 1, 1, 1]] * 2
    assert np.exp(binned.log_u(0, np.array([1.5, 1.5]), np.array([0, 1]))) == pytest.approx([0.02, 0.02], abs=1e-12)
    assert np.exp(one.log_u(0, np.array(1.5))) == pytest.approx(0.0, abs=1e-12)
    q = np.exp(binned.log_q_branches(0, np.array([1.5, 0.5]), np.array([0, 0])))
    assert q[0, 0] == pytest.approx(0.2, abs=1e-12) and q[0, 1] == pytest.approx(0.0, abs=1e-12)
    assert q[1, 0] == pytest.approx(1.0, abs=1e-12) and q[1, 1] == pytest.approx(0.2, abs=1e-12)


def test_the_cut_in_car_alone_drives_the_ego_as_the_whole_twin_does():
    """The look-ahead's one-car twin (--one-car): 300 rollouts whose cut-in car is missed and mislocated at random
    (every other car detected without error) move the ego, its ACC's choice and the failure formula's operand the same
    way with the cut-in car alone as with the whole traffic, steps 0-40 (the study measured 99.9997 % of 344,400
    look-ahead branches at the same level)."""
    from pemviz.scenarios.cut_in.batched import BatchedCutIn
    from pemviz.scenarios.cut_in.problem import cut_in_params

    params = cut_in_params("moderate")
    n, rng = 300, np.random.default_rng(3)
    whole, alone = BatchedCutIn(params, n), lookahead.OneCar(params, n)
    visible = lookahead.VISIBLE
    for _ in range(40):
        obs, obs1 = whole.observation(), alone.observation()
        np.testing.assert_allclose(lookahead.operand(obs1), lookahead.operand(obs), rtol=0, atol=1e-9)
        assert np.array_equal(obs1[:, lookahead.FOLLOWED], obs[:, lookahead.FOLLOWED])
        det = whole.objects()[:, :, visible] > 0.5
        det[:, 0] &= rng.random(n) > 0.2
        noise = np.zeros((n, params.n_objects, 2))
        noise[:, 0] = rng.standard_t(2.0, size=(n, 2)) * [0.8, 0.3]
        assert np.array_equal(alone.objects()[:, :, visible] > 0.5, whole.objects()[:, :1, visible] > 0.5)
        whole.step(det, noise)
        alone.step(det[:, :1], noise[:, :1])
    np.testing.assert_allclose(alone.state.ego_speed_mps, whole.state.ego_speed_mps, rtol=0, atol=1e-9)
    assert (whole.state.followed == 0).mean() > 0.5  # the ACC follows the cut-in car in most rollouts by step 40
