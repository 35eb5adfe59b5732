"""Each robustness semantics object (Classic, AGM, SmoothCumulative) against hand-computed operator values.

Arrays are time-major [L, n] as the semantics objects take them. Sources: classic, Donze & Maler 2010;
AGM, Mehdipour, Vasile & Belta, ACC 2019, Def. 2; smooth cumulative, Haghighi, Mehdipour, Bartocci & Belta
2019 (arXiv 1904.11611), smooth Def. 3.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from pemviz import stl
from pemviz.stl._kernels import NumpyOps as OPS


def col(*values: float) -> np.ndarray:
    """One trace as a time-major column [L, 1]."""
    return np.asarray(values, dtype=np.float64)[:, None]


def flat(x: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(x).ravel()]


def smin(xs: list[float], b: float) -> float:
    return -math.log(sum(math.exp(-b * x) for x in xs)) / b


def smax(xs: list[float], b: float) -> float:
    return math.log(sum(math.exp(b * x) for x in xs)) / b


def softplus(h: float, b: float) -> float:
    return math.log1p(math.exp(b * h)) / b


D_GE_2 = stl.parse("d >= 2")


def h_of(d: list[float]):
    """value(c) = c * (d - 2), time-major, as the formula walk hands it to a predicate."""
    h = col(*d) - 2.0
    return lambda c: c * h


# ------------------------------------------------------------------------------------------------
# Classic
# ------------------------------------------------------------------------------------------------


def test_classic_predicate_and_connectives():
    sem = stl.Classic()
    assert flat(sem.predicate(OPS, D_GE_2, h_of([5.0, 1.5]), 1.0, 1)) == [3.0, -0.5]
    assert flat(sem.predicate(OPS, D_GE_2, h_of([5.0, 1.5]), -1.0, -1)) == [-3.0, 0.5]
    x, y = np.array([[1.0, -2.0]]), np.array([[0.5, 3.0]])
    assert flat(sem.conj(OPS, [x, y])) == [0.5, -2.0]
    assert flat(sem.disj(OPS, [x, y])) == [1.0, 3.0]


def test_classic_windows_are_min_and_max_cut_at_the_trace_end():
    sem = stl.Classic()
    r = col(3.0, 1.0, 2.0, 5.0)
    assert flat(sem.window(OPS, r, 3, 2, True)) == [1.0, 1.0, 2.0]
    assert flat(sem.window(OPS, r, 3, 2, False)) == [3.0, 2.0, 5.0]
    assert flat(sem.window(OPS, r, 4, 2, True)) == [1.0, 1.0, 2.0, 5.0]  # last window: step 3 alone
    assert flat(sem.window(OPS, r, 1, 4, True)) == [1.0]
    assert flat(sem.window(OPS, r.T, 1, 4, False, axis=1)) == [5.0]  # trace-major [n, L]


def test_classic_until_takes_left_strictly_before_the_witness():
    sem = stl.Classic()
    left, right = col(1.0, -1.0, 2.0), col(-5.0, 0.5, 4.0, 1.0)
    # t = 0: t' = 0 -> -5; t' = 1 -> min(0.5, 1) = 0.5; t' = 2 -> min(4, 1, -1) = -1: max 0.5
    # t = 1: t' = 1 -> 0.5; t' = 2 -> min(4, -1) = -1; t' = 3 -> min(1, -1, 2) = -1: max 0.5
    assert flat(sem.until(OPS, left, right, 0, 2, 2, 3)) == [0.5, 0.5]
    assert flat(sem.until(OPS, left, right, 0, 2, 1, 3)) == [0.5]
    # U[2,2] at t = 0: min(right(2) = 4, left(0) = 1, left(1) = -1) = -1
    assert flat(sem.until(OPS, left, right[2:], 2, 2, 1, 3)) == [-1.0]


# ------------------------------------------------------------------------------------------------
# AGM
# ------------------------------------------------------------------------------------------------


def test_agm_predicate_divides_by_the_range_scale_and_clips():
    sem = stl.AGM({"d": (0.0, 15.0)}).prepare(D_GE_2)
    assert flat(sem.predicate(OPS, D_GE_2, h_of([8.5, 40.0, 2.0]), 1.0, 1)) == [0.5, 1.0, 0.0]
    assert flat(sem.predicate(OPS, D_GE_2, h_of([8.5]), -1.0, -1)) == [-0.5]
    # without ranges the values are used as written and must lie in [-1, 1]
    with pytest.raises(ValueError, match=r"AGM needs predicate values in \[-1, 1\]"):
        stl.AGM().predicate(OPS, D_GE_2, h_of([8.5]), 1.0, 1)
    with pytest.raises(ValueError, match="no range for signal 'd'"):
        stl.AGM({"v": (0.0, 1.0)}).prepare(D_GE_2)
    with pytest.raises(TypeError, match="signal_ranges must be a mapping"):
        stl.AGM([("d", (0.0, 1.0))])  # type: ignore[arg-type]


def test_agm_connectives_are_geometric_or_arithmetic_means():
    sem = stl.AGM()
    conj = sem.conj(OPS, [np.array([[0.2, 0.4]]), np.array([[0.5, -0.3]])])
    assert flat(conj) == pytest.approx([math.sqrt(1.2 * 1.5) - 1, -0.3 / 2], abs=1e-15)
    disj = sem.disj(OPS, [np.array([[-0.2, 0.6]]), np.array([[-0.4, -0.1]])])
    assert flat(disj) == pytest.approx([1 - math.sqrt(1.2 * 1.4), 0.6 / 2], abs=1e-15)


def test_agm_windows_average_over_the_steps_inside_the_trace():
    sem = stl.AGM()
    g = sem.window(OPS, col(0.2, 0.5, -0.4), 2, 2, True)
    assert flat(g) == pytest.approx([math.sqrt(1.2 * 1.5) - 1, -0.4 / 2], abs=1e-15)
    f = sem.window(OPS, col(0.2, -0.5, -0.4), 3, 2, False)
    # t = 2: the window [2, 3] keeps step 2 only (m = 1): 1 - (1 + 0.4)
    assert flat(f) == pytest.approx([0.2 / 2, 1 - math.sqrt(1.5 * 1.4), -0.4], abs=1e-15)
    whole = sem.window(OPS, col(0.2, 0.5, 0.1), 1, 3, True)
    assert flat(whole) == pytest.approx([(1.2 * 1.5 * 1.1) ** (1 / 3) - 1], abs=1e-15)


def test_agm_until_is_the_agm_or_over_witnesses():
    sem = stl.AGM()
    # witnesses t' = 0, 1, 2: -0.5; &(-0.2, 0.5) = -0.1; &(0.6, &(0.5, 0.4)) > 0: mean of positive parts
    got = sem.until(OPS, col(0.5, 0.4), col(-0.5, -0.2, 0.6), 0, 2, 1, 2)
    assert flat(got) == pytest.approx([(math.sqrt(1.6 * math.sqrt(1.5 * 1.4)) - 1) / 3], abs=1e-15)


# ------------------------------------------------------------------------------------------------
# Smooth cumulative
# ------------------------------------------------------------------------------------------------


def test_smooth_cumulative_predicate_is_softplus_of_the_polarity():
    sem = stl.SmoothCumulative(2.0)
    assert flat(sem.predicate(OPS, D_GE_2, h_of([2.3]), 1.0, 1)) == pytest.approx([softplus(0.3, 2.0)], abs=1e-15)
    # !(d >= 2) under rho+: minus rho- of the predicate = softplus_b(-h)
    assert flat(sem.predicate(OPS, D_GE_2, h_of([2.3]), -1.0, -1)) == pytest.approx([softplus(-0.3, 2.0)], abs=1e-15)
    # rho- of the predicate itself (under an odd number of negations): -softplus_b(-h)
    assert flat(sem.predicate(OPS, D_GE_2, h_of([2.3]), 1.0, -1)) == pytest.approx([-softplus(-0.3, 2.0)], abs=1e-15)


def test_smooth_cumulative_connectives_windows_and_until():
    b = 2.0
    sem = stl.SmoothCumulative(b)
    x, y = np.array([[1.0]]), np.array([[2.0]])
    assert flat(sem.conj(OPS, [x, y])) == pytest.approx([smin([1.0, 2.0], b)], abs=1e-14)
    assert flat(sem.disj(OPS, [x, y])) == pytest.approx([smax([1.0, 2.0], b)], abs=1e-14)
    r = col(1.0, 2.0, 0.5)
    assert flat(sem.window(OPS, r, 2, 2, True)) == pytest.approx([smin([1.0, 2.0], b), smin([2.0, 0.5], b)], abs=1e-14)
    assert flat(sem.window(OPS, r, 3, 2, False)) == pytest.approx([3.0, 2.5, 0.5], abs=1e-15)  # F sums
    assert flat(sem.window(OPS, r, 1, 3, True)) == pytest.approx([smin([1.0, 2.0, 0.5], b)], abs=1e-14)
    # until: sum over t' of softmin(right(t'), left over [0, t'))
    got = sem.until(OPS, col(1.0, 0.5), col(0.2, 1.5, 2.0), 0, 2, 1, 2)
    expected = 0.2 + smin([1.5, 1.0], b) + smin([2.0, 1.0, 0.5], b)
    assert flat(got) == pytest.approx([expected], abs=1e-14)


@pytest.mark.parametrize("bad", [0.0, -1.0, math.inf, "hot", None])
def test_smooth_cumulative_rejects_a_bad_temperature(bad):
    with pytest.raises(ValueError, match="temperature must be"):
        stl.SmoothCumulative(bad)  # type: ignore[arg-type]


# ------------------------------------------------------------------------------------------------
# Choosing a semantics at the entry point
# ------------------------------------------------------------------------------------------------


def test_semantics_from_name_and_objects_at_the_entry_point():
    assert [s.name for s in (stl.Classic(), stl.AGM(), stl.SmoothCumulative())] == list(stl.SEMANTICS)
    assert isinstance(stl.semantics_from_name("agm", signal_ranges={"d": (0.0, 15.0)}), stl.AGM)
    sc = stl.semantics_from_name("smooth-cumulative", temperature=3.0)
    assert isinstance(sc, stl.SmoothCumulative) and sc.temperature == 3.0
    with pytest.raises(ValueError, match="unknown robustness semantics 'stl'; allowed: 'classic', 'agm'"):
        stl.semantics_from_name("stl")
    d = {"d": np.array([[15.0, 8.5, 4.6]])}
    got = stl.robustness("G[0,2](d >= 2)", d, stl.AGM({"d": (0.0, 15.0)}))
    assert float(got[0]) == pytest.approx((2.0 * 1.5 * 1.2) ** (1 / 3) - 1, abs=1e-15)
    got = stl.robustness("F[0,1](d >= 8)", d, stl.SmoothCumulative(1.0))
    assert float(got[0]) == pytest.approx(softplus(7.0, 1.0) + softplus(0.5, 1.0), abs=1e-14)
    with pytest.raises(ValueError, match="give them to the object"):
        stl.robustness("d >= 2", d, stl.SmoothCumulative(1.0), temperature=3.0)
    with pytest.raises(ValueError, match="give them to the object"):
        stl.robustness("d >= 2", d, stl.Classic(), signal_ranges={"d": (0.0, 15.0)})


def test_temporal_operators_share_one_base_and_differ_in_the_reduction():
    p = stl.signal("d") >= 2
    g, f, u = stl.always(p, 1, 4), stl.eventually(p, 1, 4), stl.until(p, p, 0, None)
    assert all(isinstance(x, stl.Temporal) for x in (g, f, u))
    assert isinstance(g, stl.UnaryTemporal) and isinstance(f, stl.UnaryTemporal)
    assert (g.conjunctive, f.conjunctive) == (True, False)
    assert (g.symbol, f.symbol, u.symbol) == ("G", "F", "U")
    assert g != f and (g.operand, g.start, g.end) == (f.operand, f.start, f.end)
    assert (str(g), str(f), str(u)) == ("G[1,4](d >= 2)", "F[1,4](d >= 2)", "(d >= 2) U[0,inf] (d >= 2)")
    assert repr(f) == (
        "Eventually(operand=Predicate(lhs=Signal(name='d'), op='>=', rhs=Const(value=2.0)), start=1, " "end=4)"
    )
    with pytest.raises(ValueError, match=r"interval \[3,1\] of F is empty"):
        stl.eventually(p, 3, 1)
