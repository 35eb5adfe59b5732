"""The Student-t quantile table (pemviz.core.t_quantile) against scipy.special.stdtrit and scipy.stats (oracles): within
its stated tolerance over the whole range of u, deep into both tails, for any degrees of freedom >= 1; exact symmetry;
the values outside the table as stdtrit gives them; one clear error for df below 1."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pemviz.core.detector_noise import standard_quantile
from pemviz.core.t_quantile import LOWEST_EXPONENT, TOLERANCE, student_t_quantile
from scipy import stats
from scipy.special import stdtrit

NOISE_PEM_DF = (3.15016556, 2.66272616)
"""The shipped noise PEM's degrees of freedom (range, lateral), to 8 digits."""


def uniforms(seed: int) -> np.ndarray:
    """Uniforms over the whole range: plain draws, the lower tail to 1e-19, the upper one to 1 - 2.3e-16, the
    neighbourhood of the median and every binade's start."""
    rng = np.random.default_rng(seed)
    tail = np.exp(-rng.random(20_000) * 44.0)
    upper = 1.0 - np.exp(-rng.random(20_000) * 36.0)  # 1 - u >= 2.3e-16: below 1
    return np.concatenate(
        [rng.random(200_000), tail, upper, 0.5 + (rng.random(2_000) - 0.5) * 1e-6, np.ldexp(1.0, -np.arange(1, 64))]
    )


@pytest.mark.parametrize("df", [1.0, 1.5, *NOISE_PEM_DF, 7.0, 30.0, 300.0])
def test_the_table_is_stdtrit_to_its_tolerance_everywhere(df):
    u = uniforms(0)
    got, want = student_t_quantile(df, u), stdtrit(df, u)
    worst = np.max(np.abs(got - want) / (1.0 + np.abs(want)))
    assert worst <= TOLERANCE, f"df {df}: worst scaled difference {worst:.3g}"
    away = np.abs(u - 0.5) > 0.01  # relative too, away from the median (where Q crosses 0)
    assert np.max(np.abs(got - want)[away] / np.abs(want[away])) <= TOLERANCE


@settings(max_examples=60, deadline=None)
@given(df=st.floats(1.0, 80.0), u=st.floats(2.0 ** (LOWEST_EXPONENT - 1), 1.0, exclude_max=True))
def test_any_df_and_any_uniform_agree_with_scipy_stats(df, u):
    """Property: any df >= 1 and any u in the table's range (and above 1/2 by symmetry) against scipy.stats.t."""
    got = float(student_t_quantile(df, np.array([u]))[0])
    want = float(stats.t(df).ppf(u))
    assert abs(got - want) <= 2 * TOLERANCE * (1.0 + abs(want)) + 1e-9 * abs(want)


def test_symmetry_is_exact_and_the_median_is_zero():
    u = np.arange(1, 2**12) / 2**13  # (0, 1/2), exactly representable, as is 1 - u
    q = student_t_quantile(NOISE_PEM_DF[0], u)
    np.testing.assert_array_equal(student_t_quantile(NOISE_PEM_DF[0], 1.0 - u), -q)
    assert student_t_quantile(3.0, np.array([0.5]))[0] == 0.0
    assert np.all(np.diff(q) > 0)  # increasing


def test_values_outside_the_table_are_stdtrit_s():
    u = np.array([0.0, 1.0, -0.1, 1.1, np.nan, 2.0**-70, 1e-300])
    np.testing.assert_array_equal(student_t_quantile(3.0, u), stdtrit(3.0, u))


def test_standard_quantile_takes_one_df_per_column_and_falls_back_below_one():
    u = uniforms(1)[:1000].reshape(500, 2)
    got = standard_quantile("student-t", np.array(NOISE_PEM_DF), u)
    np.testing.assert_allclose(got, stdtrit(np.array(NOISE_PEM_DF), u), rtol=1e-10, atol=TOLERANCE)
    np.testing.assert_array_equal(
        standard_quantile("student-t", np.array([0.5, 0.8]), u), stdtrit(np.array([0.5, 0.8]), u)
    )


@pytest.mark.parametrize("df", [0.5, float("nan"), float("inf")])
def test_df_outside_the_table_s_range_is_one_clear_error(df):
    with pytest.raises(ValueError, match="df must be a finite number >= 1"):
        student_t_quantile(df, np.array([0.3]))


def test_one_df_per_column_reads_each_column_s_own_table():
    u = uniforms(2)[:20_000].reshape(10_000, 2)
    both = student_t_quantile(np.array(NOISE_PEM_DF), u)
    for j, df in enumerate(NOISE_PEM_DF):
        np.testing.assert_array_equal(both[:, j], student_t_quantile(df, np.ascontiguousarray(u[:, j])))
    with pytest.raises(ValueError, match="one df per column of u, got 2 for u of shape"):
        student_t_quantile(np.array(NOISE_PEM_DF), u[:, :1])
