"""log, exp, log1p, atan2 and pow with the C library's bits on every x86 CPU, for the rollout path's likelihoods, draws
and dynamics.

numpy dispatches its float64 ``log``, ``exp``, ``log1p`` ... to its own or SVML's AVX-512 loops where the CPU has
AVX-512, elsewhere to libm; the two round differently in the last bit, so a seed's log-likelihoods, draws and states
would depend on the CPU. scipy.special's ufuncs call libm's double functions: ``xlogy(1, x)`` is ``log(x)``,
``inv_boxcox(x, 0)`` is ``exp(x)``, ``boxcox1p(x, 0)`` is ``log1p(x)`` (scipy's ``_boxcox.pxd``), bit for bit libm's,
which numpy returns on CPUs without AVX-512, so runs recorded there stay valid. :func:`atan2` takes the imaginary part
of numpy's complex ``log`` (C99 7.3.9.2, ``carg``), :func:`power` libm's ``pow`` through :func:`math.pow`.

:mod:`pemviz.core.exact` has IEEE-754-only versions, the same under any libm. Every function takes an array (or
scalar) and returns float64 of the same shape; ``out`` (log, exp, log1p) is a ufunc's."""

from __future__ import annotations

import math
from itertools import repeat
from typing import Any

import numpy as np
from scipy.special import boxcox1p, inv_boxcox, xlogy


def log(x: Any, out: np.ndarray | None = None) -> Any:
    """The natural log of ``x`` (nats), libm's ``log``: 0 gives -inf, a negative value nan (no warning)."""
    return xlogy(1.0, x, out=out)


def exp(x: Any, out: np.ndarray | None = None) -> Any:
    """e^x, libm's ``exp``: 0 below -745.2, inf above 709.8."""
    return inv_boxcox(x, 0.0, out=out)


def log1p(x: Any, out: np.ndarray | None = None) -> Any:
    """log(1 + x) (nats), libm's ``log1p``: -1 gives -inf, below -1 nan."""
    return boxcox1p(x, 0.0, out=out)


def atan2(y: Any, x: Any) -> np.ndarray:
    """The angle of the point ``(x, y)`` from the x axis (radians, in [-pi, pi]), libm's ``atan2(y, x)``: the
    imaginary part of the complex log of ``x + iy`` (C99 7.3.9.2). ``y`` and ``x`` broadcast; float64 of their
    shape (0-d for scalars)."""
    yx = np.broadcast_arrays(np.asarray(y, dtype=np.float64), np.asarray(x, dtype=np.float64))
    z = np.empty(yx[0].shape, dtype=np.complex128)
    z.real, z.imag = yx[1], yx[0]
    with np.errstate(divide="ignore", invalid="ignore"):  # log(0) and nan in the real part: not returned
        np.log(z, out=z)
    return z.imag.copy()


def power(x: Any, y: float) -> np.ndarray:
    """``x ** y`` elementwise, libm's ``pow`` (through :func:`math.pow`): float64 of ``x``'s shape.

    Raises:
        ValueError: a negative ``x`` with a ``y`` that is not an integer, where numpy's ``power`` gives nan.
        OverflowError: a result beyond float64's range, where numpy's gives inf."""
    a = np.asarray(x, dtype=np.float64)
    return np.fromiter(map(math.pow, a.ravel().tolist(), repeat(float(y))), np.float64, a.size).reshape(a.shape)


def logsumexp(a: Any, axis: int | None = None) -> Any:
    """``log(sum(exp(a)))`` over ``axis`` (None: all), nats, as scipy.special's ``logsumexp`` (scipy 1.17) computes it
    on a CPU without AVX-512, with libm's exp, log and log1p: ``log1p(s / m) + log(m) + a_max``, ``m`` the count of
    the maxima and ``s`` the sum of the other terms ``exp(a - a_max)``; where that is not finite,
    ``log(sum(exp(a)))`` (all ``-inf`` gives ``-inf``, any ``+inf`` gives ``inf``). scipy's calls numpy's ``exp``,
    ``log`` and ``log1p``, whose AVX-512 loops round otherwise (the module's docstring).

    Args:
        a: float64 array (real), any shape.
        axis: the axis summed over, or None.
    Returns:
        float64 of ``a``'s shape without ``axis`` (a Python float for ``axis=None`` or a 1-d ``a``)."""
    a = np.array(a, dtype=np.float64, copy=True)
    if a.ndim == 0:
        a = a.reshape(1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        whole = log(np.sum(exp(a), axis=axis, keepdims=True)) if not np.isfinite(a).all() else None
        a_max = np.max(a, axis=axis, keepdims=True)
        is_max = a == a_max
        m = np.sum(is_max.astype(np.float64), axis=axis, keepdims=True)
        a[is_max] = -np.inf
        s = np.sum(exp(a - a_max), axis=axis, keepdims=True)
        s = np.where(s == 0, s, s / m)
        out = log1p(s) + log(m) + a_max
    if whole is not None:  # a row of -inf or with +inf or nan: scipy's log(sum(exp(a))) there
        out = np.where(np.isfinite(out), out, whole)
    out = out.reshape(()) if axis is None else np.squeeze(out, axis=axis)
    return out[()] if out.ndim == 0 else out
