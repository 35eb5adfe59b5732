"""Classic robustness against rtamt's offline discrete-time monitor (the test oracle), issue 5 acceptance 1."""

from __future__ import annotations

import numpy as np
import pytest
from pemviz import stl

try:
    import rtamt
except ImportError:  # a test-only dependency (pyproject [test] extra)
    rtamt = None

needs_rtamt = pytest.mark.skipif(rtamt is None, reason="rtamt (the classic-semantics oracle) is not installed")

SIGNALS = ("x", "y", "z")


class _Gen:
    """Random formulas (depth <= 4, every operator, bounded intervals) as (pemviz Formula, rtamt text)."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def number(self) -> float:
        return float(self.rng.choice([-2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 1.5, 2.0, 0.25, -1.25]))

    def predicate(self) -> tuple[stl.Formula, str]:
        rng = self.rng
        op = str(rng.choice([">=", ">", "<=", "<"]))
        c = self.number()
        a, b = (str(s) for s in rng.choice(SIGNALS, size=2, replace=False))
        form = int(rng.integers(3))
        if form == 0:
            lhs, text = stl.signal(a), a
        elif form == 1:
            lhs, text = stl.signal(a) - stl.signal(b), f"{a} - {b}"
        else:
            k = float(rng.choice([2.0, 0.5, 3.0]))
            lhs, text = k * stl.signal(a) + stl.signal(b), f"{k}*{a} + {b}"
        return stl.Predicate(lhs, op, stl.const(c)), f"{text} {op} {c}"

    def interval(self) -> tuple[int, int]:
        a = int(self.rng.integers(0, 4))
        return a, a + int(self.rng.integers(0, 6))

    def formula(self, depth: int) -> tuple[stl.Formula, str]:
        rng = self.rng
        if depth == 0 or rng.random() < 0.15:
            return self.predicate()
        kind = str(rng.choice(["not", "and", "or", "implies", "G", "F", "U", "G", "F", "U"]))
        if kind == "not":
            f, t = self.formula(depth - 1)
            return stl.Not(f), f"not({t})"
        if kind in ("and", "or"):
            n = int(rng.integers(2, 4))
            subs = [self.formula(depth - 1) for _ in range(n)]
            text = f"({subs[0][1]})"
            for _, t in subs[1:]:
                text = f"({text}) {kind} ({t})"
            cls = stl.And if kind == "and" else stl.Or
            return cls(tuple(f for f, _ in subs)), text
        if kind == "implies":
            (f1, t1), (f2, t2) = self.formula(depth - 1), self.formula(depth - 1)
            return stl.Implies(f1, f2), f"({t1}) -> ({t2})"
        a, b = self.interval()
        if kind in ("G", "F"):
            f, t = self.formula(depth - 1)
            word = "always" if kind == "G" else "eventually"
            cls = stl.Always if kind == "G" else stl.Eventually
            return cls(f, a, b), f"{word}[{a}:{b}]({t})"
        (f1, t1), (f2, t2) = self.formula(depth - 1), self.formula(depth - 1)
        return stl.Until(f1, f2, a, b), f"({t1}) until[{a}:{b}] ({t2})"


def _start_reach(f: stl.Formula) -> int:
    """Largest sum of interval starts along a path: the trace must be longer for every window to start in it."""
    own = getattr(f, "start", 0)
    return own + max((_start_reach(c) for c in f.children), default=0)


def _rtamt_signal(text: str, traces: dict[str, np.ndarray]) -> np.ndarray:
    spec = rtamt.StlDiscreteTimeOfflineSpecification()
    for s in SIGNALS:
        spec.declare_var(s, "float")
    spec.spec = text
    spec.parse()
    n, T = traces[SIGNALS[0]].shape
    out = np.empty((n, T))
    for i in range(n):
        data = {"time": list(range(T))}
        data.update({s: traces[s][i].tolist() for s in SIGNALS})
        out[i] = [v for _, v in spec.evaluate(data)]
    return out


def _assert_same(ours: np.ndarray, oracle: np.ndarray, context: str) -> float:
    inf = np.isinf(oracle)
    assert np.array_equal(np.isinf(ours), inf), context
    assert np.array_equal(ours[inf], oracle[inf]), context
    diff = float(np.max(np.abs(ours[~inf] - oracle[~inf]), initial=0.0))
    assert diff <= 1e-9, f"{context}: max abs diff {diff}"
    return diff


@needs_rtamt
def test_classic_matches_rtamt_on_500_random_formulas_at_every_step():
    gen = _Gen(seed=20240905)
    rng = np.random.default_rng(7)
    worst, ops_seen, n_formulas = 0.0, set(), 0
    while n_formulas < 520:
        f, text = gen.formula(depth=int(rng.integers(1, 5)))
        assert stl.parse(str(f)) == f
        T = max(2, _start_reach(f) + 1 + int(rng.integers(0, 14)))  # rtamt fails on T = 1
        grid = rng.random() < 0.4  # small grid values produce ties and exact zeros
        traces = {
            s: (rng.integers(-4, 5, size=(3, T)) * 0.5 if grid else rng.normal(0.0, 2.0, size=(3, T))) for s in SIGNALS
        }
        oracle = _rtamt_signal(text, traces)
        ours = stl.robustness_signal(f, traces, "classic")
        worst = max(worst, _assert_same(ours, oracle, f"{f} (rtamt: {text}), T={T}"))
        at0 = stl.robustness(f, traces, "classic")
        _assert_same(at0, oracle[:, 0], f"{f} at time 0")
        t = int(rng.integers(0, T))
        if t + _start_reach(f) <= T - 1:
            _assert_same(stl.robustness(f, traces, "classic", time=t), oracle[:, t], f"{f} at time {t}")
        ops_seen |= {type(g).__name__ for g in f.subformulas()}
        n_formulas += 1
    assert ops_seen == {"Predicate", "Not", "And", "Or", "Implies", "Always", "Eventually", "Until"}
    assert worst <= 1e-9


@needs_rtamt
def test_classic_matches_rtamt_on_the_benchmark_formulas():
    rng = np.random.default_rng(3)
    d = rng.uniform(0.0, 15.0, size=(8, 200))
    v = rng.uniform(0.0, 1.0, size=(8, 200))
    for text, ours_text in [
        ("always[0:199](d >= 2)", "G[0,199](d >= 2)"),
        ("always[0:150]((d < 5) -> eventually[0:20](v <= 0.1))", "G[0,150](d < 5 -> F[0,20](v <= 0.1))"),
        ("(d >= 3) until[5:60] (v <= 0.05)", "(d >= 3) U[5,60] (v <= 0.05)"),
    ]:
        spec = rtamt.StlDiscreteTimeOfflineSpecification()
        spec.declare_var("d", "float")
        spec.declare_var("v", "float")
        spec.spec = text
        spec.parse()
        oracle = np.array(
            [
                [r for _, r in spec.evaluate({"time": list(range(200)), "d": d[i].tolist(), "v": v[i].tolist()})]
                for i in range(8)
            ]
        )
        _assert_same(stl.robustness_signal(ours_text, {"d": d, "v": v}), oracle, text)
        _assert_same(stl.robustness(ours_text, {"d": d, "v": v}), oracle[:, 0], text)
