"""Order-free arithmetic: results that cannot depend on the CPU, its vector unit, the BLAS kernel or the batch.

A sampler draws ``detect iff u <= q``, so a last-bit change of q flips a draw; the proposal network's products and
fits use arithmetic fixed by IEEE 754 alone:

- **matrix products on grids** (:func:`matmul`): rows and columns rounded to integer multiples of a power of two
  (block floating point; Wilkinson, "Rounding Errors in Algebraic Processes", 1963) so that every partial sum is an
  integer below 2^53, exact in any order; about float32's precision;
- **elementwise arithmetic** in float64 ufuncs of one correctly rounded operation each;
- **transcendentals** (:func:`exp`, :func:`log1p`, :func:`softplus`, :func:`sigmoid`, :func:`tanh`) from those
  operations (Cody & Waite range reduction; Muller, "Elementary Functions", 2016), not libm's;
- **sums** (:func:`exact_sum`) of values on a grid.

Every function takes and returns float64 numpy arrays."""

from __future__ import annotations

import math

import numpy as np

MANTISSA_BITS = 53
"""float64's significand: integers of at most this many bits are exact."""


def grid_bits(inner: int) -> int:
    """The bits each operand of a product summed ``inner`` times may keep so that every partial sum stays an exact
    integer: ``(53 - ceil(log2 inner)) // 2`` (24 for ``inner`` = 32, 20 for 3,000).

    Raises:
        ValueError: ``inner`` < 1."""
    if inner < 1:
        raise ValueError(f"grid_bits: inner dimension must be >= 1, got {inner}")
    return (MANTISSA_BITS - (inner - 1).bit_length()) // 2


def on_grid(x: np.ndarray, bits: int, axis: int | None, nonneg: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``x`` rounded to integers times powers of two: ``x ~ xi * 2^e``, ``|xi| <= 2^bits`` integer-valued float64.

    Args:
        x: float64 [m, n], finite.
        bits: significant bits kept of the largest magnitude of each slice.
        axis: 1: one power of two per row (e [m, 1]); 0: per column (e [1, n]); None: one for all (e [1, 1]).
        nonneg: ``x`` >= 0 (skips an absolute value).
    Returns:
        (xi [m, n], e int) with e broadcastable to xi. Rounding is to nearest, ties to even (``np.rint``)."""
    magnitude = x if nonneg else np.abs(x)
    largest = np.max(magnitude, axis=axis, keepdims=True) if x.size else np.zeros((1, 1))
    _, e = np.frexp(largest)  # largest < 2^e (0 -> 0)
    shift = bits - e
    xi = times_power_of_two(x, shift)  # exact but where it rounds below 2^-1022, to a value rint makes 0
    np.rint(xi, out=xi)
    return xi, -shift


def times_power_of_two(x: np.ndarray, n: np.ndarray, m: np.ndarray | None = None) -> np.ndarray:
    """``x * 2^(n + m)`` correctly rounded, the bits of ``np.ldexp(x, n + m)``, float64 [...] (a new array): one
    multiply per element by the powers of two where each is normal and ``x * 2^n`` cannot leave the normal range,
    else ``np.ldexp``.

    Args:
        x: float64 [...].
        n: int array broadcastable to ``x``.
        m: int array broadcastable to ``x``, or None (0)."""
    lo, hi = (int(n.min()), int(n.max())) if n.size else (0, 0)
    if m is None:
        if -1022 <= lo and hi <= 1023:
            return x * np.ldexp(1.0, n)
        return np.ldexp(x, n)
    m_lo, m_hi = (int(m.min()), int(m.max())) if m.size else (0, 0)
    if -1022 <= lo and hi <= 960 and -1022 <= m_lo and m_hi <= 1023:
        out = x * np.ldexp(1.0, n)
        out *= np.ldexp(1.0, m)
        return out
    return np.ldexp(x, n + m)


def to_grid(x: np.ndarray, bits: int, nonneg: bool = False) -> tuple[np.ndarray, float]:
    """``x`` rounded on one grid for the whole array: ``x ~ xi * scale``, ``|xi| <= 2^bits`` integer-valued float64
    [...], ``scale`` a power of two (:func:`on_grid` with ``axis`` None, faster: two whole-array reductions and one
    multiply). A product of two such arrays summed k times is exact when their bits add to at most
    ``53 - ceil(log2 k)``."""
    largest = 0.0 if not x.size else float(x.max()) if nonneg else max(float(x.max()), -float(x.min()))
    if largest == 0.0:
        return np.zeros_like(x), 1.0
    shift = bits - math.frexp(largest)[1]
    xi = np.ldexp(x, shift) if shift > 1000 else x * math.ldexp(1.0, shift)  # a power of two: exact
    np.rint(xi, out=xi)
    return xi, math.ldexp(1.0, -shift)


def matmul(
    a: np.ndarray, b: np.ndarray | None, b_grid: tuple[np.ndarray, np.ndarray] | None = None, nonneg: bool = False
) -> np.ndarray:
    """``a @ b`` of ``a`` rounded per row and ``b`` per column to :func:`grid_bits` (k) bits, computed exactly and
    rounded once to float64: row i depends on ``a[i]`` and ``b`` alone, on no kernel, order, batch or CPU.

    Args:
        a: float64 [m, k].
        b: float64 [k, n] (ignored, and may be None, when ``b_grid`` is given).
        b_grid: ``b`` already on its grid (:func:`on_grid`, ``grid_bits(k)`` bits, ``axis`` 0).
        nonneg: ``a`` >= 0 (e.g. after a ReLU).
    Returns:
        float64 [m, n].
    Raises:
        ValueError: neither ``b`` nor ``b_grid``."""
    bits = grid_bits(a.shape[1])
    ai, ea = on_grid(a, bits, 1, nonneg)
    if b_grid is None:
        if b is None:
            raise ValueError("matmul: give b or b_grid")
        b_grid = on_grid(b, bits, 0)
    bi, eb = b_grid
    return times_power_of_two(ai @ bi, ea, eb)


def scaled_grid(b_grid: tuple[np.ndarray, np.ndarray]) -> np.ndarray | None:
    """An operand on its grid (``(bi [k, n], eb [1, n])``, :func:`on_grid` with ``axis`` 0) as its values ``bi *
    2^eb``, transposed: float64 [n, k], C-contiguous, for :func:`matmul_t`; None where a column's power of two is
    below 2^-1074 or above 2^971 (a product's partial sums times it could then round or overflow)."""
    bi, eb = b_grid
    if eb.size and not (-1074 <= int(eb.min()) and int(eb.max()) <= 971):
        return None
    return np.ascontiguousarray(np.ldexp(bi, eb).T)


def matmul_t(
    at: np.ndarray,
    b_grid: tuple[np.ndarray, np.ndarray],
    bt: np.ndarray | None,
    nonneg: bool = False,
    own: bool = False,
) -> np.ndarray:
    """:func:`matmul` transposed: ``(a @ b).T`` float64 [n, m] of ``at = a.T`` [k, m], with the bits of ``matmul(a,
    None, b_grid, nonneg)`` in fewer passes (:func:`matmul` itself where a power of two leaves the normal range, or
    ``bt`` is None), but for the sign of a zero: a result that is a sum of zero products only may be +0.0 where
    :func:`matmul` gives -0.0 (adding a nonzero bias afterwards gives the same bits either way).

    Each column of ``at`` is rounded to its grid of ``grid_bits(k)`` bits in place of its own scale: ``x + c - c``
    with ``c = 1.5 * 2^(52 - shift)``, where a float64's step is ``2^-shift`` (rounding to nearest, ties to even, as
    ``np.rint(x * 2^shift) * 2^-shift``); then every product with ``bt``'s values and every partial sum is an
    integer multiple of ``2^(eb - shift)`` below ``2^53`` of them: exact, in any order, with no rescaling.

    Args:
        at: float64 [k, m].
        b_grid: ``b`` on its grid (:func:`on_grid`, ``grid_bits(k)`` bits, ``axis`` 0).
        bt: ``scaled_grid(b_grid)`` [n, k] or None.
        nonneg: ``at`` >= 0.
        own: ``at`` may be overwritten.
    Returns:
        float64 [n, m]."""
    largest = (at if nonneg else np.abs(at)).max(axis=0) if at.shape[0] else np.zeros(at.shape[1])
    shift = grid_bits(at.shape[0]) - np.frexp(largest)[1]
    if bt is None or not shift.size:
        return matmul(at.T, None, b_grid, nonneg).T
    lo, hi = int(shift.min()), int(shift.max())
    eb = b_grid[1]
    if -971 <= lo and hi <= 1022 and int(eb.min()) - hi >= -1074 and int(eb.max()) - lo <= 971:
        c = np.ldexp(1.5, 52 - shift)
        xs = np.add(at, c, out=at if own else None)  # rounded to the column's grid by the addition itself
        xs -= c  # exact
        return bt @ xs
    if not (-1022 <= lo and hi <= 1022):
        return matmul(at.T, None, b_grid, nonneg).T
    xi = np.multiply(at, np.ldexp(1.0, shift), out=at if own else None)  # exact: the grid's integers, but rint
    np.rint(xi, out=xi)
    out = bt @ xi  # exact: column j of b's integers times 2^eb_j
    out *= np.ldexp(1.0, -shift)
    return out


def exact_sum(x: np.ndarray, axis: int) -> np.ndarray:
    """The sum of ``x`` [m, n] along ``axis`` (0: per column, 1: per row) of its values rounded to a grid per
    summed slice with ``53 - ceil(log2 length)`` bits: integers whose sum is exact in any order. float64 [n] or [m]."""
    length = x.shape[axis]
    xi, e = on_grid(x, MANTISSA_BITS - (max(length, 1) - 1).bit_length(), axis)
    return np.ldexp(xi.sum(axis=axis), e.reshape(-1))


def row_sum(x: np.ndarray) -> np.ndarray:
    """The sum of each row of ``x`` float64 [m, k], float64 [m]: left to right for k < 8 (numpy's own order there,
    the same bits as ``x.sum(axis=1)``, about 30 times faster on a few columns), ``x.sum(axis=1)`` otherwise."""
    if x.ndim != 2 or x.shape[1] >= 8 or x.shape[1] == 0:
        return x.sum(axis=1)
    out = x[:, 0].copy()
    for j in range(1, x.shape[1]):
        out += x[:, j]
    return out


_INV_LN2 = 1.4426950408889634
_LN2_HI = 6.93147180369123816490e-01  # fdlibm's split of log 2: the high part has 21 trailing zero bits, so that
_LN2_LO = 1.90821492927058770002e-10  # k * _LN2_HI is exact for |k| < 2^21
_EXP_TAYLOR = tuple(1.0 / math.factorial(n) for n in range(14))  # |r| <= log(2) / 2: r^14 / 14! < 1e-17
_ATANH_TERMS = tuple(1.0 / (2 * n + 1) for n in range(18))  # s <= 1/3: s^37 / 37 < 1e-19


def exp(x: np.ndarray) -> np.ndarray:
    """e^x, float64 [...], to about 1 ulp, from correctly rounded operations alone (Cody & Waite, "Software
    Manual for the Elementary Functions", 1980: x = k log 2 + r, e^r by its Taylor polynomial of degree 13,
    times 2^k). Below -745.2 it is 0, above 709.7 inf."""
    x = np.clip(np.asarray(x, dtype=np.float64), -745.2, 709.8)
    k = np.rint(x * _INV_LN2)
    r = (x - k * _LN2_HI) - k * _LN2_LO
    p = np.full_like(r, _EXP_TAYLOR[13])
    for c in _EXP_TAYLOR[12::-1]:
        p *= r
        p += c
    return np.ldexp(p, k.astype(np.int32))


def log1p(t: np.ndarray) -> np.ndarray:
    """log(1 + t) for t in [0, 1], float64 [...], to 3 ulp, from correctly rounded operations alone:
    ``2 atanh(s)``, s = t / (2 + t) <= 1/3, by its series to s^35 (Abramowitz & Stegun 4.1.29)."""
    t = np.asarray(t, dtype=np.float64)
    return _two_atanh(t / (2.0 + t))


def _two_atanh(s: np.ndarray) -> np.ndarray:
    """2 atanh(s) for |s| <= 1/3, float64 [...], by its series to s^35 (Abramowitz & Stegun 4.1.29), Horner's."""
    s2 = s * s
    p = np.full_like(s, _ATANH_TERMS[17])
    for c in _ATANH_TERMS[16::-1]:
        p *= s2
        p += c
    return 2.0 * s * p


def log(x: np.ndarray) -> np.ndarray:
    """The natural log of x, float64 [...] (nats), to about 3 ulp, from correctly rounded operations alone: x = m 2^e
    with m in [sqrt(1/2), sqrt(2)) (:func:`numpy.frexp`, exact), log m = 2 atanh(s), s = (m - 1) / (m + 1), |s| < 0.172,
    by its series (Abramowitz & Stegun 4.1.29), plus e log 2 in fdlibm's two parts. 0 gives -inf, a negative x or
    nan gives nan, inf gives inf."""
    x = np.asarray(x, dtype=np.float64)
    m, e = np.frexp(np.where(np.isfinite(x) & (x > 0.0), x, 1.0))
    low = m < math.sqrt(0.5)
    m, e = np.where(low, 2.0 * m, m), np.where(low, e - 1, e).astype(np.float64)
    out = e * _LN2_HI + (e * _LN2_LO + _two_atanh((m - 1.0) / (m + 1.0)))
    return np.where(x > 0.0, np.where(np.isinf(x), np.inf, out), np.where(x == 0.0, -np.inf, np.nan))


def softplus_and_sigmoid(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(log(1 + e^d), 1 / (1 + e^-d)), float64 [...] each, from one :func:`exp` of -|d|: ``softplus(-d) =
    softplus(d) - d`` and ``sigmoid(-d) = 1 - sigmoid(d)`` give the other sign."""
    t = exp(-np.abs(d))
    softplus = np.maximum(d, 0.0) + log1p(t)
    sigmoid = np.where(d >= 0.0, 1.0 / (1.0 + t), t / (1.0 + t))
    return softplus, sigmoid


def tanh(x: np.ndarray) -> np.ndarray:
    """tanh x = sign(x) (1 - e^-2|x|) / (1 + e^-2|x|), float64 [...], from :func:`exp`."""
    x = np.asarray(x, dtype=np.float64)
    t = exp(-2.0 * np.abs(x))
    return np.copysign((1.0 - t) / (1.0 + t), x)
