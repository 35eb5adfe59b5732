"""Batched evaluation of STL robustness: the entry points :func:`robustness`, :func:`robustness_signal` and
:func:`first_violation`, input validation, and the walk over the formula.

Inputs are one array per signal, float [N, T] (or one trace [T]), numpy or torch; the output is float64 of the same
kind (torch tensors that require grad give a differentiable result). Time is in integer steps. The semantics
(:mod:`pemviz.stl.semantics`) is one object handed to every operator.

The trace end (rtamt's offline discrete-time convention): a window is cut at step T-1 and aggregates over the steps
that remain; ``[a,inf]`` runs to the end; with no step left the operator is vacuous (G true, F and U false). A
window that starts past the end at every evaluated time is an error; with ``trace_end="error"`` so is any window
that needs steps past the end.

Only the time range each sub-formula needs is computed, on time-major [L, n] arrays: sliding min/max by
log-doubling, sums, products and log-sum-exps by a binary decomposition of the width, classic until by an
associative monoid; traces run in cache-sized chunks on a thread pool (``benchmarks/stl_speed.py``)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from pemviz.stl import _kernels as K
from pemviz.stl._kernels import torch
from pemviz.stl.expr import Signal
from pemviz.stl.formula import Always, And, Formula, Implies, Not, Or, Predicate, Temporal, UnaryTemporal, Until
from pemviz.stl.parser import parse
from pemviz.stl.semantics import DEFAULT_TEMPERATURE, SEMANTICS, Semantics, _col, semantics_from_name

if TYPE_CHECKING:
    from concurrent.futures import ThreadPoolExecutor

__all__ = ["TRACE_END", "robustness", "robustness_signal", "first_violation"]

TRACE_END = ("truncate", "error")
"""What to do with windows that run past the last step: cut them (rtamt's convention) or raise."""

_CHUNK_ELEMENTS = 1 << 17  # values per signal per chunk: ~1 MB of float64, stays in cache
_pool: ThreadPoolExecutor | None = None


def _thread_pool() -> ThreadPoolExecutor | None:
    """The pool that evaluates a long batch's chunks side by side (None on one CPU); made, and
    :mod:`concurrent.futures` (with :mod:`logging`, about 10 ms) imported, when a batch first needs it."""
    global _pool
    workers = min(os.cpu_count() or 1, 8)
    if workers <= 1:
        return None
    if _pool is None:
        from concurrent.futures import ThreadPoolExecutor

        _pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="pemviz-stl")
    return _pool


# ------------------------------------------------------------------------------------------------
# Public API
# ------------------------------------------------------------------------------------------------


def robustness(
    formula: Formula | str,
    signals: Mapping[str, Any],
    semantics: str | Semantics = "classic",
    *,
    time: int = 0,
    temperature: float = DEFAULT_TEMPERATURE,
    signal_ranges: Mapping[str, tuple[float, float]] | None = None,
    trace_end: str = "truncate",
) -> Any:
    """Robustness of ``formula`` at step ``time`` for every trace: float64 [N] (``[]`` for [T] inputs).

    Source: :mod:`pemviz.stl.semantics` (Donze & Maler 2010; Mehdipour, Vasile & Belta, ACC 2019; Haghighi,
    Mehdipour, Bartocci & Belta 2019).

    Args:
        formula: a :class:`~pemviz.stl.formula.Formula` or its text, e.g. ``"G[0,99](d >= 2)"``.
        signals: signal name -> values [N, T] (or [T]), numpy or torch, e.g. ``{"d": gap_m}`` in metres; extra names
            are ignored.
        semantics: a name from :data:`~pemviz.stl.semantics.SEMANTICS` or a :class:`~pemviz.stl.semantics.Semantics`
            object, which carries its own temperature / signal ranges.
        time: evaluation step, 0 <= time < T.
        temperature: b of ``"smooth-cumulative"`` (> 0; larger is closer to min/max).
        signal_ranges: ``{"d": (lo, hi)}`` per signal, AGM predicate normalisation.
        trace_end: ``"truncate"`` (rtamt's convention) or ``"error"`` (windows must fit in the trace).
    Returns:
        numpy float64 [N] for numpy inputs; torch float64 [N] for torch inputs (differentiable).
    Raises:
        ValueError: unknown semantics, malformed text (an ``STLSyntaxError`` with its column), a missing signal,
            signals of different shapes, NaN in a signal used, ``time`` outside the trace, an interval past the
            trace end, AGM predicate values outside [-1, 1] without ``signal_ranges``, a bad temperature, or
            ``temperature`` / ``signal_ranges`` besides a semantics object.
        TypeError: ``signals`` (or ``signal_ranges``) is not a mapping, or a signal holds non-numeric data."""
    job = _Job(formula, signals, semantics, temperature, signal_ranges, trace_end)
    if isinstance(time, bool) or not isinstance(time, (int, np.integer)):
        raise TypeError(f"time must be an int step, got {time!r}")
    if not 0 <= int(time) < job.T:
        raise ValueError(f"time={time} is outside the trace: 0 <= time < T = {job.T}")
    out = job.run(int(time), int(time))[:, 0]
    return job.finish(out[0] if job.single else out)


def robustness_signal(
    formula: Formula | str,
    signals: Mapping[str, Any],
    semantics: str | Semantics = "classic",
    *,
    temperature: float = DEFAULT_TEMPERATURE,
    signal_ranges: Mapping[str, tuple[float, float]] | None = None,
    trace_end: str = "truncate",
) -> Any:
    """Robustness of ``formula`` at every step: float64 [N, T] (``[T]`` for [T] inputs); column t is
    :func:`robustness` at ``time=t``, windows cut at the trace end (so ``trace_end="error"`` passes only formulas
    without temporal operators)."""
    job = _Job(formula, signals, semantics, temperature, signal_ranges, trace_end)
    out = job.run(0, job.T - 1)
    return job.finish(out[0] if job.single else out)


# ------------------------------------------------------------------------------------------------
# Preparation and validation
# ------------------------------------------------------------------------------------------------


def _signal_positions(formula: Formula) -> dict[str, int | None]:
    """First column at which each signal is read."""
    out: dict[str, int | None] = {}

    def walk_expr(e: Any) -> None:
        if isinstance(e, Signal):
            if out.get(e.name) is None:
                out[e.name] = e.pos
            return
        for attr in ("left", "right", "operand"):
            sub = getattr(e, attr, None)
            if sub is not None:
                walk_expr(sub)

    for f in formula.subformulas():
        if isinstance(f, Predicate):
            walk_expr(f.lhs)
            walk_expr(f.rhs)
    return out


def _is_torch(x: Any) -> bool:
    return K.is_tensor(x)


class _Job:
    """Validated inputs for one robustness call."""

    def __init__(
        self,
        formula: Formula | str,
        signals: Mapping[str, Any],
        semantics: str | Semantics,
        temperature: float,
        signal_ranges: Mapping[str, tuple[float, float]] | None,
        trace_end: str,
    ) -> None:
        if isinstance(formula, str):
            formula = parse(formula)
        if not isinstance(formula, Formula):
            raise TypeError(f"formula must be an STL Formula or its text, got {type(formula).__name__}")
        if not isinstance(semantics, Semantics) and semantics not in SEMANTICS:
            semantics_from_name(semantics)  # raises: unknown name, with the allowed ones
        if trace_end not in TRACE_END:
            raise ValueError(f"unknown trace_end {trace_end!r}; allowed: " + ", ".join(repr(s) for s in TRACE_END))
        if not isinstance(semantics, Semantics):  # a name
            semantics = semantics_from_name(semantics, temperature=temperature, signal_ranges=signal_ranges)
        elif signal_ranges is not None or temperature != DEFAULT_TEMPERATURE:
            raise ValueError(
                f"got the semantics object {semantics!r} and temperature / signal_ranges as well: "
                "give them to the object (AGM(signal_ranges), SmoothCumulative(temperature)) or "
                "name the semantics by its string"
            )
        if not isinstance(signals, Mapping):
            raise TypeError(f"signals must be a mapping name -> array [N, T], got {type(signals).__name__}")
        self.formula = formula
        self.trace_end = trace_end

        positions = _signal_positions(formula)
        missing = [n for n in positions if n not in signals]
        if missing:
            name = missing[0]
            pos = positions[name]
            where = "" if pos is None else f" at column {pos + 1}"
            raise ValueError(
                f"the formula reads signal {name!r}{where} but signals has only "
                f"{sorted(signals)}; names are case-sensitive"
            )
        names = sorted(positions)
        use_torch = any(_is_torch(signals[n]) for n in names)
        self.ops: Any = K.TorchOps if use_torch else K.NumpyOps
        arrays: dict[str, Any] = {}
        shape = None
        for n in names:
            arrays[n] = a = self._convert(n, signals[n], use_torch)
            if shape is None:
                shape = tuple(a.shape)
            elif tuple(a.shape) != shape:
                raise ValueError(
                    f"signals must all have the same shape [N, T]: {names[0]!r} is "
                    f"{list(shape)}, {n!r} is {list(a.shape)}"
                )
        assert shape is not None
        if len(shape) not in (1, 2):
            raise ValueError(f"signal arrays must be [N, T] (or one trace [T]), got shape {list(shape)}")
        # torch inputs without gradients on the CPU run through numpy (zero-copy both ways): the same numbers,
        # and steadier timings than torch's intra-op threads on a busy machine
        self.torch_out = use_torch and all(a.device.type == "cpu" and not a.requires_grad for a in arrays.values())
        if self.torch_out:
            arrays = {n: a.detach().numpy() for n, a in arrays.items()}
            self.ops = K.NumpyOps
        self.single = len(shape) == 1
        if self.single:
            arrays = {n: a[None, :] for n, a in arrays.items()}
        self.N, self.T = int(arrays[names[0]].shape[0]), int(arrays[names[0]].shape[1])
        if self.T < 1:
            raise ValueError("signals have no time steps (T = 0)")
        self.arrays = arrays
        self.semantics: Semantics = semantics.prepare(formula)

    def finish(self, out: Any) -> Any:
        """The result in the callers' kind: torch for torch inputs."""
        if self.torch_out:
            return torch.from_numpy(np.asarray(out))
        return out

    @staticmethod
    def _convert(name: str, x: Any, use_torch: bool) -> Any:
        try:
            if use_torch:
                t = x if _is_torch(x) else torch.as_tensor(np.asarray(x, dtype=np.float64))
                if t.dtype.is_complex or t.dtype == torch.bool:
                    raise TypeError
                return t.to(torch.float64)
            a = np.asarray(x)
            if a.dtype.kind not in "fiu":
                raise TypeError
            return a.astype(np.float64, copy=False)
        except (TypeError, ValueError):
            raise TypeError(f"signal {name!r} must be a real numeric array [N, T], got {type(x).__name__}") from None

    def run(self, lo: int, hi: int) -> Any:
        """Robustness at steps lo..hi: [N, hi - lo + 1]. Chunks of traces, time-major inside (see _Evaluator)."""
        ops = self.ops
        chunk = max(1, _CHUNK_ELEMENTS // self.T)
        starts = list(range(0, max(self.N, 1), chunk))

        def one(s: int) -> Any:
            data = {n: a[s : s + chunk] for n, a in self.arrays.items()}
            return _Evaluator(self, data).eval(self.formula, lo, hi, 1).T  # [L, n] -> [n, L]

        pool = _thread_pool() if (ops is K.NumpyOps and len(starts) > 1) else None
        parts = list(pool.map(one, starts)) if pool is not None else [one(s) for s in starts]
        out = ops.concat(parts, axis=0) if len(parts) > 1 else ops.contiguous(parts[0])
        if ops.isnan_any(out):
            self._explain_nan(out)
        return out

    def _explain_nan(self, out: Any) -> None:
        for n, a in self.arrays.items():
            bad = np.argwhere(np.isnan(a.detach().cpu().numpy() if _is_torch(a) else a))
            if len(bad):
                i, t = (int(v) for v in bad[0])
                raise ValueError(
                    f"signal {n!r} contains NaN (trace {i}, step {t}); robustness needs finite " "or infinite values"
                )
        raise ValueError(
            "robustness is NaN: a predicate met inf - inf (infinite signal values of opposite "
            "effect); use finite signal values"
        )


# ------------------------------------------------------------------------------------------------
# Evaluation: eval(node, lo, hi) -> [hi - lo + 1, n] values at steps lo..hi (0 <= lo <= hi <= T - 1).
# Time-major: a window shift is a contiguous block of rows, so every pass is one flat vectorised loop.
# ------------------------------------------------------------------------------------------------


class _Evaluator:
    """The walk over the formula for one chunk of traces; every operator's arithmetic is the semantics'."""

    def __init__(self, job: _Job, data: dict[str, Any]) -> None:
        self.job = job
        self.ops = job.ops
        self.data = data  # name -> [n, T] (trace-major views of the caller's arrays)
        self.T = job.T
        self.sem = job.semantics

    # -- dispatch --------------------------------------------------------------------------------
    # pol: +1 computes rho (cumulative: rho+), -1 the negative cumulative robustness rho- (only differs
    # for smooth cumulative; ``!`` swaps them, Haghighi et al. 2019 Def. 3).
    def eval(self, f: Formula, lo: int, hi: int, pol: int) -> Any:
        if isinstance(f, Predicate):
            return self.predicate(f, lo, hi, pol, 1.0)
        if isinstance(f, Not):
            return self.negated(f.operand, lo, hi, pol)
        if isinstance(f, And):
            return self.sem.conj(self.ops, [self.eval(o, lo, hi, pol) for o in f.operands])
        if isinstance(f, Or):
            return self.sem.disj(self.ops, [self.eval(o, lo, hi, pol) for o in f.operands])
        if isinstance(f, Implies):
            return self.sem.disj(self.ops, [self.negated(f.left, lo, hi, pol), self.eval(f.right, lo, hi, pol)])
        if isinstance(f, UnaryTemporal):
            return self.unary_temporal(f, lo, hi, pol)
        if isinstance(f, Until):
            return self.until(f, lo, hi, pol)
        raise TypeError(f"not an STL formula node: {type(f).__name__}")

    def negated(self, f: Formula, lo: int, hi: int, pol: int) -> Any:
        """Robustness of ``!f``: minus that of f with the opposite polarity (folded into predicates)."""
        if isinstance(f, Predicate):
            return self.predicate(f, lo, hi, -pol, -1.0)
        return -self.eval(f, lo, hi, -pol)

    # -- predicates ------------------------------------------------------------------------------
    def _affine(self, p: Predicate, lo: int, hi: int, factor: float, time_major: bool) -> Any:
        """factor * (sum_i c_i x_i + k) at steps lo..hi: a fresh array, time-major [hi - lo + 1, n] (or
        trace-major [n, hi - lo + 1] for a reduction over time right away).

        Negating (factor -1) is exact, so signs and zeros match the unnegated value."""
        k = p.offset * factor
        h = None
        affine = self.ops.affine_t if time_major else self.ops.affine
        for name, c in p.coefficients.items():
            term = affine(self.data[name][:, lo : hi + 1], c * factor, k if h is None else 0.0)
            h = term if h is None else h + term
        return h

    def predicate(self, p: Predicate, lo: int, hi: int, pol: int, sign: float, time_major: bool = True) -> Any:
        """sign * rho(p) at steps lo..hi in the semantics (classic h, AGM h / scale, cumulative softplus)."""
        return self.sem.predicate(self.ops, p, lambda factor: self._affine(p, lo, hi, factor, time_major), sign, pol)

    # -- windows ---------------------------------------------------------------------------------
    def window(self, f: Temporal, lo: int, hi: int) -> tuple[int, int]:
        """(a, b_eff): the interval with its end cut at the trace end for evaluation from step ``lo``."""
        a, b, T = f.start, f.end, self.T
        name, shown = f.symbol, f.interval
        if lo + a > T - 1:
            raise ValueError(
                f"the interval {shown} of {name}{_col(f)} lies past the end of the trace: evaluated from step "
                f"{lo}, its window starts at step {lo + a}, but the trace has T = {T} steps (0..{T - 1})"
            )
        if self.job.trace_end == "error":
            last = hi + (a if b is None else b)
            if last > T - 1:
                raise ValueError(
                    f"the interval {shown} of {name}{_col(f)} needs step {last} (evaluated at steps {lo}..{hi}) "
                    f"but the trace has T = {T} steps (0..{T - 1}); shorten the interval or use "
                    "trace_end='truncate'"
                )
        b_eff = T - 1 - lo if b is None else min(b, T - 1 - lo)
        return a, b_eff

    def unary_temporal(self, f: UnaryTemporal, lo: int, hi: int, pol: int) -> Any:
        """G or F at steps lo..hi: the operand over the steps the windows need, then the semantics' reduction."""
        a, be = self.window(f, lo, hi)
        clo, chi = lo + a, min(hi + be, self.T - 1)
        n_out, w = hi - lo + 1, be - a + 1
        op = f.operand
        ax = 0
        if n_out == 1 and isinstance(op, Predicate):  # one reduction over time: skip the time-major copy
            child, ax = self.predicate(op, clo, chi, pol, 1.0, time_major=False), 1
        elif n_out == 1 and isinstance(op, Not) and isinstance(op.operand, Predicate):
            child, ax = self.predicate(op.operand, clo, chi, -pol, -1.0, time_major=False), 1
        else:
            child = self.eval(op, clo, chi, pol)
        return self.sem.window(self.ops, child, n_out, w, f.conjunctive, ax)

    # -- until -----------------------------------------------------------------------------------
    def until(self, f: Until, lo: int, hi: int, pol: int) -> Any:
        T = self.T
        a, be = self.window(f, lo, hi)
        r2 = self.eval(f.right, lo + a, min(hi + be, T - 1), pol)
        if be == 0:  # U[0,0]: the right operand now
            return r2
        l1 = self.eval(f.left, lo, min(hi + be - 1, T - 1), pol)
        return self.sem.until(self.ops, l1, r2, a, be, hi - lo + 1, T - 1 - lo)


def first_violation(formula: Formula | str, signals: Mapping[str, Any], level: float = 0.0) -> np.ndarray:
    """The step at which a safety formula ``G[a,b](operand)`` with a time-free operand is first violated: int [N]
    (``[]`` for [T] inputs), the first t in [a, b] with the operand's classic robustness < 0 (or <= ``level`` > 0),
    else T; importance weights and NLLs stop there.

    Raises:
        ValueError: if the formula is not ``G[a,b](operand)`` with an operand of horizon 0."""
    f = parse(formula) if isinstance(formula, str) else formula
    if not isinstance(f, Always) or f.operand.horizon() != 0:
        raise ValueError(f"a failure step needs a safety formula G[a,b](state predicate), got {f}")
    rho = np.asarray(robustness_signal(f.operand, signals, "classic"), dtype=np.float64)
    single = rho.ndim == 1
    rho = np.atleast_2d(rho)
    n_steps = rho.shape[1]
    end = n_steps - 1 if f.end is None else min(f.end, n_steps - 1)
    bad = rho <= level if level > 0.0 else rho < 0.0
    bad[:, : f.start] = False
    bad[:, end + 1 :] = False
    steps = np.where(bad.any(axis=1), bad.argmax(axis=1), n_steps)
    return steps[0] if single else steps
