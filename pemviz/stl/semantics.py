"""The robustness semantics of STL as objects: :class:`Classic`, :class:`AGM`, :class:`SmoothCumulative`.

One :class:`Semantics` object is chosen at the API boundary (:func:`semantics_from_name`, or passed to
:func:`pemviz.stl.robustness`) and handed to every operator of the formula walk (:mod:`pemviz.stl.evaluate`). Values
are float64 arrays, time-major [L, n], in the predicates' units (classic: the signals', e.g. metres; AGM: unitless
in [-1, 1]; smooth cumulative: signal units x steps).

- :class:`Classic` (Donze & Maler 2010; discrete time as rtamt's offline monitor, agreeing with rtamt 0.4.10 to
  1e-9): predicate ``lhs - rhs``; ``&``/G min, ``|``/F max; ``(a) U[s,e] (b)`` at t is the max over t' in [t+s, t+e]
  of min(b(t'), min over [t, t') of a) (the left operand holds strictly before t', for all three semantics).
- :class:`AGM` (Mehdipour, Vasile & Belta, "Arithmetic-geometric mean robustness for control from signal temporal
  logic specifications", ACC 2019, Def. 2): ``&``/G over m values: (1/m) sum min(0, r_i) if some r_i <= 0, else
  (prod (1 + r_i))^(1/m) - 1; ``|``/F their De Morgan duals. Signs agree with classic; predicates are divided by
  :func:`agm_scale` over ``signal_ranges`` and clipped to [-1, 1] (without ranges they must already lie there).
- :class:`SmoothCumulative` (Haghighi, Mehdipour, Bartocci & Belta 2019, arXiv 1904.11611, smooth Def. 3; used by
  Innes & Ramamoorthy 2022): rho+ with softplus predicates, soft min/max of temperature b (default 50), F and U
  summed over their windows.

Empty windows are vacuous: G true (classic +inf, AGM +1, cumulative +inf), F and U false (-inf, -1, 0)."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from pemviz.stl import _kernels as K
from pemviz.stl.formula import Formula, Predicate

__all__ = [
    "SEMANTICS",
    "DEFAULT_TEMPERATURE",
    "Semantics",
    "Classic",
    "AGM",
    "SmoothCumulative",
    "semantics_from_name",
    "agm_scale",
]

DEFAULT_TEMPERATURE = 50.0
"""Temperature b of the smooth-cumulative semantics (Innes & Ramamoorthy's paper run)."""

_INF = math.inf

Array = Any  # float64 np.ndarray | torch.Tensor, time-major [L, n]
Ops = Any  # pemviz.stl._kernels.NumpyOps | TorchOps


def _col(node: Any) -> str:
    pos = getattr(node, "pos", None)
    return "" if pos is None else f" (column {pos + 1})"


def column(ops: Ops, values: np.ndarray, like: Array) -> Array:
    """A per-step constant [L] as a column [L, 1] that broadcasts over the n traces of ``like`` [L, n]."""
    return ops.const(np.asarray(values, dtype=np.float64)[:, None], like)


def _valid(room: int, n_out: int, k: int) -> np.ndarray:
    """bool [n_out]: whether output step i has its candidate i + k inside the trace (``room`` steps left)."""
    return np.arange(n_out) + k <= room


class Semantics(ABC):
    """A robustness semantics of STL: how each operator turns its operands' robustness into its own.

    Every method gets ``ops`` (the array backend, numpy or torch, chosen per call from the inputs) and
    float64 arrays, time-major [L, n] (L steps, n traces), and returns a new array. Until and the window
    reductions receive their operands already cut at the trace end (see :mod:`pemviz.stl.evaluate`).

    ``pol`` is the polarity of the evaluation: +1 for rho (cumulative: rho+), -1 for the negative cumulative
    robustness rho- under an odd number of ``!`` (Haghighi et al. 2019, Def. 3); only
    :class:`SmoothCumulative` tells them apart."""

    name: str = ""
    """The name the sampler and the recordings use, one of :data:`SEMANTICS`."""

    def prepare(self, formula: Formula) -> Semantics:
        """The semantics ready to evaluate ``formula`` (AGM: every predicate's scale); raises ValueError when
        the formula does not fit (AGM: a predicate signal without a range)."""
        return self

    @abstractmethod
    def predicate(self, ops: Ops, p: Predicate, value: Callable[[float], Array], sign: float, pol: int) -> Array:
        """``sign`` * robustness of predicate ``p``; ``value(c)`` is c * (its affine value h), a fresh array."""

    @abstractmethod
    def conj(self, ops: Ops, xs: list[Array]) -> Array:
        """``x_1 & x_2 & ...`` of equally shaped arrays, pointwise."""

    @abstractmethod
    def disj(self, ops: Ops, xs: list[Array]) -> Array:
        """``x_1 | x_2 | ...`` of equally shaped arrays, pointwise."""

    @abstractmethod
    def window(self, ops: Ops, r: Array, n_out: int, w: int, conjunctive: bool, axis: int = 0) -> Array:
        """G (``conjunctive``) or F over the windows [i, i + w - 1] of r [L, n], for i < n_out: [n_out, n].

        Windows are cut at row L (the trace end); an empty one is vacuous. With n_out == 1 the whole of r
        is the window, reduced along ``axis`` (1: r is trace-major [n, L]); the result is then [1, n]."""

    @abstractmethod
    def until(self, ops: Ops, left: Array, right: Array, a: int, be: int, n_out: int, room: int) -> Array:
        """``(left) U[a,be] (right)`` at n_out consecutive steps t: [n_out, n], for be >= 1.

        ``left`` [>= n_out + be - 1 rows] holds the left operand from the first t on, ``right`` the right
        operand from the first t + a on (both cut at the trace end); ``room`` = T - 1 - (first t) is the
        number of steps after the first t inside the trace."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


class Classic(Semantics):
    """Classic (space) robustness: Donze & Maler, "Robust satisfaction of temporal logic over real-valued
    signals", FORMATS 2010, in rtamt's discrete time. Values in the predicates' units."""

    name = "classic"

    def predicate(self, ops: Ops, p: Predicate, value: Callable[[float], Array], sign: float, pol: int) -> Array:
        return value(sign)

    def conj(self, ops: Ops, xs: list[Array]) -> Array:
        out = xs[0]
        for x in xs[1:]:
            out = ops.minimum(out, x)
        return out

    def disj(self, ops: Ops, xs: list[Array]) -> Array:
        out = xs[0]
        for x in xs[1:]:
            out = ops.maximum(out, x)
        return out

    def window(self, ops: Ops, r: Array, n_out: int, w: int, conjunctive: bool, axis: int = 0) -> Array:
        if n_out == 1:
            return (ops.amin(r, axis) if conjunctive else ops.amax(r, axis))[None, :]
        x = K.pad_right(ops, r, n_out + w - 1, _INF if conjunctive else -_INF)
        return K.sliding_idempotent(ops, x, w, n_out, ops.minimum if conjunctive else ops.maximum)

    def until(self, ops: Ops, left: Array, right: Array, a: int, be: int, n_out: int, room: int) -> Array:
        if n_out == 1:
            # exclusive running min of the left operand: P[k] = min left[0..k-1], P[0] = +inf
            P = ops.concat([ops.full((1, left.shape[1]), _INF, left), ops.cummin(left, 0)], axis=0)
            k_hi = a + right.shape[0]
            return ops.amax(ops.minimum(right, P[a:k_hi]), 0)[None, :]
        # U[a,b](t) = min(min of left over [t, t+a), V(t+a)), V(s) = U[0,b-a](s): an associative scan of
        # (value, running min of left) pairs over each window
        c = be - a
        length = n_out + c
        r2p = K.pad_right(ops, right, length, -_INF)
        l1p = K.pad_right(ops, left[a:], length, _INF)

        def combine(p: tuple, q: tuple) -> tuple:
            # segment p then q: (max over t' of min(right(t'), left on [start, t')), min of left on the segment)
            return ops.maximum(p[0], ops.minimum(p[1], q[0])), ops.minimum(p[1], q[1])

        V, _ = K.sliding_monoid((r2p, l1p), c + 1, n_out, combine)
        if a == 0:
            return V
        pre = K.sliding_idempotent(ops, K.pad_right(ops, left, n_out + a - 1, _INF), a, n_out, ops.minimum)
        return ops.minimum(pre, V)


class AGM(Semantics):
    """Arithmetic-geometric mean robustness: Mehdipour, Vasile & Belta, "Arithmetic-geometric mean robustness
    for control from signal temporal logic specifications", ACC 2019, Def. 2. Values unitless in [-1, 1].

    Args:
        signal_ranges: ``{"d": (lo, hi)}`` per signal (its units): each predicate is divided by
            :func:`agm_scale` and clipped to [-1, 1]; None: predicates must already lie in [-1, 1].
    Raises:
        TypeError: ``signal_ranges`` is not a mapping."""

    name = "agm"

    def __init__(self, signal_ranges: Mapping[str, tuple[float, float]] | None = None) -> None:
        if signal_ranges is not None and not isinstance(signal_ranges, Mapping):
            raise TypeError("signal_ranges must be a mapping name -> (lo, hi)")
        self.signal_ranges = signal_ranges
        self._scales: dict[int, float] = {}  # id(predicate) -> scale, for the formula of prepare()
        self._formula: Formula | None = None  # keeps those ids alive

    def prepare(self, formula: Formula) -> Semantics:
        if self.signal_ranges is None:
            return self
        bound = AGM(self.signal_ranges)
        bound._scales = {
            id(p): agm_scale(p, self.signal_ranges) for p in formula.subformulas() if isinstance(p, Predicate)
        }
        bound._formula = formula
        return bound

    def __repr__(self) -> str:
        return f"AGM(signal_ranges={self.signal_ranges!r})"

    def predicate(self, ops: Ops, p: Predicate, value: Callable[[float], Array], sign: float, pol: int) -> Array:
        if self.signal_ranges is not None:
            scale = self._scales.get(id(p))
            if scale is None:  # a predicate outside the prepared formula
                scale = agm_scale(p, self.signal_ranges)
            # h first, then the scale: h / scale keeps the exact sign (and zeros) of classic's h
            return ops.clip(value(sign) / scale, -1.0, 1.0)
        h = value(sign)
        worst = float(abs(h).max()) if h.shape[0] * h.shape[1] else 0.0
        if worst > 1.0 + 1e-12:
            raise ValueError(
                f"AGM needs predicate values in [-1, 1], but '{p}'{_col(p)} reaches {worst:.6g}: pass "
                "signal_ranges={name: (lo, hi)} (each predicate is divided by its largest |value| over the "
                "ranges, e.g. {'d': (0.0, 15.0)} gives (d - 2) / 13 for d >= 2), or write the scale into "
                "the formula, e.g. '(d - 2) / 13 >= 0'"
            )
        return h

    def conj(self, ops: Ops, xs: list[Array]) -> Array:
        return self._pointwise(ops, xs, dual=False)

    def disj(self, ops: Ops, xs: list[Array]) -> Array:
        return self._pointwise(ops, xs, dual=True)

    @staticmethod
    def _finish(ops: Ops, ext: Array, s: Array, log_p: Array, m: Any, dual: bool) -> Array:
        """AGM & (dual: |) from ext = min (max) of the values, s = sum of min(r, 0) (max(r, 0)),
        log_p = log prod(1 + max(r, 0)) (log prod(1 - min(r, 0))) and their number m.

        Mathematically s <= ext (>= for the dual) and the geometric branch lies between ext and the max, so
        clamping to ext only removes rounding and keeps the sign exactly that of classic (ext)."""
        if not dual:
            geo = ops.maximum(ops.expm1(log_p / m), ext)
            return ops.where(ext <= 0, ops.minimum(s, ext) / m, geo)
        geo = ops.minimum(-ops.expm1(log_p / m), ext)
        return ops.where(ext >= 0, ops.maximum(s, ext) / m, geo)

    def _pointwise(self, ops: Ops, xs: list[Array], dual: bool) -> Array:
        pick = ops.maximum if dual else ops.minimum
        part = ops.pos if dual else ops.neg
        ext, s, p = xs[0], part(xs[0]), 1.0 + (ops.pos(xs[0]) if not dual else -ops.neg(xs[0]))
        for x in xs[1:]:
            ext = pick(ext, x)
            s = s + part(x)
            p = p * (1.0 + (ops.pos(x) if not dual else -ops.neg(x)))
        return self._finish(ops, ext, s, ops.log(p), float(len(xs)), dual)

    def window(self, ops: Ops, r: Array, n_out: int, w: int, conjunctive: bool, axis: int = 0) -> Array:
        dual = not conjunctive
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
            return self._finish(ops, ext, s, log_p, float(L), dual)
        length = n_out + w - 1
        ext = K.sliding_idempotent(
            ops, K.pad_right(ops, r, length, -_INF if dual else _INF), w, n_out, ops.maximum if dual else ops.minimum
        )
        (s,) = K.sliding_monoid((K.pad_right(ops, part, length, 0.0),), w, n_out, lambda a, b: (a[0] + b[0],))
        if w <= 1000:
            (p,) = K.sliding_monoid((K.pad_right(ops, fac, length, 1.0),), w, n_out, lambda a, b: (a[0] * b[0],))
            log_p = ops.log(p)
        else:
            (log_p,) = K.sliding_monoid(
                (K.pad_right(ops, ops.log(fac), length, 0.0),), w, n_out, lambda a, b: (a[0] + b[0],)
            )
        m_np = np.clip(L - np.arange(n_out), 0, w).astype(np.float64)
        out = self._finish(ops, ext, s, log_p, column(ops, np.maximum(m_np, 1.0), r), dual)
        if (m_np == 0).any():
            out = ops.where(column(ops, m_np == 0, r) > 0, ops.zeros_like(out) + (-1.0 if dual else 1.0), out)
        return out

    def until(self, ops: Ops, left: Array, right: Array, a: int, be: int, n_out: int, room: int) -> Array:
        """AGM | over t' = t + k of AGM &(right(t'), AGM & of left over [t, t')); a loop over the offsets k,
        each step vectorised over traces x times."""
        length = n_out + be
        mn1 = K.pad_right(ops, left, length, _INF)
        neg1 = K.pad_right(ops, ops.neg(left), length, 0.0)
        fac1 = K.pad_right(ops, 1.0 + ops.pos(left), length, 1.0)
        r2p = K.pad_right(ops, right, n_out + be - a, 0.0)
        zero = ops.full((n_out, left.shape[1]), 0.0, left)
        use_log = be + 1 > 1000  # products of > 1000 factors in [1, 2] could overflow: sum logs instead
        p_min, p_neg, p_fac = zero + _INF, zero, (zero if use_log else zero + 1.0)  # left on [t, t + k)
        o_max, o_pos, o_fac = zero - _INF, zero, (zero if use_log else zero + 1.0)  # | over candidates
        m_np = np.zeros(n_out)
        for k in range(be + 1):
            if k >= a:
                valid_np = _valid(room, n_out, k)
                if not valid_np.any():
                    break
                m_np += valid_np
                x = r2p[k - a : k - a + n_out]
                if k == 0:
                    term = x
                else:
                    pre = self._finish(ops, p_min, p_neg, p_fac if use_log else ops.log(p_fac), float(k), False)
                    term = self._pointwise(ops, [x, pre], dual=False)
                fac = 1.0 - ops.neg(term)
                if not valid_np.all():  # candidates past the trace end do not count
                    valid = column(ops, valid_np, left) > 0
                    term = ops.where(valid, term, zero - _INF)
                    fac = ops.where(valid, fac, zero + 1.0)
                o_max = ops.maximum(o_max, term)
                o_pos = o_pos + ops.pos(term)
                o_fac = o_fac + ops.log(fac) if use_log else o_fac * fac
            if k < be:
                p_min = ops.minimum(p_min, mn1[k : k + n_out])
                p_neg = p_neg + neg1[k : k + n_out]
                p_fac = p_fac + ops.log(fac1[k : k + n_out]) if use_log else p_fac * fac1[k : k + n_out]
        m = column(ops, np.maximum(m_np, 1.0), left)
        out = self._finish(ops, o_max, o_pos, o_fac if use_log else ops.log(o_fac), m, True)
        if (m_np == 0).any():
            out = ops.where(column(ops, m_np == 0, left) > 0, zero - 1.0, out)
        return out


class SmoothCumulative(Semantics):
    """Smooth positive cumulative robustness rho+: Haghighi, Mehdipour, Bartocci & Belta, "Control from signal
    temporal logic specifications with smooth cumulative quantitative semantics", CDC 2019 (arXiv
    1904.11611), smooth version of Def. 3, as in the authors' ``sc_rob_pos`` and Innes & Ramamoorthy 2022.

    Args:
        temperature: b of the softplus and the soft min/max, finite and > 0 (larger is closer to min/max).
    Raises:
        ValueError: ``temperature`` is not a finite number > 0."""

    name = "smooth-cumulative"

    def __init__(self, temperature: float = DEFAULT_TEMPERATURE) -> None:
        try:
            temperature = float(temperature)
        except (TypeError, ValueError):
            raise ValueError(f"temperature must be a positive number, got {temperature!r}") from None
        if not (math.isfinite(temperature) and temperature > 0):
            raise ValueError(f"temperature must be finite and > 0, got {temperature!r}")
        self.temperature = temperature

    def __repr__(self) -> str:
        return f"SmoothCumulative(temperature={self.temperature!r})"

    def predicate(self, ops: Ops, p: Predicate, value: Callable[[float], Array], sign: float, pol: int) -> Array:
        # rho+ = softplus_b(h), rho- = -softplus_b(-h): sign * pol * softplus_b(pol * h)
        sp = ops.softplus(value(float(pol)), self.temperature)
        return sp if sign * pol > 0 else -sp

    def conj(self, ops: Ops, xs: list[Array]) -> Array:
        return self._soft_extreme(ops, xs, -self.temperature)

    def disj(self, ops: Ops, xs: list[Array]) -> Array:
        return self._soft_extreme(ops, xs, self.temperature)

    @staticmethod
    def _soft_extreme(ops: Ops, xs: list[Array], b: float) -> Array:
        """(1/b) log sum e^(b x): the soft max for b > 0, the soft min for b < 0."""
        acc = xs[0] * b
        for x in xs[1:]:
            acc = ops.logaddexp(acc, x * b)
        return acc / b

    def window(self, ops: Ops, r: Array, n_out: int, w: int, conjunctive: bool, axis: int = 0) -> Array:
        # G: soft minimum over the window; F: sum over the window
        b = self.temperature
        if conjunctive:
            y = r * -b
            if n_out == 1:
                return (ops.logsumexp(y, axis) / -b)[None, :]
            y = K.pad_right(ops, y, n_out + w - 1, -_INF)
            (lse,) = K.sliding_monoid((y,), w, n_out, lambda p, q: (ops.logaddexp(p[0], q[0]),))
            return lse / -b
        if n_out == 1:
            return ops.sum(r, axis)[None, :]
        x = K.pad_right(ops, r, n_out + w - 1, 0.0)
        (s,) = K.sliding_monoid((x,), w, n_out, lambda p, q: (p[0] + q[0],))
        return s

    def until(self, ops: Ops, left: Array, right: Array, a: int, be: int, n_out: int, room: int) -> Array:
        """Sum over t' = t + k of softmin(right(t'), left over [t, t')): a loop over the offsets k."""
        b = self.temperature
        y1 = K.pad_right(ops, left * -b, n_out + be, 0.0)
        y2 = K.pad_right(ops, right * -b, n_out + be - a, 0.0)
        zero = ops.full((n_out, left.shape[1]), 0.0, left)
        run = zero - _INF  # log sum exp(-b left) over [t, t + k)
        total = zero
        for k in range(be + 1):
            if k >= a:
                valid_np = _valid(room, n_out, k)
                if not valid_np.any():
                    break
                term = ops.logaddexp(y2[k - a : k - a + n_out], run) / -b
                total = total + (term if valid_np.all() else ops.where(column(ops, valid_np, left) > 0, term, zero))
            if k < be:
                run = ops.logaddexp(run, y1[k : k + n_out])
        return total


_BY_NAME = {cls.name: cls for cls in (Classic, AGM, SmoothCumulative)}

SEMANTICS = tuple(_BY_NAME)
"""Names of the robustness semantics, as the sampler and the recordings take them:
``("classic", "agm", "smooth-cumulative")``."""


def semantics_from_name(
    name: str,
    *,
    temperature: float = DEFAULT_TEMPERATURE,
    signal_ranges: Mapping[str, tuple[float, float]] | None = None,
) -> Semantics:
    """The semantics object for a metric name: ``"classic"``, ``"agm"`` or ``"smooth-cumulative"``.

    ``temperature`` goes to :class:`SmoothCumulative`, ``signal_ranges`` to :class:`AGM`; the others ignore
    them.

    Raises:
        ValueError: unknown name (lists the allowed ones); a bad temperature for ``"smooth-cumulative"``.
        TypeError: ``signal_ranges`` is not a mapping, for ``"agm"``."""
    if name not in _BY_NAME:
        raise ValueError(f"unknown robustness semantics {name!r}; allowed: " + ", ".join(repr(s) for s in SEMANTICS))
    if name == AGM.name:
        return AGM(signal_ranges)
    if name == SmoothCumulative.name:
        return SmoothCumulative(temperature)
    return Classic()


def _range(name: str, r: Any) -> tuple[float, float]:
    try:
        lo, hi = (float(v) for v in r)
    except (TypeError, ValueError):
        raise ValueError(f"signal_ranges[{name!r}] must be a pair (lo, hi) of numbers, got {r!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ValueError(f"signal_ranges[{name!r}] = {r!r} must be finite with lo < hi")
    return lo, hi


def agm_scale(predicate: Predicate, signal_ranges: Mapping[str, tuple[float, float]]) -> float:
    """AGM normalisation of a predicate: max |h| of its value h over the box of signal ranges (its units).

    ``agm_scale(parse("d >= 2"), {"d": (0, 15)}) == 13``: AGM uses (d - 2) / 13 (Innes & Ramamoorthy's code,
    after Mehdipour et al. 2019).

    Raises:
        ValueError: a signal of the predicate has no range, a range is not finite with lo < hi, or the
            predicate is 0 over the whole box."""
    hmin = hmax = predicate.offset
    for name, c in predicate.coefficients.items():
        if name not in signal_ranges:
            raise ValueError(
                f"signal_ranges has no range for signal {name!r} of predicate '{predicate}'"
                f"{_col(predicate)}; given: {sorted(signal_ranges)}"
            )
        lo, hi = _range(name, signal_ranges[name])
        hmin += min(c * lo, c * hi)
        hmax += max(c * lo, c * hi)
    scale = max(abs(hmin), abs(hmax))
    if not scale > 0.0:
        raise ValueError(f"predicate '{predicate}'{_col(predicate)} is 0 over the whole signal range box")
    return float(scale)
