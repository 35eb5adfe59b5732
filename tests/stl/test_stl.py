"""STL formulas: text round trip, builders, trace-end convention, and one clear error per bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from pemviz import stl
from pemviz.stl import always, eventually, signal, until

CANONICAL = [
    "G[0,99](d >= 2)",
    "G[0,150](d < 5 -> F[0,20](v <= 0.1))",
    "(d - 2) / 13 >= 0",
    "!(a > 1) & b < 2 | (c >= 0) U[1,5] (d < 3)",
    "F[2,inf](x >= -2 * y + 1)",
    "a >= 1 -> b >= 1 -> c >= 1",
    "(a >= 1 -> b >= 1) -> c >= 1",
    "a > 0 & (b > 0 & c > 0)",
    "a > 0 & (b > 0 | c > 0)",
    "d - -2 >= 0.25",
    "-(d - 2) <= 1e-05",
    "G[0,3](F[1,2](x > 0) & !(G[0,0](y <= 1)))",
    "(G[0,2](x > 0)) U[0,4] (F[1,1](y.z >= 3.5))",
    "gap_m >= 2 | ego_speed_mps <= 0.1",
]


@pytest.mark.parametrize("text", CANONICAL)
def test_canonical_text_round_trips(text):
    f = stl.parse(text)
    assert str(f) == text
    assert stl.parse(str(f)) == f


@pytest.mark.parametrize(
    "text,canonical",
    [
        ("always[0:99](d>=2)", "G[0,99](d >= 2)"),
        ("G(d >= 2)", "G[0,inf](d >= 2)"),
        ("eventually [ 1 , inf ) (v<0)", "F[1,inf](v < 0)"),
        ("not d >= 2 and v > 1 or w < 0", "!(d >= 2) & v > 1 | w < 0"),
        ("~(d >= 2) && v > 1 || w < 0", "!(d >= 2) & v > 1 | w < 0"),
        ("d >= 2 implies v <= 0", "d >= 2 -> v <= 0"),
        ("(x > 0) until[0:5] (y > 0)", "(x > 0) U[0,5] (y > 0)"),
        ("x > 0 U y > 0", "(x > 0) U[0,inf] (y > 0)"),
        ("((d >= 2))", "d >= 2"),
        ("G[0,9] d >= 2", "G[0,9](d >= 2)"),
        ("2*(d - 1) >= .5e1", "2 * (d - 1) >= 5"),
    ],
)
def test_alternative_spellings_parse_to_canonical_text(text, canonical):
    assert str(stl.parse(text)) == canonical


def test_builders_equal_parsed_formulas():
    d, v = signal("d"), signal("v")
    spec = always((d < 5) >> eventually(v <= 0.1, 0, 20), 0, 150)
    assert spec == stl.parse("G[0,150](d < 5 -> F[0,20](v <= 0.1))")
    assert str(spec) == "G[0,150](d < 5 -> F[0,20](v <= 0.1))"
    assert (d >= 2) & (v < 1) & (v > 0) == stl.parse("d >= 2 & v < 1 & v > 0")
    assert ~(d >= 2) | (v < 1) == stl.parse("!(d >= 2) | v < 1")
    assert until(d >= 2, v <= 0, 1, 4) == stl.parse("(d >= 2) U[1,4] (v <= 0)")
    assert str((d - 2) / 13 >= 0) == "(d - 2) / 13 >= 0"
    assert stl.braking_spec(100) == stl.parse("G[0,99](d >= 2)")


def test_predicate_is_affine_in_the_signals():
    p = stl.parse("2 * (d - 1) - v / 4 < 3 + d")
    # rhs - lhs = 3 + d - 2 d + 2 + v / 4 = 5 - d + v / 4
    assert p.coefficients == {"d": -1.0, "v": 0.25}
    assert p.offset == 5.0
    assert p.signals() == frozenset({"d", "v"})


def test_horizon_and_signals():
    f = stl.parse("G[0,150](d < 5 -> F[0,20](v <= 0.1))")
    assert f.horizon() == 170
    assert f.signals() == frozenset({"d", "v"})
    assert stl.parse("(x > 0) U[2,7] (G[0,3](y > 0))").horizon() == 10
    assert stl.parse("F[2,inf](x > 0)").horizon() is None


# ------------------------------------------------------------------------------------------------
# Robustness basics and the trace-end convention
# ------------------------------------------------------------------------------------------------


def test_braking_spec_classic_is_min_gap_minus_two():
    rng = np.random.default_rng(0)
    d = rng.uniform(0.0, 15.0, size=(50, 100))
    np.testing.assert_array_equal(stl.robustness("G[0,99](d >= 2)", {"d": d}), d.min(axis=1) - 2.0)
    sig = stl.robustness_signal("G[0,99](d >= 2)", {"d": d})
    # suffix minima: the window [t, t+99] is cut at the trace end
    np.testing.assert_array_equal(sig, np.minimum.accumulate(d[:, ::-1], axis=1)[:, ::-1] - 2.0)


def test_windows_past_the_trace_end_are_cut_and_empty_ones_are_vacuous():
    x = {"x": np.array([[1.0, -2.0, 3.0, 0.5]])}
    # G[2,3] at t = 0..3: windows [2,3], [3,3], empty, empty
    np.testing.assert_array_equal(stl.robustness_signal("G[2,3](x >= 0)", x)[0], [0.5, 0.5, math.inf, math.inf])
    np.testing.assert_array_equal(stl.robustness_signal("F[2,3](x >= 0)", x)[0], [3.0, 0.5, -math.inf, -math.inf])
    agm = stl.robustness_signal("G[2,3](x >= 0) | F[2,3](x >= 0)", x, "agm", signal_ranges={"x": (-4, 4)})
    assert agm[0, 3] == 0.5  # AGM vacuous G is +1, F is -1; | of them: mean of the positive parts (1 + 0) / 2
    assert stl.robustness_signal("G[2,3](x >= 0)", x, "agm", signal_ranges={"x": (-4, 4)})[0, 3] == 1.0
    assert stl.robustness_signal("F[2,3](x >= 0)", x, "agm", signal_ranges={"x": (-4, 4)})[0, 3] == -1.0
    assert stl.robustness_signal("F[2,3](x >= 0)", x, "smooth-cumulative")[0, 3] == 0.0
    assert stl.robustness_signal("G[2,3](x >= 0)", x, "smooth-cumulative")[0, 3] == math.inf


def test_open_ended_interval_runs_to_the_trace_end():
    rng = np.random.default_rng(1)
    sig = {"x": rng.normal(size=(6, 30)), "y": rng.normal(size=(6, 30))}
    for sem in stl.SEMANTICS:
        kw = dict(signal_ranges={"x": (-5, 5), "y": (-5, 5)})
        a = stl.robustness_signal("F[3,inf](x > 0) & (x > -1) U[1,inf] (y > 1)", sig, sem, **kw)
        b = stl.robustness_signal("F[3,29](x > 0) & (x > -1) U[1,29] (y > 1)", sig, sem, **kw)
        np.testing.assert_array_equal(a, b)


def test_single_trace_gives_a_scalar_and_empty_batch_an_empty_result():
    d = np.array([5.0, 3.0, 2.5])
    r = stl.robustness("G[0,2](d >= 2)", {"d": d})
    assert r.shape == () and float(r) == 0.5
    assert stl.robustness_signal("G[0,2](d >= 2)", {"d": d}).shape == (3,)
    assert stl.robustness("G[0,2](d >= 2)", {"d": np.zeros((0, 3))}).shape == (0,)
    t = stl.robustness("G[0,2](d >= 2)", {"d": torch.tensor(d)})
    assert isinstance(t, torch.Tensor) and t.shape == () and float(t) == 0.5


def test_inputs_are_not_modified_and_outputs_do_not_alias_them():
    d = np.array([[5.0, 3.0, 2.5]])
    out = stl.robustness_signal("d >= 0", {"d": d})
    out[0, 0] = -1.0
    assert d[0, 0] == 5.0


def test_agrees_with_integer_and_float32_inputs():
    d = np.array([[5, 3, 4]], dtype=np.int32)
    assert stl.robustness("G[0,2](d >= 2)", {"d": d})[0] == 1.0
    assert stl.robustness("G[0,2](d >= 2)", {"d": d.astype(np.float32)}).dtype == np.float64


# ------------------------------------------------------------------------------------------------
# Bad input: one clear error each
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text,column,message",
    [
        ("G[0,99(d >= 2)", 7, "expected ']'"),
        ("G[0,99](d >= )", 14, "expected a signal, a number or '('"),
        ("G[0,99](d >= 2", 15, "expected ')'"),
        ("d >= 2 &", 9, "end of text"),
        ("G[5,2](d >= 0)", 5, "is empty"),
        ("G[-1,2](d >= 0)", 3, "must be >= 0"),
        ("F[0,1.5](d >= 0)", 5, "non-negative integer"),
        ("d * v >= 1", 3, "not affine"),
        ("d / v >= 1", 3, "divides by a signal"),
        ("d >= 2 2", 8, "after a complete formula"),
        ("d == 2", 3, "not supported"),
        ("F >= 2", 1, "operator, not a signal name"),
        ("inf >= 2", 1, "keyword"),
        ("d >= 2 $ v", 8, "unexpected character"),
        ("d + 2 >= 2 + d", 1, "reads no signal"),
        ("(a > 0) U[0,1] (b > 0) U[0,1] (c > 0)", 24, "chained U"),
        ("", 1, "empty formula"),
    ],
)
def test_malformed_text_error_names_the_column(text, column, message):
    with pytest.raises(stl.STLSyntaxError) as err:
        stl.parse(text)
    assert err.value.column == column, str(err.value)
    assert message in str(err.value)
    assert f"column {column}" in str(err.value)
    assert isinstance(err.value, ValueError)


def test_unknown_signal_names_the_signal_and_column():
    with pytest.raises(ValueError, match=r"reads signal 'v' at column 17 but signals has only \['d'\]"):
        stl.robustness("G[0,9](d >= 2 & v <= 1)", {"d": np.zeros((2, 10))})


def test_interval_past_the_trace_end_names_the_operator_and_column():
    d = {"d": np.zeros((2, 100))}
    with pytest.raises(ValueError, match=r"interval \[120,130\] of F \(column 9\) lies past the end of the trace"):
        stl.robustness("G[0,10](F[120,130](d >= 2))", d)
    with pytest.raises(ValueError, match=r"interval \[0,199\] of G \(column 1\) needs step 199.*T = 100"):
        stl.robustness("G[0,199](d >= 2)", d, trace_end="error")
    assert stl.robustness("G[0,199](d >= 2)", d)[0] == -2.0  # truncate (default): cut at the end


def test_unknown_semantics_lists_the_allowed_names():
    with pytest.raises(
        ValueError, match=r"unknown robustness semantics 'smooth'; allowed: 'classic', 'agm', " r"'smooth-cumulative'"
    ):
        stl.robustness("d >= 2", {"d": np.zeros((1, 3))}, "smooth")
    assert stl.SEMANTICS == ("classic", "agm", "smooth-cumulative")


@pytest.mark.parametrize(
    "kwargs,error,message",
    [
        (dict(time=3), ValueError, r"time=3 is outside the trace: 0 <= time < T = 3"),
        (dict(time=-1), ValueError, r"outside the trace"),
        (dict(time=1.0), TypeError, r"time must be an int"),
        (dict(semantics="smooth-cumulative", temperature=0.0), ValueError, r"temperature must be finite and > 0"),
        (dict(trace_end="clip"), ValueError, r"unknown trace_end 'clip'; allowed: 'truncate', 'error'"),
        (dict(semantics="agm", signal_ranges={"d": (1.0, 1.0)}), ValueError, r"lo < hi"),
        (dict(semantics="agm", signal_ranges={"v": (0.0, 1.0)}), ValueError, r"no range for signal 'd'"),
    ],
)
def test_bad_arguments_raise_one_clear_error(kwargs, error, message):
    with pytest.raises(error, match=message):
        stl.robustness("G[0,2](d >= 2)", {"d": np.ones((2, 3))}, **kwargs)


def test_bad_signal_arrays_raise_clear_errors():
    f = "G[0,2](d >= 2 & v > 0)"
    with pytest.raises(ValueError, match=r"same shape.*'d' is \[2, 3\], 'v' is \[2, 4\]"):
        stl.robustness(f, {"d": np.ones((2, 3)), "v": np.ones((2, 4))})
    with pytest.raises(ValueError, match=r"signal 'v' contains NaN \(trace 1, step 2\)"):
        v = np.ones((2, 3))
        v[1, 2] = np.nan
        stl.robustness(f, {"d": np.ones((2, 3)), "v": v})
    with pytest.raises(TypeError, match=r"signals must be a mapping"):
        stl.robustness(f, [np.ones((2, 3))])
    with pytest.raises(TypeError, match=r"signal 'd' must be a real numeric array"):
        stl.robustness(f, {"d": np.array([["a", "b", "c"]]), "v": np.ones((1, 3))})
    with pytest.raises(ValueError, match=r"\[N, T\] \(or one trace \[T\]\), got shape \[2, 3, 1\]"):
        stl.robustness(f, {"d": np.ones((2, 3, 1)), "v": np.ones((2, 3, 1))})


def test_builder_rejects_bad_intervals_and_operands():
    with pytest.raises(ValueError, match=r"interval \[3,1\] of G is empty"):
        always(signal("d") >= 2, 3, 1)
    with pytest.raises(TypeError, match=r"must be an int"):
        eventually(signal("d") >= 2, 0.5, 2)
    with pytest.raises(TypeError, match=r"must be an STL Formula"):
        (signal("d") >= 2) & 3
    with pytest.raises(ValueError, match=r"keyword"):
        signal("until")
