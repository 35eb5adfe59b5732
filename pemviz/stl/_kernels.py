"""Batched sliding-window kernels over the time axis (axis 0 of time-major [L, n] arrays), numpy or torch.

No Python loop runs over traces; loops run over log2(window) doubling levels or, for the until of AGM and
smooth-cumulative, over the window offsets (each step vectorised over traces x output times)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np


class _Torch:
    """torch, imported at its first use (about 1 s): numpy inputs never import it."""

    def __getattr__(self, name: str) -> Any:
        import torch as module

        return getattr(module, name)


torch: Any = _Torch()


def is_tensor(x: Any) -> bool:
    """Whether ``x`` is a torch tensor (never imports torch: without it imported, nothing is one)."""
    module = sys.modules.get("torch")
    return module is not None and isinstance(x, module.Tensor)


Array = Any  # np.ndarray | torch.Tensor


def _same(name: str) -> Any:
    """A classmethod calling ``xp.<name>`` with the arguments it is given."""
    return classmethod(lambda cls, *args: getattr(cls.xp, name)(*args))


def _along(name: str) -> Any:
    """A classmethod reducing ``x`` with ``xp.<name>(x, axis=axis)``."""
    return classmethod(lambda cls, x, axis: getattr(cls.xp, name)(x, axis=axis))


class _Ops:
    """The array operations numpy and torch spell alike, on the array module ``xp`` (float64 arrays)."""

    xp: Any
    minimum, maximum, where = _same("minimum"), _same("maximum"), _same("where")
    log, expm1, zeros_like = _same("log"), _same("expm1"), _same("zeros_like")
    amin, amax, sum, prod = _along("amin"), _along("amax"), _along("sum"), _along("prod")

    @classmethod
    def isnan_any(cls, x: Array) -> bool:
        return bool(cls.xp.isnan(x).any())

    @staticmethod
    def affine(x: Array, c: float, k: float) -> Array:
        """c * x + k as a fresh array of x's layout."""
        if c == 1.0:
            return x + k
        if c == -1.0:
            return k - x
        return x * c + k if k != 0.0 else x * c


class NumpyOps(_Ops):
    """Array operations on float64 numpy arrays."""

    xp = np

    @staticmethod
    def logaddexp(a: Array, b: Array) -> Array:
        """log(e^a + e^b), 2-3x faster than np.logaddexp (which has no SIMD loop)."""
        mx = np.maximum(a, b)
        with np.errstate(invalid="ignore"):
            d = np.subtract(a, b)
            np.abs(d, out=d)
            np.negative(d, out=d)
            np.exp(d, out=d)
            np.log1p(d, out=d)
            d += mx
        if mx.size and not np.isfinite(mx).all():  # inf - inf above: the answer is the max
            bad = np.isnan(d) & ~np.isnan(mx)
            d[bad] = mx[bad]
        return d

    @staticmethod
    def softplus(x: Array, b: float) -> Array:
        """log(1 + e^(b x)) / b, exact (no threshold)."""
        u = b * x
        e = np.abs(u)
        np.negative(e, out=e)
        np.exp(e, out=e)
        np.log1p(e, out=e)
        np.maximum(u, 0.0, out=u)
        e += u
        e /= b
        return e

    @staticmethod
    def logsumexp(x: Array, axis: int) -> Array:
        m = x.max(axis=axis, keepdims=True)
        m = np.where(np.isfinite(m), m, 0.0)
        with np.errstate(divide="ignore"):
            return np.log(np.exp(x - m).sum(axis=axis)) + np.squeeze(m, axis=axis)

    @staticmethod
    def cummin(x: Array, axis: int) -> Array:
        return np.minimum.accumulate(x, axis=axis)

    @staticmethod
    def full(shape: tuple[int, ...], value: float, like: Array) -> Array:
        return np.full(shape, value, dtype=np.float64)

    @staticmethod
    def concat(xs: Sequence[Array], axis: int) -> Array:
        return np.concatenate(xs, axis=axis)

    @staticmethod
    def const(values: Any, like: Array) -> Array:
        return np.asarray(values, dtype=np.float64)

    @staticmethod
    def affine_t(x: Array, c: float, k: float) -> Array:
        """c * x.T + k for x [n, L], as a fresh C-contiguous (time-major) [L, n] array."""
        out = np.empty((x.shape[1], x.shape[0]))
        xt = x.T
        if c == 1.0:
            np.add(xt, k, out=out)
        elif c == -1.0:
            np.subtract(k, xt, out=out)
        else:
            np.multiply(xt, c, out=out)
            if k != 0.0:
                out += k
        return out

    @staticmethod
    def contiguous(x: Array) -> Array:
        return np.ascontiguousarray(x)

    @staticmethod
    def pos(x: Array) -> Array:
        return np.maximum(x, 0.0)

    @staticmethod
    def neg(x: Array) -> Array:
        return np.minimum(x, 0.0)

    @staticmethod
    def clip(x: Array, lo: float, hi: float) -> Array:
        return np.clip(x, lo, hi)


class TorchOps(_Ops):
    """Array operations on float64 torch tensors (differentiable where the maths is)."""

    xp = torch

    @staticmethod
    def logaddexp(a: Array, b: Array) -> Array:
        return torch.logaddexp(a, b)

    @staticmethod
    def softplus(x: Array, b: float) -> Array:
        # threshold 40: beyond it log1p(e^u)/b differs from u by < e^-40 / b
        return torch.nn.functional.softplus(x, beta=b, threshold=40.0)

    @staticmethod
    def logsumexp(x: Array, axis: int) -> Array:
        return torch.logsumexp(x, dim=axis)

    @staticmethod
    def cummin(x: Array, axis: int) -> Array:
        return torch.cummin(x, dim=axis).values

    @staticmethod
    def full(shape: tuple[int, ...], value: float, like: Array) -> Array:
        return torch.full(shape, value, dtype=torch.float64, device=like.device)

    @staticmethod
    def concat(xs: Sequence[Array], axis: int) -> Array:
        return torch.cat(list(xs), dim=axis)

    @staticmethod
    def const(values: Any, like: Array) -> Array:
        return torch.as_tensor(values, dtype=torch.float64, device=like.device)

    @classmethod
    def affine_t(cls, x: Array, c: float, k: float) -> Array:
        """c * x.T + k for x [n, L], as a fresh contiguous (time-major) [L, n] tensor."""
        return cls.affine(x.T.contiguous(), c, k)

    @staticmethod
    def contiguous(x: Array) -> Array:
        return x.contiguous()

    @staticmethod
    def pos(x: Array) -> Array:
        return torch.clamp(x, min=0.0)

    @staticmethod
    def neg(x: Array) -> Array:
        return torch.clamp(x, max=0.0)

    @staticmethod
    def clip(x: Array, lo: float, hi: float) -> Array:
        return torch.clamp(x, lo, hi)


def pad_right(ops: Any, x: Array, length: int, value: float) -> Array:
    """x [L, n] extended to [length, n] with ``value`` rows (no copy when already long enough)."""
    missing = length - x.shape[0]
    if missing <= 0:
        return x
    return ops.concat([x, ops.full((missing,) + tuple(x.shape[1:]), value, x)], axis=0)


def sliding_idempotent(ops: Any, x: Array, width: int, n_out: int, op: Callable[[Array, Array], Array]) -> Array:
    """out[i] = op-reduce of x[i : i + width] for i < n_out (rows), x with >= n_out + width - 1 rows; ``op``
    idempotent (min, max): log-doubling, ceil(log2 width) passes."""
    if width == 1:
        return x[:n_out]
    y = x[: n_out + width - 1]
    k = 1
    while 2 * k <= width:
        y = op(y[:-k], y[k:])
        k *= 2
    if k == width:
        return y[:n_out]
    return op(y[:n_out], y[width - k : width - k + n_out])


Elems = tuple  # tuple of arrays, one monoid element per time step


def sliding_monoid(xs: Elems, width: int, n_out: int, combine: Callable[[Elems, Elems], Elems]) -> Elems:
    """out[i] = combine-reduce of steps i .. i + width - 1, in order, for an associative ``combine`` over a tuple
    ``xs`` of [L, n] arrays: power-of-two segments, O(L log width) work."""
    level = tuple(e[: n_out + width - 1] for e in xs)
    size = 1
    offset = 0
    result: Elems | None = None
    while True:
        if width & size:
            seg = tuple(e[offset : offset + n_out] for e in level)
            result = seg if result is None else combine(result, seg)
            offset += size
        if 2 * size > width:
            break
        level = combine(tuple(e[:-size] for e in level), tuple(e[size:] for e in level))
        size *= 2
    assert result is not None
    return result
