"""The feature a state proposal moved most from the PEM, and q(detect) against the PEM over it
(pemviz.core.feature_view), against closed forms: a hand-built GLM whose one weight is nonzero, a quadratic shift."""

from __future__ import annotations

import numpy as np
import pytest
from pemviz.core.detectors import StageSamplers
from pemviz.core.feature_view import feature_curve, feature_effects, state_proposal_of
from pemviz.estimators.state import FirstColumns
from pemviz.estimators.state_glm import StateGLM
from scipy.special import expit

NAMES = ("gap_m", "object track_misses", "ego ttc_s", "ego constant")


class GapPem:
    """A PEM of the gap alone: logit p(detect) = 2 - 0.3 gap (rows [N, 1])."""

    def detect_logit(self, rows: np.ndarray) -> np.ndarray:
        assert rows.shape[1] == 1, "the PEM reads the rows' own column only"
        return 2.0 - 0.3 * rows[:, 0]


def rows_of(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.column_stack(
        [rng.uniform(0.0, 10.0, n), rng.integers(0, 5, n).astype(np.float64), rng.normal(3.0, 1.5, n), np.full(n, 7.0)]
    )


def glm_with(weights: list[float]) -> StateGLM:
    """A GLM over the four columns (scales 10, 1, 2, 1), its linear part's (w, b) set by hand."""
    glm = StateGLM((0, 1, 2, 3), (10.0, 1.0, 2.0, 1.0), (5.0, 0.0, 3.0, 7.0), FirstColumns(GapPem(), 1))
    glm.coef = np.asarray(weights, dtype=np.float64)
    return glm


@pytest.mark.parametrize(
    "column, w, bins",
    [
        (2, 1.5, "quantile"),  # a continuous feature: 20 quantile bins
        (1, -0.8, "values"),  # a feature of 5 values: a bin per value
    ],
)
def test_a_glm_whose_one_weight_is_nonzero_moves_that_feature_and_its_curve_is_the_closed_form(column, w, bins):
    rows = rows_of(2000, seed=column)  # no more than the rows perturbed at most: every row counts
    weights = [0.0, 0.0, 0.0, 0.0, -0.4]
    weights[column] = w
    scale = (10.0, 1.0, 2.0, 1.0)[column]
    curve = feature_curve(glm_with(weights), GapPem(), rows, NAMES, own_columns=1)
    assert curve is not None and curve.name == NAMES[column] and curve.column == column
    # the shift w x / scale - 0.4 changes by |w| sd / scale across one sd of the feature; no other column moves it
    sd = rows[:, column].std()
    assert curve.effect == pytest.approx(abs(w) * sd / scale, rel=1e-6)
    others = np.delete(curve.effects, column)
    np.testing.assert_allclose(others, 0.0, atol=1e-6)
    # the bins, made here: 20 quantile bins, or a bin per value
    x = rows[:, column]
    if bins == "quantile":
        edges = np.quantile(x, np.linspace(0.0, 1.0, 21))
        masks = [(x >= lo) & (x < hi) for lo, hi in zip(edges[:-2], edges[1:-1], strict=True)]
        masks.append(x >= edges[-2])
    else:
        masks = [x == v for v in range(5)]
    assert len(curve.x) == len(masks)
    pem = 2.0 - 0.3 * rows[:, 0]
    for b, m in enumerate(masks):
        assert curve.n_rows[b] == m.sum()
        assert curve.x[b] == pytest.approx(x[m].mean(), rel=1e-12)
        # the GLM's linear part is exact arithmetic on a fixed-point grid (pemviz.core.exact): ~1e-7 from float64's
        assert curve.q_detect[b] == pytest.approx(expit(pem[m] + w * x[m] / scale - 0.4).mean(), rel=1e-6)
        assert curve.p_detect[b] == pytest.approx(expit(pem[m]).mean(), rel=1e-12)
    assert curve.n_rows.sum() == len(rows)


def test_a_glm_that_only_shifts_every_row_alike_moves_no_feature():
    assert feature_curve(glm_with([0.0, 0.0, 0.0, 0.0, -0.4]), GapPem(), rows_of(500, 1), NAMES, 1) is None


class QuadraticShift:
    """q's logit: the PEM's plus 0.5 x1^2 + 0.3 x2 (a network's curved shift, in closed form)."""

    def detect_logit(self, rows: np.ndarray) -> np.ndarray:
        return GapPem().detect_logit(rows[:, :1]) + 0.5 * rows[:, 1] ** 2 + 0.3 * rows[:, 2]


def test_a_curved_shift_is_ranked_by_its_mean_derivative_times_the_features_sd():
    rng = np.random.default_rng(4)
    n = 1000  # below the rows perturbed at most: every row counts
    rows = np.column_stack([rng.uniform(0, 10, n), rng.normal(0.0, 1.0, n), rng.normal(0.0, 2.0, n)])
    effects = feature_effects(QuadraticShift(), GapPem(), rows, 1)
    # 0.5 ((x + sd/2)^2 - (x - sd/2)^2) = x sd: the mean |x| sd; the linear 0.3 x2: 0.3 sd2
    sd1, sd2 = rows[:, 1].std(), rows[:, 2].std()
    assert effects[1] == pytest.approx(np.abs(rows[:, 1]).mean() * sd1, rel=1e-9)
    assert effects[2] == pytest.approx(0.3 * sd2, rel=1e-9)
    assert effects[0] == pytest.approx(0.0, abs=1e-9)
    # rows out of the PEM's sight (logit -inf) are left out of the curve: p = q = 0 there
    rows[:5, 0] = np.inf
    curve = feature_curve(QuadraticShift(), GapPem(), rows, ("gap_m", "a", "b"), 1)
    assert curve is not None and curve.name == "a" and curve.n_rows.sum() == n - 5


def test_the_proposal_is_found_inside_a_stage_s_samplers_and_the_pem_reads_no_state():
    glm = glm_with([0.0, 0.0, 1.0, 0.0, 0.0])
    samplers = StageSamplers(glm, GapPem(), radius_m=10.0, eps=0.1)
    assert state_proposal_of(samplers.defensive) is glm and state_proposal_of(glm) is glm
    assert state_proposal_of(GapPem()) is None


def test_bad_rows_are_refused_in_one_line():
    with pytest.raises(ValueError, match="C names"):
        feature_curve(glm_with([0.0] * 5), GapPem(), rows_of(10, 0), NAMES[:3], 1)
    with pytest.raises(ValueError, match="own_columns"):
        feature_effects(glm_with([0.0] * 5), GapPem(), rows_of(10, 0), 0)
