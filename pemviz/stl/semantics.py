"""Batched robustness of STL formulas in three semantics: classic, AGM and smooth cumulative.

Inputs are one array per signal, float [N, T] (N traces of T steps; a single trace [T] also works), numpy or
torch; the output has the same kind, float64 (torch in: torch out; tensors that require grad are computed
with torch ops and the result is differentiable, others run through numpy zero-copy). Time is in integer
steps.

Semantics (``SEMANTICS``):

- ``"classic"`` (Donze & Maler 2010; discrete time as in rtamt's offline monitor): predicate value
  ``lhs - rhs``; ``!`` negates; ``&``/G take min, ``|``/F max; ``(a) U[s,e] (b)`` at t is the max over
  t' in [t+s, t+e] of min(b(t'), min over [t, t') of a). Agrees with rtamt 0.4.10 to 1e-9 (tests). The
  left operand must hold strictly before t' (rtamt's and LTL's discrete-time until; the spec's
  "min over j <= k" is the continuous-time form; ``(a) U (a & b)`` gives the inclusive one). All three
  semantics use this window for until.
- ``"agm"`` (Mehdipour, Vasile & Belta, ACC 2019, Def. 2): predicates scaled into [-1, 1] (see below);
  ``&`` / G over m values r_i: if some r_i <= 0, (1/m) sum min(0, r_i); else (prod (1 + r_i))^(1/m) - 1.
  ``|`` / F are the exact De Morgan duals (``|`` = ``!(!a & !b)``): if some r_i >= 0, (1/m) sum max(0, r_i);
  else 1 - (prod (1 - r_i))^(1/m). ``a -> b`` = ``!a | b``; until is the AGM ``|`` over t' of the binary AGM
  ``&`` of b(t') and the AGM ``&`` of a over [t, t') (only b(t') when that is empty). Every value has the
  sign of the classic robustness (zero included) and lies in [-1, 1].
- ``"smooth-cumulative"`` (Haghighi, Mehdipour, Bartocci & Belta 2019, arXiv 1904.11611, smooth version of
  Def. 3; the authors' ``sc_rob_pos``): the positive cumulative robustness rho+. Predicates give
  softplus_b(h) = log(1 + e^(b h)) / b (rho- gives -softplus_b(-h)); ``!`` maps rho+ to -rho- of its
  operand; ``&``/G take the soft minimum -(1/b) log sum e^(-b r), ``|`` the soft maximum; F sums over its
  window, U sums over t' of softmin(b(t'), a over [t, t')). Temperature b (``temperature``), default 50
  (the paper's run). Its sign is not the classic sign on borderline traces (Haghighi et al. 2019).

Predicate normalisation for AGM (explicit): pass ``signal_ranges={"d": (0.0, 15.0)}``; each predicate's
value h is divided by max |h| over the box of signal ranges (``d >= 2`` with d in [0, 15] -> (d - 2) / 13,
the authors' braking normalisation) and clipped to [-1, 1] (values beyond the declared ranges saturate; the
sign is kept). Without ``signal_ranges`` the predicate values are used as written, which must already lie
in [-1, 1] (write ``(d - 2) / 13 >= 0``), else a ValueError says how to normalise.

The trace end (rtamt's offline discrete-time convention): a window [t+a, t+b] is cut at the last step T-1;
G, F, U and their AGM/cumulative versions aggregate over the steps that remain (AGM divides by their
number). ``[a,inf]`` runs to the trace end. If no step remains at some evaluation time the operator is
vacuous: G is true (classic +inf, AGM +1, cumulative +inf), F and U false (classic -inf, AGM -1,
cumulative 0). An operator whose window starts past the trace end at every time it is evaluated is an
error; with ``trace_end="error"`` any window that needs steps past the end is an error.

Speed: only the time range each sub-formula needs is computed (robustness at time 0 of ``G[0,199](d >= 2)``
is one predicate pass and one min over time). Inside, arrays are time-major [L, n] so that a window shift is
a contiguous block. Sliding min/max use log-doubling (ceil(log2 w) passes), sliding sums, products and
log-sum-exps a binary decomposition of the width, classic until an associative (value, running min)
monoid; AGM and cumulative until loop over the window offsets, vectorised over traces and times. Traces
run in cache-sized chunks on a thread pool (numpy releases the GIL). ``benchmarks/stl_speed.py``: 10^4 x
200 in milliseconds, >= 1000x rtamt.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from pemviz.stl import _kernels as K
from pemviz.stl.formula import (
    Always,
    And,
    Eventually,
    Formula,
    Implies,
    Not,
    Or,
    Predicate,
    Signal,
    Until,
)
from pemviz.stl.parser import parse

try:
    import torch
except ImportError:  # pragma: no cover
    torch = None  # type: ignore[assignment]

__all__ = [
    "SEMANTICS",
    "DEFAULT_TEMPERATURE",
    "TRACE_END",
    "robustness",
    "robustness_signal",
    "agm_scale",
]

SEMANTICS = ("classic", "agm", "smooth-cumulative")
"""Names of the robustness semantics, as the sampler and the recordings take them."""

DEFAULT_TEMPERATURE = 50.0
"""Temperature b of the smooth-cumulative semantics (Innes & Ramamoorthy's paper run)."""

TRACE_END = ("truncate", "error")
"""What to do with windows that run past the last step: cut them (rtamt's convention) or raise."""

_CHUNK_ELEMENTS = 1 << 17  # values per signal per chunk: ~1 MB of float64, stays in cache
_pool: ThreadPoolExecutor | None = None


def _thread_pool() -> ThreadPoolExecutor | None:
    global _pool
    workers = min(os.cpu_count() or 1, 8)
    if workers <= 1:
        return None
    if _pool is None:
        _pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="pemviz-stl")
    return _pool


# ------------------------------------------------------------------------------------------------
# Public API
# ------------------------------------------------------------------------------------------------


def robustness(
    formula: Formula | str,
    signals: Mapping[str, Any],
    semantics: str = "classic",
    *,
    time: int = 0,
    temperature: float = DEFAULT_TEMPERATURE,
    signal_ranges: Mapping[str, tuple[float, float]] | None = None,
    trace_end: str = "truncate",
) -> Any:
    """Robustness of ``formula`` at step ``time`` for every trace: float64 [N] (``[]`` for [T] inputs).

    Args:
        formula: a :class:`~pemviz.stl.formula.Formula` or its text, e.g. ``"G[0,99](d >= 2)"``.
        signals: signal name -> values [N, T] (or [T]), numpy or torch, e.g. ``{"d": gap_m}`` in metres.
            Extra names are ignored.
        semantics: one of :data:`SEMANTICS`: ``"classic"``, ``"agm"``, ``"smooth-cumulative"``.
        time: evaluation step, 0 <= time < T.
        temperature: b of ``"smooth-cumulative"`` (> 0; larger is closer to min/max).
        signal_ranges: ``{"d": (lo, hi)}`` per signal, AGM predicate normalisation (module docstring).
        trace_end: ``"truncate"`` (rtamt's convention) or ``"error"`` (windows must fit in the trace).

    Returns:
        numpy float64 [N] for numpy inputs; torch float64 [N] for torch inputs (differentiable).

    Raises:
        ValueError: unknown semantics (lists the allowed ones), malformed text (with its column; a
            ``STLSyntaxError``), a signal the formula reads is missing, signals of different shapes, NaN in a
            signal used, ``time`` outside the trace, an interval past the trace end (with its column),
            AGM predicate values outside [-1, 1] without ``signal_ranges``, a bad temperature.
        TypeError: ``signals`` is not a mapping or holds non-numeric data.

    Source: module docstring (Donze & Maler 2010; Mehdipour et al. ACC 2019; Haghighi et al. 2019).
    """
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
    semantics: str = "classic",
    *,
    temperature: float = DEFAULT_TEMPERATURE,
    signal_ranges: Mapping[str, tuple[float, float]] | None = None,
    trace_end: str = "truncate",
) -> Any:
    """Robustness of ``formula`` at every step: float64 [N, T] (``[T]`` for [T] inputs).

    Column t is :func:`robustness` at ``time=t``; near the trace end windows are cut (module docstring), so
    with ``trace_end="error"`` only formulas without temporal operators pass. Arguments, return kinds and
    errors as in :func:`robustness`.
    """
    job = _Job(formula, signals, semantics, temperature, signal_ranges, trace_end)
    out = job.run(0, job.T - 1)
    return job.finish(out[0] if job.single else out)


def agm_scale(predicate: Predicate, signal_ranges: Mapping[str, tuple[float, float]]) -> float:
    """AGM normalisation of a predicate: max |h| of its value h over the box of signal ranges.

    ``agm_scale(parse("d >= 2"), {"d": (0, 15)}) == 13``: AGM uses (d - 2) / 13 (Innes & Ramamoorthy's code).

    Raises:
        ValueError: a signal of the predicate has no range, a range is not finite with lo < hi, or the
            predicate is 0 over the whole box.
    """
    hmin = hmax = predicate.offset
    for name, c in predicate.coefficients.items():
        if name not in signal_ranges:
            raise ValueError(f"signal_ranges has no range for signal {name!r} of predicate '{predicate}'"
                             f"{_col(predicate)}; given: {sorted(signal_ranges)}")
        lo, hi = _range(name, signal_ranges[name])
        hmin += min(c * lo, c * hi)
        hmax += max(c * lo, c * hi)
    scale = max(abs(hmin), abs(hmax))
    if not scale > 0.0:
        raise ValueError(f"predicate '{predicate}'{_col(predicate)} is 0 over the whole signal range box")
    return float(scale)


# ------------------------------------------------------------------------------------------------
# Preparation and validation
# ------------------------------------------------------------------------------------------------


def _col(node: Any) -> str:
    pos = getattr(node, "pos", None)
    return "" if pos is None else f" (column {pos + 1})"


def _range(name: str, r: Any) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in r)
    except (TypeError, ValueError):
        raise ValueError(f"signal_ranges[{name!r}] must be a pair (lo, hi) of numbers, got {r!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"signal_ranges[{name!r}] = {r!r} must be finite with lo < hi")
    return lo, hi


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
    return torch is not None and isinstance(x, torch.Tensor)


class _Job:
    """Validated inputs for one robustness call."""

    def __init__(
        self,
        formula: Formula | str,
        signals: Mapping[str, Any],
        semantics: str,
        temperature: float,
        signal_ranges: Mapping[str, tuple[float, float]] | None,
        trace_end: str,
    ) -> None:
        if isinstance(formula, str):
            formula = parse(formula)
        if not isinstance(formula, Formula):
            raise TypeError(f"formula must be an STL Formula or its text, got {type(formula).__name__}")
        if semantics not in SEMANTICS:
            raise ValueError(f"unknown robustness semantics {semantics!r}; allowed: "
                             + ", ".join(repr(s) for s in SEMANTICS))
        if trace_end not in TRACE_END:
            raise ValueError(f"unknown trace_end {trace_end!r}; allowed: " + ", ".join(repr(s) for s in TRACE_END))
        if semantics == "smooth-cumulative":
            try:
                temperature = float(temperature)
            except (TypeError, ValueError):
                raise ValueError(f"temperature must be a positive number, got {temperature!r}") from None
            if not (math.isfinite(temperature) and temperature > 0):
                raise ValueError(f"temperature must be finite and > 0, got {temperature!r}")
        if not isinstance(signals, Mapping):
            raise TypeError(f"signals must be a mapping name -> array [N, T], got {type(signals).__name__}")
        self.formula = formula
        self.semantics = semantics
        self.temperature = float(temperature)
        self.trace_end = trace_end

        positions = _signal_positions(formula)
        missing = [n for n in positions if n not in signals]
        if missing:
            name = missing[0]
            where = "" if positions[name] is None else f" at column {positions[name] + 1}"
            raise ValueError(f"the formula reads signal {name!r}{where} but signals has only "
                             f"{sorted(signals)}; names are case-sensitive")
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
                raise ValueError(f"signals must all have the same shape [N, T]: {names[0]!r} is "
                                 f"{list(shape)}, {n!r} is {list(a.shape)}")
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

        self.scales: dict[int, float] | None = None
        if semantics == "agm" and signal_ranges is not None:
            if not isinstance(signal_ranges, Mapping):
                raise TypeError("signal_ranges must be a mapping name -> (lo, hi)")
            self.scales = {id(p): agm_scale(p, signal_ranges)
                           for p in formula.subformulas() if isinstance(p, Predicate)}

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
                raise ValueError(f"signal {n!r} contains NaN (trace {i}, step {t}); robustness needs finite "
                                 "or infinite values")
        raise ValueError("robustness is NaN: a predicate met inf - inf (infinite signal values of opposite "
                         "effect); use finite signal values")


# ------------------------------------------------------------------------------------------------
# Evaluation: eval(node, lo, hi) -> [hi - lo + 1, n] values at steps lo..hi (0 <= lo <= hi <= T - 1).
# Time-major: a window shift is a contiguous block of rows, so every pass is one flat vectorised loop.
# ------------------------------------------------------------------------------------------------

_INF = math.inf


class _Evaluator:
    def __init__(self, job: _Job, data: dict[str, Any]) -> None:
        self.job = job
        self.ops = job.ops
        self.data = data  # name -> [n, T] (trace-major views of the caller's arrays)
        self.T = job.T
        self.n = int(next(iter(data.values())).shape[0])
        self.sem = job.semantics
        self.b = job.temperature

    def col(self, values: np.ndarray, like: Any) -> Any:
        """A per-step constant [L] as a column [L, 1] that broadcasts over traces."""
        return self.ops.const(np.asarray(values, dtype=np.float64)[:, None], like)

    # -- dispatch --------------------------------------------------------------------------------
    # pol: +1 computes rho (cumulative: rho+), -1 the negative cumulative robustness rho- (only differs
    # for "smooth-cumulative"; ``!`` swaps them, Haghighi et al. Def. 3).
    def eval(self, f: Formula, lo: int, hi: int, pol: int) -> Any:
        if isinstance(f, Predicate):
            return self.predicate(f, lo, hi, pol, 1.0)
        if isinstance(f, Not):
            return self.negated(f.operand, lo, hi, pol)
        if isinstance(f, And):
            return self.conj([self.eval(o, lo, hi, pol) for o in f.operands])
        if isinstance(f, Or):
            return self.disj([self.eval(o, lo, hi, pol) for o in f.operands])
        if isinstance(f, Implies):
            return self.disj([self.negated(f.left, lo, hi, pol), self.eval(f.right, lo, hi, pol)])
        if isinstance(f, (Always, Eventually)):
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
        """sign * rho(p): classic h, AGM h / scale, cumulative pol * softplus_b(pol * h)."""
        ops = self.ops
        if self.sem == "classic":
            return self._affine(p, lo, hi, sign, time_major)
        if self.sem == "agm":
            scales = self.job.scales
            if scales is not None:
                # h first, then the scale: h / scale keeps the exact sign (and zeros) of classic's h
                return ops.clip(self._affine(p, lo, hi, sign, time_major) / scales[id(p)], -1.0, 1.0)
            h = self._affine(p, lo, hi, sign, time_major)
            worst = float(abs(h).max()) if h.shape[0] * h.shape[1] else 0.0
            if worst > 1.0 + 1e-12:
                raise ValueError(
                    f"AGM needs predicate values in [-1, 1], but '{p}'{_col(p)} reaches {worst:.6g}: pass "
                    "signal_ranges={name: (lo, hi)} (each predicate is divided by its largest |value| over the "
                    "ranges, e.g. {'d': (0.0, 15.0)} gives (d - 2) / 13 for d >= 2), or write the scale into "
                    "the formula, e.g. '(d - 2) / 13 >= 0'")
            return h
        # smooth cumulative: rho+ = softplus_b(h), rho- = -softplus_b(-h); sign * pol * softplus_b(pol * h)
        sp = ops.softplus(self._affine(p, lo, hi, float(pol), time_major), self.b)
        return sp if sign * pol > 0 else -sp

    # -- boolean connectives -----------------------------------------------------------------------
    def conj(self, xs: list[Any]) -> Any:
        ops = self.ops
        if self.sem == "classic":
            out = xs[0]
            for x in xs[1:]:
                out = ops.minimum(out, x)
            return out
        if self.sem == "agm":
            return self._agm_pointwise(xs, dual=False)
        b = self.b
        acc = xs[0] * -b
        for x in xs[1:]:
            acc = ops.logaddexp(acc, x * -b)
        return acc / -b

    def disj(self, xs: list[Any]) -> Any:
        ops = self.ops
        if self.sem == "classic":
            out = xs[0]
            for x in xs[1:]:
                out = ops.maximum(out, x)
            return out
        if self.sem == "agm":
            return self._agm_pointwise(xs, dual=True)
        b = self.b
        acc = xs[0] * b
        for x in xs[1:]:
            acc = ops.logaddexp(acc, x * b)
        return acc / b

    # -- AGM (Mehdipour et al. 2019): conjunction and its De Morgan dual -------------------------
    def _agm_finish(self, ext: Any, s: Any, log_p: Any, m: Any, dual: bool) -> Any:
        """AGM & (dual: |) from ext = min (max) of the values, s = sum of min(r, 0) (max(r, 0)),
        log_p = log prod(1 + max(r, 0)) (log prod(1 - min(r, 0))) and their number m.

        Mathematically s <= ext (>= for the dual) and the geometric branch lies between ext and the max, so
        clamping to ext only removes rounding and keeps the sign exactly that of classic (ext)."""
        ops = self.ops
        if not dual:
            geo = ops.maximum(ops.expm1(log_p / m), ext)
            return ops.where(ext <= 0, ops.minimum(s, ext) / m, geo)
        geo = ops.minimum(-ops.expm1(log_p / m), ext)
        return ops.where(ext >= 0, ops.maximum(s, ext) / m, geo)

    def _agm_pointwise(self, xs: list[Any], dual: bool) -> Any:
        ops = self.ops
        pick = ops.maximum if dual else ops.minimum
        part = ops.pos if dual else ops.neg
        ext, s, p = xs[0], part(xs[0]), 1.0 + (ops.pos(xs[0]) if not dual else -ops.neg(xs[0]))
        for x in xs[1:]:
            ext = pick(ext, x)
            s = s + part(x)
            p = p * (1.0 + (ops.pos(x) if not dual else -ops.neg(x)))
        return self._agm_finish(ext, s, ops.log(p), float(len(xs)), dual)

    def _agm_window(self, r: Any, n_out: int, w: int, dual: bool, axis: int = 0) -> Any:
        """AGM G (dual: F) over windows [i, i + w - 1] of r [L, n] (cut at L); vacuous +1 (-1) if empty.

        With n_out == 1 the whole of r is the window, reduced along ``axis`` (1: r is trace-major [n, L])."""
        ops = self.ops
        L = r.shape[axis]
        part = ops.pos(r) if dual else ops.neg(r)
        fac = 1.0 - ops.neg(r) if dual else 1.0 + ops.pos(r)  # in [1, 2]: a product of <= 1000 fits
        if n_out == 1:
            ext = (ops.amax(r, axis) if dual else ops.amin(r, axis))[None, :]
            s = ops.sum(part, axis)[None, :]
            if L <= 1000:
                log_p = ops.log(ops.prod(fac, axis))[None, :]
            else:
                log_p = ops.sum(ops.log(fac), axis)[None, :]
            return self._agm_finish(ext, s, log_p, float(L), dual)
        length = n_out + w - 1
        ext = K.sliding_idempotent(ops, K.pad_right(ops, r, length, -_INF if dual else _INF), w, n_out,
                                   ops.maximum if dual else ops.minimum)
        (s,) = K.sliding_monoid((K.pad_right(ops, part, length, 0.0),), w, n_out, lambda a, b: (a[0] + b[0],))
        if w <= 1000:
            (p,) = K.sliding_monoid((K.pad_right(ops, fac, length, 1.0),), w, n_out, lambda a, b: (a[0] * b[0],))
            log_p = ops.log(p)
        else:
            (log_p,) = K.sliding_monoid((K.pad_right(ops, ops.log(fac), length, 0.0),), w, n_out,
                                        lambda a, b: (a[0] + b[0],))
        m_np = np.clip(L - np.arange(n_out), 0, w).astype(np.float64)
        out = self._agm_finish(ext, s, log_p, self.col(np.maximum(m_np, 1.0), r), dual)
        if (m_np == 0).any():
            out = ops.where(self.col(m_np == 0, r) > 0, ops.zeros_like(out) + (-1.0 if dual else 1.0), out)
        return out

    # -- windows ---------------------------------------------------------------------------------
    def window(self, f: Any, lo: int, hi: int) -> tuple[int, int]:
        """(a, b_eff): the interval with its end cut at the trace end for evaluation from step ``lo``."""
        a, b, T = f.start, f.end, self.T
        name = {Always: "G", Eventually: "F", Until: "U"}[type(f)]
        shown = f"[{a},{'inf' if b is None else b}]"
        if lo + a > T - 1:
            raise ValueError(
                f"the interval {shown} of {name}{_col(f)} lies past the end of the trace: evaluated from step "
                f"{lo}, its window starts at step {lo + a}, but the trace has T = {T} steps (0..{T - 1})")
        if self.job.trace_end == "error":
            last = hi + (a if b is None else b)
            if last > T - 1:
                raise ValueError(
                    f"the interval {shown} of {name}{_col(f)} needs step {last} (evaluated at steps {lo}..{hi}) "
                    f"but the trace has T = {T} steps (0..{T - 1}); shorten the interval or use "
                    "trace_end='truncate'")
        b_eff = T - 1 - lo if b is None else min(b, T - 1 - lo)
        return a, b_eff

    def unary_temporal(self, f: Always | Eventually, lo: int, hi: int, pol: int) -> Any:
        ops, T = self.ops, self.T
        a, be = self.window(f, lo, hi)
        clo, chi = lo + a, min(hi + be, T - 1)
        n_out, w = hi - lo + 1, be - a + 1
        is_g = isinstance(f, Always)
        op = f.operand
        ax = 0
        if n_out == 1 and isinstance(op, Predicate):  # one reduction over time: skip the time-major copy
            child, ax = self.predicate(op, clo, chi, pol, 1.0, time_major=False), 1
        elif n_out == 1 and isinstance(op, Not) and isinstance(op.operand, Predicate):
            child, ax = self.predicate(op.operand, clo, chi, -pol, -1.0, time_major=False), 1
        else:
            child = self.eval(op, clo, chi, pol)
        if self.sem == "classic":
            if n_out == 1:
                return (ops.amin(child, ax) if is_g else ops.amax(child, ax))[None, :]
            x = K.pad_right(ops, child, n_out + w - 1, _INF if is_g else -_INF)
            return K.sliding_idempotent(ops, x, w, n_out, ops.minimum if is_g else ops.maximum)
        if self.sem == "agm":
            return self._agm_window(child, n_out, w, dual=not is_g, axis=ax)
        # smooth cumulative: G soft-min, F sum
        b = self.b
        if is_g:
            y = child * -b
            if n_out == 1:
                return (ops.logsumexp(y, ax) / -b)[None, :]
            y = K.pad_right(ops, y, n_out + w - 1, -_INF)
            (lse,) = K.sliding_monoid((y,), w, n_out, lambda p, q: (ops.logaddexp(p[0], q[0]),))
            return lse / -b
        if n_out == 1:
            return ops.sum(child, ax)[None, :]
        x = K.pad_right(ops, child, n_out + w - 1, 0.0)
        (s,) = K.sliding_monoid((x,), w, n_out, lambda p, q: (p[0] + q[0],))
        return s

    # -- until -----------------------------------------------------------------------------------
    def until(self, f: Until, lo: int, hi: int, pol: int) -> Any:
        T = self.T
        a, be = self.window(f, lo, hi)
        n_out = hi - lo + 1
        r2 = self.eval(f.right, lo + a, min(hi + be, T - 1), pol)
        if be == 0:  # U[0,0]: the right operand now
            return r2
        l1 = self.eval(f.left, lo, min(hi + be - 1, T - 1), pol)
        if self.sem == "classic":
            return self._until_classic(l1, r2, a, be, n_out)
        if self.sem == "agm":
            return self._until_agm(l1, r2, a, be, lo, n_out)
        return self._until_cumulative(l1, r2, a, be, lo, n_out)

    def _until_classic(self, l1: Any, r2: Any, a: int, be: int, n_out: int) -> Any:
        ops = self.ops
        if n_out == 1:
            # exclusive running min of the left operand: P[k] = min l1[0..k-1], P[0] = +inf
            P = ops.concat([ops.full((1, l1.shape[1]), _INF, l1), ops.cummin(l1, 0)], axis=0)
            k_hi = a + r2.shape[0]
            return ops.amax(ops.minimum(r2, P[a:k_hi]), 0)[None, :]
        # U[a,b](t) = min(min of left over [t, t+a), V(t+a)), V(s) = U[0,b-a](s): an associative scan of
        # (value, running min of left) pairs over each window
        c = be - a
        length = n_out + c
        r2p = K.pad_right(ops, r2, length, -_INF)
        l1p = K.pad_right(ops, l1[a:], length, _INF)

        def combine(p: tuple, q: tuple) -> tuple:
            # segment p then q: (max over t' of min(right(t'), left on [start, t')), min of left on the segment)
            return ops.maximum(p[0], ops.minimum(p[1], q[0])), ops.minimum(p[1], q[1])

        V, _ = K.sliding_monoid((r2p, l1p), c + 1, n_out, combine)
        if a == 0:
            return V
        pre = K.sliding_idempotent(ops, K.pad_right(ops, l1, n_out + a - 1, _INF), a, n_out, ops.minimum)
        return ops.minimum(pre, V)

    def _valid(self, lo: int, n_out: int, k: int) -> np.ndarray:
        return np.arange(n_out) + k <= self.T - 1 - lo

    def _until_agm(self, l1: Any, r2: Any, a: int, be: int, lo: int, n_out: int) -> Any:
        """AGM | over t' = t + k of AGM &(right(t'), AGM & of left over [t, t')); a loop over the offsets k,
        each step vectorised over traces x times."""
        ops = self.ops
        length = n_out + be
        mn1 = K.pad_right(ops, l1, length, _INF)
        neg1 = K.pad_right(ops, ops.neg(l1), length, 0.0)
        fac1 = K.pad_right(ops, 1.0 + ops.pos(l1), length, 1.0)
        r2p = K.pad_right(ops, r2, n_out + be - a, 0.0)
        zero = ops.full((n_out, l1.shape[1]), 0.0, l1)
        use_log = be + 1 > 1000  # products of > 1000 factors in [1, 2] could overflow: sum logs instead
        p_min, p_neg, p_fac = zero + _INF, zero, (zero if use_log else zero + 1.0)  # left on [t, t + k)
        o_max, o_pos, o_fac = zero - _INF, zero, (zero if use_log else zero + 1.0)  # | over candidates
        m_np = np.zeros(n_out)
        for k in range(be + 1):
            if k >= a:
                valid_np = self._valid(lo, n_out, k)
                if not valid_np.any():
                    break
                m_np += valid_np
                x = r2p[k - a : k - a + n_out]
                if k == 0:
                    term = x
                else:
                    pre = self._agm_finish(p_min, p_neg, p_fac if use_log else ops.log(p_fac), float(k), False)
                    term = self._agm_pointwise([x, pre], dual=False)
                fac = 1.0 - ops.neg(term)
                if not valid_np.all():  # candidates past the trace end do not count
                    valid = self.col(valid_np, l1) > 0
                    term = ops.where(valid, term, zero - _INF)
                    fac = ops.where(valid, fac, zero + 1.0)
                o_max = ops.maximum(o_max, term)
                o_pos = o_pos + ops.pos(term)
                o_fac = o_fac + ops.log(fac) if use_log else o_fac * fac
            if k < be:
                p_min = ops.minimum(p_min, mn1[k : k + n_out])
                p_neg = p_neg + neg1[k : k + n_out]
                p_fac = p_fac + ops.log(fac1[k : k + n_out]) if use_log else p_fac * fac1[k : k + n_out]
        m = self.col(np.maximum(m_np, 1.0), l1)
        out = self._agm_finish(o_max, o_pos, o_fac if use_log else ops.log(o_fac), m, True)
        if (m_np == 0).any():
            out = ops.where(self.col(m_np == 0, l1) > 0, zero - 1.0, out)
        return out

    def _until_cumulative(self, l1: Any, r2: Any, a: int, be: int, lo: int, n_out: int) -> Any:
        """Sum over t' = t + k of softmin(right(t'), left over [t, t')): a loop over the offsets k."""
        ops, b = self.ops, self.b
        y1 = K.pad_right(ops, l1 * -b, n_out + be, 0.0)
        y2 = K.pad_right(ops, r2 * -b, n_out + be - a, 0.0)
        zero = ops.full((n_out, l1.shape[1]), 0.0, l1)
        run = zero - _INF  # log sum exp(-b left) over [t, t + k)
        total = zero
        for k in range(be + 1):
            if k >= a:
                valid_np = self._valid(lo, n_out, k)
                if not valid_np.any():
                    break
                term = ops.logaddexp(y2[k - a : k - a + n_out], run) / -b
                total = total + (term if valid_np.all() else ops.where(self.col(valid_np, l1) > 0, term, zero))
            if k < be:
                run = ops.logaddexp(run, y1[k : k + n_out])
        return total


def first_violation(formula: Formula | str, signals: Mapping[str, Any], level: float = 0.0) -> np.ndarray:
    """The step at which a safety formula ``G[a,b](operand)`` with a time-free operand is first violated.

    Returns int [N] (``[]`` for [T] inputs): the first step t in [a, b] at which the operand's classic
    robustness is < 0 (or <= ``level`` when ``level`` > 0: the formula's robustness is then <= ``level`` whatever
    comes after), and T where there is none. Only the actions before that step can change whether a rollout
    violates the formula, so importance weights and NLLs stop there.

    Raises:
        ValueError: if the formula is not ``G[a,b](operand)`` with an operand of horizon 0.
    """
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
