"""Asking the PEM about each distinct object row once (pemviz.pem.perception.repeated_rows): the grouping is exact or
declined, and a detector's answers with it are its answers without it, bit for bit (each row is computed on its own:
pemviz.pem.network.GridMLP)."""

from __future__ import annotations

import numpy as np
import pemviz.pem.perception as perception
import pytest
from pemviz.config import ExperimentConfig
from pemviz.pem.perception import PROBE_ROWS, repeated_rows
from pemviz.scenarios.problems import problem_for


def test_few_distinct_rows_are_grouped_exactly_and_many_are_declined():
    rng = np.random.default_rng(0)
    distinct = rng.normal(size=(6, 7))  # 7 rows of 6 values, feature by feature
    columns = distinct[:, rng.integers(0, 7, 4 * PROBE_ROWS + 3)]
    first, inverse = repeated_rows(columns)
    assert first.size == 7
    np.testing.assert_array_equal(columns[:, first][:, inverse], columns)
    assert repeated_rows(rng.normal(size=(6, 4 * PROBE_ROWS))) is None  # all distinct: the probe declines
    assert repeated_rows(columns[:, : 4 * PROBE_ROWS - 1]) is None  # too few rows to pay


def test_two_different_rows_with_one_key_are_declined():
    w1 = 1.0 + 0.6180339887498949  # the key's second weight: (w1, 0) and (0, 1) share a key
    a, b = np.array([w1, 0.0, 2.0]), np.array([0.0, 1.0, 2.0])
    columns = np.array([a, b] * (2 * PROBE_ROWS)).T
    assert perception._row_keys(columns[:, :2])[0] == perception._row_keys(columns[:, :2])[1]
    assert repeated_rows(columns) is None


@pytest.fixture(scope="module")
def cut_in_rows():
    """Object rows [R, G] of 2,048 cut-in rollouts at steps 5 and 60: many repeats, then none (a read-only array)."""
    pb = problem_for(ExperimentConfig.of(scenario="cut-in"))
    (batch,) = pb.stream(2048, pb.target, pb.target, np.random.default_rng(1))
    return pb.target, {t: batch.objects[:, t].reshape(-1, batch.objects.shape[-1]) for t in (5, 60)}


@pytest.mark.parametrize("t", [5, 60])
def test_a_detector_answers_the_same_with_and_without_grouping(cut_in_rows, t, monkeypatch):
    detector, by_step = cut_in_rows
    rows = np.array(by_step[t])
    columns = rows[rows[:, detector.visible] > 0.5][:, detector._code_columns(rows.shape[1])].T  # what it reads
    grouped = repeated_rows(np.ascontiguousarray(columns))
    assert (grouped is not None) == (t == 5)  # at step 5 the egos still share their states
    u = np.random.default_rng(2).random((rows.shape[0], 2))
    hit = rows[:, detector.visible] > 0.5

    def ask(rows_in):
        view = rows_in.view()
        view.flags.writeable = False
        return detector.detect_logit(view), detector.noise_draw(view, u[hit], hit)

    logit, (errors, log_density) = ask(rows)
    monkeypatch.setattr(perception, "repeated_rows", lambda raw: None)
    logit_0, (errors_0, log_density_0) = ask(rows.copy())
    np.testing.assert_array_equal(logit, logit_0)
    np.testing.assert_array_equal(errors, errors_0)
    np.testing.assert_array_equal(log_density, log_density_0)
