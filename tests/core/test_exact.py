"""Order-free arithmetic (pemviz.core.exact) against exact rational arithmetic and the standard library."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pemviz.core import exact


def exact_product(a: np.ndarray, b: np.ndarray) -> list[list[Fraction]]:
    """a @ b in rational arithmetic: the truth a float64 kernel can only round."""
    fa = [[Fraction(v) for v in row] for row in a]
    fb = [[Fraction(v) for v in row] for row in b]
    return [
        [sum((fa[i][k] * fb[k][j] for k in range(a.shape[1])), Fraction(0)) for j in range(b.shape[1])]
        for i in range(a.shape[0])
    ]


def test_grid_bits_keep_every_partial_sum_below_two_to_the_53():
    assert (exact.grid_bits(1), exact.grid_bits(4), exact.grid_bits(32), exact.grid_bits(3000)) == (26, 25, 24, 20)
    for inner in (1, 2, 3, 31, 32, 33, 1000, 10**5):
        assert 2 * exact.grid_bits(inner) + math.ceil(math.log2(inner)) <= 53
    with pytest.raises(ValueError, match="inner dimension must be >= 1"):
        exact.grid_bits(0)


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 6), st.integers(1, 40), st.integers(1, 5), st.integers(0, 2**32 - 1), st.floats(-30, 30))
def test_a_product_on_grids_is_the_rational_product_of_the_rounded_operands(m, k, n, seed, log_scale):
    # each row of a and column of b rounded to grid_bits(k) bits of its largest magnitude; then the float64 kernel's
    # result equals the exact rational product of the rounded operands (no rounding left), and row i is the same
    # bits computed alone
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(m, k)) * math.exp(log_scale) * (rng.random((m, k)) < 0.8)
    b = rng.normal(size=(k, n)) * rng.choice([1e-3, 1.0, 1e3], size=(1, n))
    bits = exact.grid_bits(k)
    ai, ea = exact.on_grid(a, bits, 1)
    bi, eb = exact.on_grid(b, bits, 0)
    assert np.all(np.abs(ai) <= 2.0**bits) and np.all(ai == np.rint(ai)) and np.all(bi == np.rint(bi))
    assert np.all(np.abs(np.ldexp(ai, ea) - a) <= np.ldexp(0.5, ea))  # to nearest: half a step of the row's grid
    got = exact.matmul(a, b)
    truth = exact_product(np.ldexp(ai, ea), np.ldexp(bi, eb))
    assert [[Fraction(v) for v in row] for row in got] == truth
    for i in range(m):
        np.testing.assert_array_equal(exact.matmul(a[i : i + 1], b), got[i : i + 1])


@pytest.mark.parametrize(
    "a_exp, b_exp, fast",
    [
        ((-8, 8), 0, True),
        ((-900, -400), -560, True),
        ((400, 900), 500, True),
        ((-1074, 0), 0, False),
        ((0, 8), -1060, False),
    ],
)
@pytest.mark.parametrize("k, n, nonneg", [(4, 32, False), (32, 32, True), (32, 1, True), (1, 32, False)])
def test_the_transposed_product_gives_the_products_bits_from_the_normal_range_to_the_subnormals(
    a_exp, b_exp, fast, k, n, nonneg
):
    # matmul_t computes (a @ b).T with b's values (its integers times its column powers of two), each row of a
    # rounded to its grid by an added constant (the normal range), or as integers and one multiply per row where
    # results round into the subnormals (b at 2^-560 and rows at 2^-900) or overflow: the same bits as matmul's
    # integer product scaled by 2^(ea + eb), and by matmul itself where a row's or a column's power of two leaves the
    # range the multiplies need
    rng = np.random.default_rng(k + n)
    a = rng.normal(size=(300, k)) * 2.0 ** rng.integers(*a_exp, size=(300, 1))
    a[:40] = 0.0
    a = np.abs(a) if nonneg else a
    grid = exact.on_grid(rng.normal(size=(k, n)) * 2.0**b_exp, exact.grid_bits(k), 0)
    shift = exact.grid_bits(k) - np.frexp(np.abs(a).max(axis=1))[1]
    taken = exact.scaled_grid(grid) is not None and -1022 <= shift.min() and shift.max() <= 1022
    with np.errstate(over="ignore", invalid="ignore"):
        want = exact.matmul(a, None, grid, nonneg)
        got = exact.matmul_t(a.T.copy(), grid, exact.scaled_grid(grid), nonneg, own=True)
    assert taken == fast and got.shape == (n, 300)
    assert np.array_equal(got.T.view(np.int64), want.view(np.int64))
    if b_exp == -560:  # results below the normal range, rounded once
        assert ((want != 0) & (np.abs(want) < 2.0**-1022)).any()


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([(4, 32, False), (32, 32, True), (32, 1, True)]), st.integers(-60, 9))
def test_the_transposed_product_rounds_by_an_added_constant_with_the_products_bits_but_a_zeros_sign(seed, shape, e):
    # the fast path rounds each column to its grid by x + 1.5 * 2^(52 - shift) - 1.5 * 2^(52 - shift) and multiplies
    # by b's values: every nonzero result has matmul's bits; a result that is a sum of zero products may be +0.0
    # where matmul's is -0.0 (its rounded -0.0 entries are +0.0 here), so adding a nonzero bias gives the same bits
    k, n, nonneg = shape
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(200, k)) * 2.0 ** rng.integers(-30, 30, size=(200, 1))
    a[rng.random(a.shape) < 0.2] = 0.0
    a[:, 1:] *= np.where(rng.random((200, 1)) < 0.1, 2.0**-40, 1.0)  # entries that round to zero beside the largest
    a = np.abs(a) if nonneg else a
    b = rng.normal(size=(k, n)) * 2.0**e
    b[rng.random(b.shape) < 0.2] = 0.0
    grid = exact.on_grid(b, exact.grid_bits(k), 0)
    want = exact.matmul(a, None, grid, nonneg)
    got = exact.matmul_t(a.T.copy(), grid, exact.scaled_grid(grid), nonneg).T
    nonzero = want != 0.0
    assert np.array_equal(got != 0.0, nonzero)
    assert np.array_equal(got[nonzero].view(np.int64), want[nonzero].view(np.int64))
    bias = rng.normal(size=n)
    assert np.array_equal((got + bias).view(np.int64), (want + bias).view(np.int64))


def test_a_sum_on_a_grid_is_exact_in_any_order():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(5000, 3)) * np.array([1e-8, 1.0, 1e8])
    s = exact.exact_sum(x, 0)
    xi, e = exact.on_grid(x, 53 - math.ceil(math.log2(5000)), 0)
    for j in range(3):
        truth = sum(Fraction(v) for v in np.ldexp(xi[:, j], e[0, j]))
        assert Fraction(s[j]) == truth
        assert exact.exact_sum(x[::-1], 0)[j] == s[j]
        assert abs(s[j] - math.fsum(x[:, j])) <= 5000 * 2.0**-41 * np.abs(x[:, j]).max()  # half a step per term


def test_the_transcendentals_agree_with_the_standard_library_to_a_few_ulp():
    x = np.concatenate([-np.logspace(-300, np.log10(745), 4000), np.linspace(-40, 40, 4001), [0.0, -0.0, 709.0]])
    ulp = np.spacing(np.abs(np.array([math.exp(v) for v in x]))) + 5e-324
    assert np.all(np.abs(exact.exp(x) - [math.exp(v) for v in x]) <= 2 * ulp)
    assert exact.exp(np.array([-800.0]))[0] == 0.0
    t = np.concatenate([np.linspace(0.0, 1.0, 5001), np.logspace(-300, 0, 2000)])
    want = np.array([math.log1p(v) for v in t])
    assert np.all(np.abs(exact.log1p(t) - want) <= 3 * np.spacing(want) + 5e-324)  # measured: 3 ulp at most
    d = np.linspace(-50, 50, 2001)
    softplus, sigmoid = exact.softplus_and_sigmoid(d)
    np.testing.assert_allclose(softplus, np.logaddexp(0.0, d), rtol=1e-15, atol=1e-300)
    np.testing.assert_allclose(sigmoid, 1.0 / (1.0 + np.exp(-d)), rtol=1e-15)
    np.testing.assert_allclose(exact.tanh(d / 10), np.tanh(d / 10), rtol=1e-14, atol=1e-16)


@pytest.mark.parametrize("k", [1, 2, 3, 5, 7, 8, 12])
def test_row_sum_is_numpy_s_row_sum_bit_for_bit(k):
    # left to right below 8 columns (numpy's order there); numpy's pairwise sum from 8 on
    rng = np.random.default_rng(k)
    x = rng.normal(size=(5000, k)) * 10.0 ** rng.integers(-8, 8, size=(5000, k))
    np.testing.assert_array_equal(exact.row_sum(x), x.sum(axis=1))
    if k == 3:  # by hand: (a + b) + c, where a + (b + c) rounds otherwise
        y = np.array([[1.0, 2.0**-53, 2.0**-53]])
        assert exact.row_sum(y)[0] == (1.0 + 2.0**-53) + 2.0**-53 == 1.0 != 1.0 + (2.0**-53 + 2.0**-53)


@pytest.mark.parametrize("with_m", [False, True])
def test_times_power_of_two_is_ldexp_bit_for_bit_from_the_normal_range_to_the_subnormals(with_m):
    # C's ldexp (numpy's) scales exactly or rounds once; the two multiplies by powers of two must give its bits
    # wherever they are taken, including results that round into the subnormals or to 0, and fall back to it beyond
    rng = np.random.default_rng(7)
    x = (
        np.rint(rng.normal(size=(400, 6)) * 2.0 ** rng.integers(0, 52, size=(400, 1)))
        if with_m
        else rng.normal(size=(400, 6)) * 2.0 ** rng.integers(-1070, 1000, size=(400, 1))
    )
    n = rng.integers(-1100 if not with_m else -1022, 1000, size=(400, 1))
    m = rng.integers(-1040, 40, size=(1, 6)) if with_m else None
    with np.errstate(over="ignore"):
        want = np.ldexp(x, n if m is None else n + m)
        for i in range(0, 400, 4):  # a few rows at a time: most on the multiplies, the others beyond their range
            got = exact.times_power_of_two(x[i : i + 4], n[i : i + 4], m)
            assert np.array_equal(got.view(np.int64), want[i : i + 4].view(np.int64))
    assert (want != 0).any() and (np.abs(want[want != 0]) < 2.0**-1022).any()  # subnormal results were checked
