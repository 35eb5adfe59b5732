"""AGM and smooth-cumulative robustness against hand-computed values of their papers' definitions.

AGM: Mehdipour, Vasile & Belta, "Arithmetic-Geometric Mean Robustness for Control from STL Specifications",
ACC 2019. Smooth cumulative: Haghighi, Mehdipour, Bartocci & Belta, arXiv 1904.11611 (2019), positive
cumulative robustness rho+ with softplus rectification and log-sum-exp soft min/max at temperature b.
Until uses the discrete-time convention of rtamt for all semantics: the left operand over [t, t').
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from pemviz import stl


def _sp(h: float, b: float) -> float:
    """softplus_b(h) = log(1 + e^(b h)) / b."""
    return math.log1p(math.exp(b * h)) / b if b * h < 30 else h + math.log1p(math.exp(-b * h)) / b


def _smin(xs: list[float], b: float) -> float:
    """-(1/b) log sum exp(-b x); +inf terms drop out, a -inf term wins."""
    if any(x == -math.inf for x in xs):
        return -math.inf
    xs = [x for x in xs if x != math.inf]
    if not xs:
        return math.inf
    lo = min(xs)
    return lo - math.log(sum(math.exp(-b * (x - lo)) for x in xs)) / b


def _smax(xs: list[float], b: float) -> float:
    return -_smin([-x for x in xs], b)


def _cum(text: str, b: float, time: int = 0, **signals: list[float]) -> float:
    arrays = {k: np.asarray([v], dtype=float) for k, v in signals.items()}
    return float(stl.robustness(text, arrays, "smooth-cumulative", time=time, temperature=b)[0])


def _agm(text: str, time: int = 0, ranges: dict | None = None, **signals: list[float]) -> float:
    arrays = {k: np.asarray([v], dtype=float) for k, v in signals.items()}
    return float(stl.robustness(text, arrays, "agm", time=time, signal_ranges=ranges)[0])


# ------------------------------------------------------------------------------------------------
# AGM, hand-computed (Mehdipour et al. 2019, Definition 2)
# ------------------------------------------------------------------------------------------------

AGM_CASES = [
    # all positive: geometric branch (prod(1 + r))^(1/m) - 1
    ("G[0,2](x >= 0)", dict(x=[0.2, 0.5, 0.1]), (1.2 * 1.5 * 1.1) ** (1 / 3) - 1),
    # some negative: arithmetic mean of the negative parts
    ("G[0,2](x >= 0)", dict(x=[0.2, -0.4, -0.1]), (0 - 0.4 - 0.1) / 3),
    # F: all negative -> 1 - (prod(1 - r))^(1/m)
    ("F[0,2](x >= 0)", dict(x=[-0.2, -0.4, -0.1]), 1 - (1.2 * 1.4 * 1.1) ** (1 / 3)),
    # F: some positive -> mean of the positive parts
    ("F[0,2](x >= 0)", dict(x=[0.3, -0.4, 0.6]), (0.3 + 0.6) / 3),
    # and of two satisfied predicates
    ("x >= 0 & y >= 0", dict(x=[0.5], y=[0.3]), math.sqrt(1.5 * 1.3) - 1),
    # or of two violated predicates
    ("x >= 0 | y >= 0", dict(x=[-0.5], y=[-0.2]), 1 - math.sqrt(1.5 * 1.2)),
    # or with one satisfied: mean of positive parts over all m = 3 operands
    ("x >= 0 | y >= 0 | z >= 0", dict(x=[-0.5], y=[0.6], z=[-0.1]), 0.6 / 3),
    # or at exactly zero: 0, like classic max(0, -0.5) (the De Morgan dual of & )
    ("x >= 0 | y >= 0", dict(x=[0.0], y=[-0.5]), 0.0),
    # implies = !a | b
    ("x >= 0 -> y >= 0", dict(x=[0.4], y=[-0.2]), 1 - math.sqrt(1.4 * 1.2)),
    # not
    ("!(G[0,1](x >= 0))", dict(x=[0.2, 0.6]), -(math.sqrt(1.2 * 1.6) - 1)),
    # until, candidates t' = 0, 1, 2: -0.5; &(-0.2, 0.5) = -0.1; &(0.6, &(0.5, 0.4)) > 0 -> mean of positives
    (
        "(x >= 0) U[0,2] (y >= 0)",
        dict(x=[0.5, 0.4, -0.9], y=[-0.5, -0.2, 0.6]),
        (math.sqrt(1.6 * math.sqrt(1.5 * 1.4)) - 1) / 3,
    ),
    # until [1,2], all candidates violated: t' = 1: &(-0.3, 0.5) = -0.15; t' = 2: &(-0.6, &(0.5, -0.2)) =
    # (-0.6 - 0.1) / 2 = -0.35; | over both negative: 1 - sqrt(1.15 * 1.35)
    ("(x >= 0) U[1,2] (y >= 0)", dict(x=[0.5, -0.2, 0.3], y=[0.9, -0.3, -0.6]), 1 - math.sqrt(1.15 * 1.35)),
    # nested: F[0,1] at t = 0 and 1 is (0 + 0.4) / 2 = 0.2 each; G of [0.2, 0.2] = 0.2
    ("G[0,1](F[0,1](x >= 0))", dict(x=[-0.2, 0.4, -0.6]), 0.2),
    # nested with a violated inner window: F at t = 0: 0.3 / 2; at t = 1: 1 - sqrt(1.1 * 1.4); G mixes signs
    ("G[0,1](F[0,1](x >= 0))", dict(x=[0.3, -0.1, -0.4]), (0 + (1 - math.sqrt(1.1 * 1.4))) / 2),
    # window cut at the trace end (rtamt convention): F[0,5] at t = 1 of a 3-step trace averages 2 values
    ("F[0,5](x >= 0)", dict(x=[0.9, -0.2, -0.4]), 1 - math.sqrt(1.2 * 1.4), 1),
]


@pytest.mark.parametrize("case", AGM_CASES, ids=[f"{c[0]}@{c[3] if len(c) > 3 else 0}" for c in AGM_CASES])
def test_agm_matches_hand_computed_definition(case):
    text, signals, expected = case[:3]
    time = case[3] if len(case) > 3 else 0
    assert _agm(text, time=time, **signals) == pytest.approx(expected, abs=1e-12)


def test_agm_normalises_braking_predicate_by_signal_range_like_the_authors():
    # d >= 2 with d in [0, 15]: (d - 2) / 13 (Innes & Ramamoorthy's code); d = [15, 8.5, 4.6] -> [1, .5, .2]
    got = _agm("G[0,2](d >= 2)", ranges={"d": (0.0, 15.0)}, d=[15.0, 8.5, 4.6])
    assert got == pytest.approx((2.0 * 1.5 * 1.2) ** (1 / 3) - 1, abs=1e-12)
    assert stl.agm_scale(stl.parse("d >= 2"), {"d": (0.0, 15.0)}) == 13.0
    # the same normalisation written into the formula gives the same number
    assert _agm("G[0,2]((d - 2) / 13 >= 0)", d=[15.0, 8.5, 4.6]) == pytest.approx(got, abs=1e-15)
    # values past the declared range saturate at 1 and keep their sign
    assert _agm("d >= 2", ranges={"d": (0.0, 15.0)}, d=[40.0]) == 1.0


def test_agm_without_normalisation_rejects_values_outside_unit_interval():
    with pytest.raises(ValueError, match=r"AGM needs predicate values in \[-1, 1\].*signal_ranges"):
        _agm("G[0,2](d >= 2)", d=[15.0, 8.5, 4.6])


def test_agm_sign_equals_classic_sign_on_10000_braking_traces():
    rng = np.random.default_rng(11)
    n, T = 10_000, 100
    # gaps that wander around the 2 m crash threshold; a tenth touch it exactly (robustness exactly 0)
    d = 2.0 + rng.uniform(-0.5, 2.0, size=(n, 1)) + np.cumsum(rng.normal(0.0, 0.08, size=(n, T)), axis=1)
    d = np.clip(d, -1.0, 15.0)
    touch = rng.random(n) < 0.1
    d[touch] = np.maximum(d[touch], 2.0)
    d[touch, rng.integers(0, T, size=int(touch.sum()))] = 2.0
    spec = stl.braking_spec(T)
    classic = stl.robustness(spec, {"d": d}, "classic")
    agm = stl.robustness(spec, {"d": d}, "agm", signal_ranges=stl.BRAKING_SIGNAL_RANGES)
    assert (classic < 0).sum() > 1000 and (classic > 0).sum() > 1000 and (classic == 0).sum() > 100
    assert np.array_equal(np.sign(agm), np.sign(classic))
    assert np.all(np.abs(agm) <= 1.0)


# ------------------------------------------------------------------------------------------------
# Smooth cumulative, hand-computed (Haghighi et al. 2019, Definition 3 with smooth min/max/rectifiers)
# ------------------------------------------------------------------------------------------------

B = 2.0
x3 = [1.0, -1.0, 0.5]
y3 = [-0.5, 0.25, 1.5]
CUM_CASES = [
    # predicate: rho+ = softplus_b(h)
    ("x >= 1", dict(x=[1.5]), _sp(0.5, B)),
    # G: soft-min of rho+; exp(-b softplus_b(h)) = 1 / (1 + e^(b h))
    ("G[0,2](x >= 0)", dict(x=x3), -math.log(sum(1 / (1 + math.exp(B * v)) for v in x3)) / B),
    # F sums rho+ over the window
    ("F[0,2](x >= 0)", dict(x=x3), sum(_sp(v, B) for v in x3)),
    # not: rho+(!p) = -rho-(p) = softplus_b(-h)
    ("!(x >= 0)", dict(x=[0.7]), _sp(-0.7, B)),
    # and / or: soft min / soft max of rho+
    ("x >= 0 & y >= 0", dict(x=[1.0], y=[-0.5]), _smin([_sp(1.0, B), _sp(-0.5, B)], B)),
    ("x >= 0 | y >= 0", dict(x=[1.0], y=[-0.5]), _smax([_sp(1.0, B), _sp(-0.5, B)], B)),
    # implies = !a | b
    ("x >= 0 -> y >= 0", dict(x=[1.0], y=[-0.5]), _smax([_sp(-1.0, B), _sp(-0.5, B)], B)),
    # until [0,2]: sum over t' of softmin(rho+(y, t'), rho+(x) on [0, t'))
    (
        "(x >= 0) U[0,2] (y >= 0)",
        dict(x=x3, y=y3),
        _sp(y3[0], B)
        + _smin([_sp(y3[1], B), _sp(x3[0], B)], B)
        + _smin([_sp(y3[2], B), _sp(x3[0], B), _sp(x3[1], B)], B),
    ),
    # until [1,2]
    (
        "(x >= 0) U[1,2] (y >= 0)",
        dict(x=x3, y=y3),
        _smin([_sp(y3[1], B), _sp(x3[0], B)], B) + _smin([_sp(y3[2], B), _sp(x3[0], B), _sp(x3[1], B)], B),
    ),
    # nested: G[0,1](F[0,1]): soft-min of the two window sums
    (
        "G[0,1](F[0,1](x >= 0))",
        dict(x=x3),
        _smin([_sp(x3[0], B) + _sp(x3[1], B), _sp(x3[1], B) + _sp(x3[2], B)], B),
    ),
    # not of G: rho+(!G p) = -rho-(G p) = -softmin(-softplus_b(-x)) = softmax(softplus_b(-x))
    ("!(G[0,2](x >= 0))", dict(x=x3), _smax([_sp(-v, B) for v in x3], B)),
    # nested F inside !: rho+(!F p) = -rho-(F p) = sum softplus_b(-x)
    ("!(F[0,2](x >= 0))", dict(x=x3), sum(_sp(-v, B) for v in x3)),
    # window cut at the trace end: F[0,9] at t = 1 sums the 2 remaining steps
    ("F[0,9](x >= 0)", dict(x=x3), _sp(x3[1], B) + _sp(x3[2], B), 1),
]


@pytest.mark.parametrize("case", CUM_CASES, ids=[f"{c[0]}@{c[3] if len(c) > 3 else 0}" for c in CUM_CASES])
def test_smooth_cumulative_matches_hand_computed_definition(case):
    text, signals, expected = case[:3]
    time = case[3] if len(case) > 3 else 0
    assert _cum(text, B, time=time, **signals) == pytest.approx(expected, abs=1e-12)


def test_smooth_cumulative_default_temperature_is_50_and_approaches_classic_softmin():
    d = np.array([[5.0, 3.0, 2.5, 4.0]])
    got = stl.robustness("G[0,3](d >= 2)", {"d": d}, "smooth-cumulative")[0]
    expected = -math.log(sum(1 / (1 + math.exp(50 * (v - 2))) for v in d[0])) / 50
    assert got == pytest.approx(expected, abs=1e-12)
    assert got == pytest.approx(0.5, abs=0.02)  # close to the classic min 0.5


# ------------------------------------------------------------------------------------------------
# Independent scalar reference of the papers' definitions, compared on random formulas
# ------------------------------------------------------------------------------------------------


def _ref(f: stl.Formula, sig: dict[str, list[float]], t: int, sem: str, b: float, scales: dict) -> object:
    """Literal per-trace recursion. AGM: a float; cumulative: the pair (rho+, rho-)."""
    T = len(next(iter(sig.values())))
    if isinstance(f, stl.Predicate):
        h = f.offset + sum(c * sig[n][t] for n, c in f.coefficients.items())
        if sem == "agm":
            return max(-1.0, min(1.0, h / scales[f]))
        return (_sp(h, b), -_sp(-h, b))
    if isinstance(f, stl.Not):
        r = _ref(f.operand, sig, t, sem, b, scales)
        return -r if sem == "agm" else (-r[1], -r[0])
    if isinstance(f, (stl.And, stl.Or)):
        rs = [_ref(o, sig, t, sem, b, scales) for o in f.operands]
        return _combine(rs, isinstance(f, stl.And), sem, b)
    if isinstance(f, stl.Implies):
        return _ref(stl.Or((stl.Not(f.left), f.right)), sig, t, sem, b, scales)
    end = T - 1 if f.end is None else min(t + f.end, T - 1)
    ts = range(t + f.start, end + 1)
    if isinstance(f, stl.Always):
        rs = [_ref(f.operand, sig, s, sem, b, scales) for s in ts]
        return (1.0 if sem == "agm" else (math.inf, math.inf)) if not rs else _combine(rs, True, sem, b)
    if isinstance(f, stl.Eventually):
        rs = [_ref(f.operand, sig, s, sem, b, scales) for s in ts]
        if sem == "agm":
            return -1.0 if not rs else _combine(rs, False, sem, b)
        return (sum(r[0] for r in rs), sum(r[1] for r in rs))
    # until
    cands = []
    for s in ts:
        right = _ref(f.right, sig, s, sem, b, scales)
        left = [_ref(f.left, sig, u, sem, b, scales) for u in range(t, s)]
        if sem == "agm":
            cands.append(right if not left else _combine([right, _combine(left, True, sem, b)], True, sem, b))
        else:
            cands.append(_combine([right] + left, True, sem, b))
    if sem == "agm":
        return -1.0 if not cands else _combine(cands, False, sem, b)
    return (sum(c[0] for c in cands), sum(c[1] for c in cands))


def _combine(rs: list, conj: bool, sem: str, b: float) -> object:
    if sem == "agm":
        m = len(rs)
        if conj:
            if any(r <= 0 for r in rs):
                return sum(min(0.0, r) for r in rs) / m
            return math.prod(1 + r for r in rs) ** (1 / m) - 1
        if any(r >= 0 for r in rs):
            return sum(max(0.0, r) for r in rs) / m
        return 1 - math.prod(1 - r for r in rs) ** (1 / m)
    agg = _smin if conj else _smax
    return tuple(agg([r[i] for r in rs], b) for i in (0, 1))


from .test_stl_rtamt import _Gen, _start_reach  # noqa: E402  (the shared random formula generator)


@pytest.mark.parametrize("sem", ["agm", "smooth-cumulative"])
def test_vectorised_semantics_match_scalar_reference_on_random_formulas(sem):
    gen = _Gen(seed=99 if sem == "agm" else 98)
    rng = np.random.default_rng(5)
    b = 3.0
    for _ in range(120):
        f, _text = gen.formula(depth=int(rng.integers(1, 4)))
        T = max(2, _start_reach(f) + 1 + int(rng.integers(0, 8)))
        sig = {s: rng.uniform(-1.0, 1.0, size=(2, T)) for s in ("x", "y", "z")}  # no ties: AGM jumps at 0
        ranges = {s: (-2.0, 2.0) for s in sig}
        scales = {p: stl.agm_scale(p, ranges) for p in f.subformulas() if isinstance(p, stl.Predicate)}
        ours = stl.robustness_signal(f, sig, sem, temperature=b, signal_ranges=ranges)
        for i in range(2):
            rows = {s: v[i].tolist() for s, v in sig.items()}
            for t in range(T):
                ref = _ref(f, rows, t, sem, b, scales)
                ref = ref if sem == "agm" else ref[0]
                if math.isinf(ref):
                    assert ours[i, t] == ref, (str(f), t)
                else:
                    assert ours[i, t] == pytest.approx(ref, rel=1e-9, abs=1e-9), (str(f), i, t)


def test_agm_sign_equals_classic_sign_on_random_formulas():
    gen = _Gen(seed=123)
    rng = np.random.default_rng(6)
    for _ in range(150):
        f, _ = gen.formula(depth=int(rng.integers(1, 5)))
        T = max(2, _start_reach(f) + 1 + int(rng.integers(0, 10)))
        sig = {s: rng.integers(-4, 5, size=(4, T)) * 0.25 for s in ("x", "y", "z")}
        ranges = {s: (-1.0, 1.0) for s in sig}
        classic = stl.robustness_signal(f, sig, "classic")
        agm = stl.robustness_signal(f, sig, "agm", signal_ranges=ranges)
        assert np.array_equal(np.sign(agm), np.sign(classic)), str(f)


# ------------------------------------------------------------------------------------------------
# torch: same numbers, differentiable
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("requires_grad", [False, True], ids=["no-grad", "grad"])
@pytest.mark.parametrize("sem", list(stl.SEMANTICS))
def test_torch_inputs_give_torch_outputs_equal_to_numpy(sem, requires_grad):
    rng = np.random.default_rng(8)
    d = rng.uniform(0.0, 15.0, size=(7, 40))
    v = rng.uniform(0.0, 1.0, size=(7, 40))
    text = "G[0,30](d < 5 -> F[0,5](v <= 0.1)) & (d >= 1) U[2,9] (v > 0.5) | !(F[1,inf](d > 14))"
    kw = dict(signal_ranges={"d": (0.0, 15.0), "v": (0.0, 1.0)})
    ref = stl.robustness_signal(text, {"d": d, "v": v}, sem, **kw)
    td = torch.tensor(d, requires_grad=requires_grad)
    tv = torch.tensor(v, requires_grad=requires_grad)
    out = stl.robustness_signal(text, {"d": td, "v": tv}, sem, **kw)
    assert isinstance(out, torch.Tensor) and out.dtype == torch.float64 and out.shape == (7, 40)
    assert out.requires_grad == requires_grad
    np.testing.assert_allclose(out.detach().numpy(), ref, rtol=1e-12, atol=1e-12)
    at3 = stl.robustness(text, {"d": td, "v": tv}, sem, time=3, **kw)
    np.testing.assert_allclose(at3.detach().numpy(), ref[:, 3], rtol=1e-12, atol=1e-12)


def test_chunked_threaded_evaluation_equals_trace_by_trace():
    rng = np.random.default_rng(12)
    d = rng.uniform(0.0, 15.0, size=(2000, 200))  # several chunks of traces, evaluated on the thread pool
    v = rng.uniform(0.0, 1.0, size=(2000, 200))
    text = "G[0,150](d < 5 -> F[0,20](v <= 0.1))"
    kw = dict(signal_ranges={"d": (0.0, 15.0), "v": (0.0, 1.0)})
    for sem in stl.SEMANTICS:
        batch = stl.robustness(text, {"d": d, "v": v}, sem, **kw)
        for i in (0, 654, 655, 1311, 1999):
            one = stl.robustness(text, {"d": d[i], "v": v[i]}, sem, **kw)
            # classic is exact; sums may round differently with another batch size
            assert batch[i] == (one if sem == "classic" else pytest.approx(one, rel=1e-13, abs=1e-15))


def test_smooth_cumulative_gradient_matches_finite_differences():
    rng = np.random.default_rng(9)
    d = torch.tensor(rng.uniform(1.0, 6.0, size=(3, 25)), requires_grad=True)
    v = torch.tensor(rng.uniform(0.0, 1.0, size=(3, 25)), requires_grad=True)
    f = stl.parse("G[0,15](d < 5 -> F[0,5](v <= 0.3)) | (d >= 2) U[1,6] (v > 0.5)")
    assert torch.autograd.gradcheck(
        lambda d, v: stl.robustness(f, {"d": d, "v": v}, "smooth-cumulative", temperature=3.0), (d, v)
    )
    rho = stl.robustness("G[0,24](d >= 2)", {"d": d}, "smooth-cumulative").sum()
    rho.backward()
    assert torch.isfinite(d.grad).all() and (d.grad >= 0).all() and d.grad.sum() > 0


def test_classic_gradient_flows_to_the_minimising_step():
    d = torch.tensor([[5.0, 3.0, 2.5, 4.0]], requires_grad=True)
    stl.robustness("G[0,3](d >= 2)", {"d": d}).sum().backward()
    assert d.grad.tolist() == [[0.0, 0.0, 1.0, 0.0]]


def test_agm_windows_longer_than_1000_steps_use_log_sums_without_overflow():
    rng = np.random.default_rng(13)
    T = 1200
    pos = rng.uniform(0.5, 0.9, size=(2, T))  # prod(1 + r) over 1200 steps ~ 1e300: past float64 range
    neg = -pos
    got = stl.robustness(f"G[0,{T - 1}](x >= 0)", {"x": pos}, "agm")
    np.testing.assert_allclose(got, np.expm1(np.log1p(pos).mean(axis=1)), rtol=1e-12)
    sig = stl.robustness_signal("F[0,1100](x >= 0)", {"x": neg}, "agm")
    for t in (0, 50, 99, 150):
        window = neg[:, t : t + 1101]
        np.testing.assert_allclose(sig[:, t], -np.expm1(np.log1p(-window).mean(axis=1)), rtol=1e-12)
    # until whose window (1010 candidate steps) takes the log-sum branch
    T = 1012
    x = rng.uniform(0.2, 0.9, size=(1, T))
    y = rng.uniform(-0.9, -0.2, size=(1, T))
    f = stl.parse("(x >= 0) U[1000,1010] (y >= 0)")
    got = stl.robustness(f, {"x": x, "y": y}, "agm")
    rows = {"x": x[0].tolist(), "y": y[0].tolist()}
    scales = {p: 1.0 for p in f.subformulas() if isinstance(p, stl.Predicate)}
    assert got[0] == pytest.approx(_ref(f, rows, 0, "agm", 1.0, scales), rel=1e-10)
