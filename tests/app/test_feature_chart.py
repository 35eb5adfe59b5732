"""The panel's chart of a state proposal's q(detect) against the PEM over the feature that moved it most
(pemviz.app.feature_chart), without a browser: the chart holds the newest stage's curve as computed, titled with its
feature, and a PanelRun hearing a small crossing state run keeps a curve for every stage its proposal drew."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from pemviz.app.feature_chart import fill_feature_plot
from pemviz.app.runs import PanelRun
from pemviz.config import ExperimentConfig
from pemviz.core.feature_view import FeatureCurve
from pemviz.engine.experiment import Experiment
from pemviz.scenarios.problems import problem_for
from scipy.special import expit


def handle() -> SimpleNamespace:
    """A stand-in for viser's uPlot handle: the fill function only assigns its attributes."""
    return SimpleNamespace(title="", series=(), data=(), scales={}, axes=(), visible=False)


def test_the_chart_shows_the_newest_stage_s_q_and_pem_over_its_feature_and_hides_without_one():
    record = PanelRun(1, ExperimentConfig.of(scenario="crossing", method="state"))
    plot = handle()
    fill_feature_plot(plot, record)
    assert plot.visible is False  # no curve: hidden
    names = ("range_m", "object track_misses")

    def curve(x, q, p) -> FeatureCurve:
        return FeatureCurve(names[1], 1, names, np.array([0.01, 0.56]), *map(np.array, (x, q, p)), np.array([9, 3, 1]))

    record.feature_curves = {
        1: ("ce", curve([0.0, 1.0, 2.0], [0.5, 0.6, 0.7], [0.9, 0.9, 0.9])),
        3: ("final", curve([0.0, 1.0, 2.0], [0.64, 0.79, 0.88], [0.904, 0.906, 0.91])),
    }
    fill_feature_plot(plot, record)
    assert plot.visible is True
    assert plot.title == "q(detect) vs PEM over object track_misses"
    assert [s["label"] for s in plot.series] == ["object track_misses", "q(detect)", "PEM p(detect)"]
    np.testing.assert_array_equal(plot.data[0], [0.0, 1.0, 2.0])
    np.testing.assert_array_equal(plot.data[1], [0.64, 0.79, 0.88])  # the final batch's, not stage 1's
    np.testing.assert_array_equal(plot.data[2], [0.904, 0.906, 0.91])
    assert plot.caption_text.startswith("final batch: ") and "0.56 nats" in plot.caption_text
    assert "13 object rows" in plot.caption_text


def test_a_panel_run_keeps_the_curve_of_every_stage_its_state_proposal_drew():
    cfg = ExperimentConfig.of(
        scenario="crossing", method="state", n_per_stage=20, n_final=20, n_stages=2, seed=5, plain_fallback=0
    )
    problem = problem_for(cfg)
    record = PanelRun(1, cfg)
    record.problem = problem
    Experiment(cfg, [record], problem=problem).run()
    assert sorted(record.feature_curves) == [1, 2, 3]  # pretraining draws from the PEM: no curve
    assert [record.feature_curves[k][0] for k in (1, 2, 3)] == ["ce", "ce", "final"]
    kind, last = record.feature_curves[3]
    assert last.name in last.names and last.effect == last.effects.max() > 0.0
    assert np.all((last.q_detect >= 0) & (last.q_detect <= 1) & (last.p_detect >= 0) & (last.p_detect <= 1))
    plot = handle()
    fill_feature_plot(plot, record)
    np.testing.assert_array_equal(plot.data[1], last.q_detect)
    assert plot.axes[0]["label"] == last.name
    # the kept rollouts show each object's p and q: the state proposal is asked with the replayed features (it read
    # them as it drew), the PEM with the rows' own columns
    assert record.trajectories and record.most_likely_failure is not None  # seed 5 fails in stage 2 and the final
    for t in record.trajectories:
        rows = t.batch.object_rows[0]
        pem = expit(problem.target.detect_logit(rows.reshape(-1, rows.shape[-1]))).reshape(rows.shape[:2])
        np.testing.assert_array_equal(t.object_p, pem)
        assert t.object_q is not None and t.object_q.shape == pem.shape
    drawn = [t for t in record.trajectories if t.stage > 0]  # the proposal's: q moved from p somewhere
    assert drawn and all(np.max(np.abs(t.object_q - t.object_p)) > 1e-3 for t in drawn)
