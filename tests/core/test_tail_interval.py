"""The importance-sampling interval's upper end widened by the weights' Pareto tail
(:func:`pemviz.core.confidence.log_mean_interval`, :func:`pemviz.core.confidence.tail_multiplier`): on lognormal
weights, whose mean is known, it holds the mean at the nominal 95 % where the symmetric log-scale t interval does
not."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pemviz.core.confidence import TAIL_QUANTILES, TAIL_SHAPES, log_mean_interval, tail_multiplier
from pemviz.core.diagnostics import pareto_khat
from scipy.special import stdtrit


def test_lognormal_weights_are_held_at_the_nominal_level_where_the_symmetric_interval_is_not():
    """N = 1,000 terms 1[fail] w, P(fail) = 0.4, log w ~ N(-sigma^2 / 2, sigma^2) with sigma = 2 (E w = 1, so the mean
    is 0.4 exactly; k-hat 0.5-0.7, the crowd's): over 500 seeded replications the symmetric log-scale t interval holds
    0.4 in 83.8 % (0.846 over 2,000 replications), the tail-widened one in 95.8 % (0.948 over 2,000)."""
    rng = np.random.default_rng(7)
    sigma, n, reps, truth = 2.0, 1000, 500, math.log(0.4)
    old = new = 0
    for _ in range(reps):
        failed = rng.random(n) < 0.4
        log_y = np.full(n, -np.inf)
        log_y[failed] = sigma * rng.standard_normal(int(failed.sum())) - sigma**2 / 2
        _, lo, hi = log_mean_interval(log_y)
        _, lo_t, hi_t = log_mean_interval(log_y, pareto_khat(log_y))
        old += lo <= truth <= hi
        new += lo_t <= truth <= hi_t
        assert lo_t == lo and hi_t >= hi  # only the upper end moves, and only up
    assert old / reps == pytest.approx(0.838, abs=0.01)  # 1.96 binomial s.e. below 0.95 is 0.931
    assert new / reps == pytest.approx(0.958, abs=0.01)


def test_the_multiplier_is_t_for_a_light_or_unfitted_tail_and_the_table_above():
    """Below the table's first quantile and for a nan k-hat: Student's t_{N-1}; at k = 0.5 and 0.7 the table's 2.90 and
    4.32; between knots the line between them; beyond k = 0.9 the last knot."""
    t = float(stdtrit(99, 0.975))
    assert tail_multiplier(math.nan, 100) == pytest.approx(t)
    assert tail_multiplier(0.0, 10) == pytest.approx(float(stdtrit(9, 0.975)))  # t_9 = 2.26 > 2.01
    assert tail_multiplier(0.5, 1000) == pytest.approx(2.90)
    assert tail_multiplier(0.7, 1000) == pytest.approx(4.32)
    assert tail_multiplier(0.65, 1000) == pytest.approx(0.5 * (3.42 + 4.32))
    assert tail_multiplier(1.4, 1000) == pytest.approx(TAIL_QUANTILES[-1])
    assert len(TAIL_SHAPES) == len(TAIL_QUANTILES) and np.all(np.diff(TAIL_QUANTILES) > 0)
    with pytest.raises(ValueError, match="n >= 2"):
        tail_multiplier(0.5, 1)


def test_the_upper_end_by_hand():
    """Four terms 1, 1, 0, 0: mean 1/2, y / mean = 2, 2, 0, 0 with standard deviation sqrt(4 / 3), so se / mean =
    sqrt(4 / 3) / 2; the lower end uses t_3 = 3.18, the upper end the larger of t_3 and the table at k = 0.5 (2.90)."""
    log_y = np.array([0.0, 0.0, -np.inf, -np.inf])
    rel_se = math.sqrt(4.0 / 3.0) / 2.0  # sd of y / mean = (2, 2, 0, 0): sqrt(4 * 1 / 3); over sqrt(4)
    log_mean, lo, hi = log_mean_interval(log_y, 0.5)
    assert log_mean == pytest.approx(math.log(0.5))
    assert lo == pytest.approx(math.log(0.5) - float(stdtrit(3, 0.975)) * rel_se)
    assert hi == pytest.approx(math.log(0.5) + max(float(stdtrit(3, 0.975)), 2.90) * rel_se)
