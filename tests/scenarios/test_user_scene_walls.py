"""The four walls a user's own multi-object scene met, each with its regression test, on a crosswalk written from the
guide alone (:mod:`tests.scenarios.user_crosswalk`): a hidden object's ``-inf`` logit through every file round trip,
the target's curve without ``curve_rows``, a first observation not named ``gap_m``, and the scene's own object names
in what pemviz says. Plus the recording of a problem without signal ranges (no ``agm`` to draw)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.core.problem_view import object_label
from pemviz.core.problems import Problem
from pemviz.engine.experiment import Experiment, RobustnessByMetric
from pemviz.io.rollout_estimate import estimate_rollouts
from pemviz.io.rollout_format import RolloutMeta, json_float
from pemviz.io.rollouts import read_rollouts
from pemviz.scenarios import register
from pemviz.scenarios.registry import unregister
from pemviz.sinks.most_likely import MostLikelyFailure
from pemviz.sinks.rollouts import RolloutSink
from pemviz.testing import check_scenario
from scipy.special import expit

from .user_crosswalk import SCENARIO, Crosswalk, T, crosswalk_problem


@pytest.fixture
def crosswalk():
    register(SCENARIO, replace=True)
    yield SCENARIO.name
    unregister(SCENARIO.name)


def test_the_user_scene_passes_the_conformance_kit(crosswalk, tmp_path):
    """At 13 m/s (stopping takes 14 m of the 20 m it sees) the kit's naive50 run sees failures (12 of 500): its
    rollout file, where the hidden pedestrian's -inf logit is in every rollout, re-estimates a weighted answer."""
    report = check_scenario(crosswalk, params={"speed_mps": 13.0}, folder=tmp_path)
    assert report.passed == ("schema", "problem", "determinism", "rollout-file", "recording")
    assert (tmp_path / f"{crosswalk}-naive50.parquet").is_file()
    assert not (tmp_path / f"{crosswalk}-adaptive.parquet").exists()  # naive50 saw failures: no second run


def test_first_observation_of_any_name_round_trips_and_re_estimates(tmp_path):
    problem = crosswalk_problem()
    sink = RolloutSink(tmp_path / "r.parquet")
    sink.problem = problem
    done = Experiment(
        ExperimentConfig.of(seed=3, n_per_stage=100, n_final=400, plain_fallback=0), [sink], problem=problem
    ).run()
    side = json.loads((tmp_path / "r.rollouts.json").read_text())
    assert side["h_column"] == "dist_m" and side["observation_columns"][0] == "dist_m"
    assert "gap_m" not in side["observation_columns"]
    assert side["dt_s"] == 1.0 and "dt_s_unknown" in side["provenance"]  # the problem gave no step
    data = read_rollouts(tmp_path / "r.parquet")
    assert data.meta.columns[0] == "dist_m"
    again = estimate_rollouts(data, data.log_p, data.log_q, log_p_seen=side["provenance"]["estimate"]["log_p_seen"])
    assert again.estimate.log_mu_hat == pytest.approx(done.final.estimate.log_mu_hat, rel=1e-9, abs=1e-9)
    assert np.isfinite(data.log_p).all()  # a hidden pedestrian's miss has log p 0 (its logit is -inf)
    batch = problem.simulate(200, problem.target, problem.target, np.random.default_rng(0))
    hidden = batch.objects[:, :, 1, 1] < 0.5
    assert hidden.any() and not batch.detected[:, :, 1][hidden].any()


def test_a_sidecar_minus_infinity_reads_back_as_a_number(tmp_path):
    """The sidecar writes a non-finite number as text (JSON has none); the estimate reads it back (a TypeError
    traceback before)."""
    assert json_float("-inf") == -np.inf and json_float(-3.5) == -3.5 and json_float(None) is None
    assert np.isnan(json_float("nan")) and json_float(True) is None and json_float("x") is None
    meta = RolloutMeta("G[0,9](d >= 2)", 0.1, provenance={"estimate": {"log_p_seen": float("-inf")}})
    back = RolloutMeta.from_json(json.loads(json.dumps(meta.to_json())))
    assert back.provenance["estimate"]["log_p_seen"] == "-inf"
    problem = crosswalk_problem()
    sink = RolloutSink(tmp_path / "r.parquet")
    sink.problem = problem
    done = Experiment(
        ExperimentConfig.of(seed=1, n_per_stage=100, n_final=300, plain_fallback=0), [sink], problem=problem
    ).run()
    data = read_rollouts(tmp_path / "r.parquet")
    again = estimate_rollouts(data, data.log_p, data.log_q, log_p_seen="-inf")
    assert again.estimate.log_mu_hat == pytest.approx(done.final.estimate.log_mu_hat, rel=1e-9, abs=1e-9)


def test_the_target_curve_needs_no_curve_rows():
    """Without ``curve_rows`` the curve is the first object's start row moved along the grid: the camera reads the
    ``visible`` column, 1 for pedestrian A, so the curve is expit(4 - h / 4) (an IndexError traceback before)."""
    problem = crosswalk_problem()
    curve = problem.target_curve()
    np.testing.assert_allclose(curve, expit(4.0 - problem.curve_grid / 4.0), rtol=1e-12)


def test_a_curve_the_target_cannot_read_says_what_to_give():
    class Wide:  # reads a column the scene's rows do not have
        def detect_logit(self, rows):
            return rows[:, 5]

    problem = crosswalk_problem()
    bad = Problem(problem.name, problem.simulate, Wide(), problem.formula, problem.signals)
    with pytest.raises(ValueError, match=r"crosswalk: the target's detection curve .*IndexError.* curve_rows="):
        bad.target_curve()


def test_the_scene_names_its_objects():
    assert object_label(("pedestrian A", "pedestrian B"), 1) == "pedestrian B"
    assert object_label((), 3) == "object 3" and object_label(None, 0) == "object 0"
    problem = crosswalk_problem()
    assert problem.view.object_label(0) == "pedestrian A"
    likely = MostLikelyFailure()
    config = ExperimentConfig.of(seed=0, n_per_stage=100, n_final=400, plain_fallback=0)  # its stages see failures
    Experiment(config, [likely], problem=problem).run()
    why = likely.why(problem)
    assert why is not None and "pedestrian A missed at step" in why and "object 0" not in why


def test_a_problem_without_signal_ranges_has_no_agm_to_draw():
    problem = crosswalk_problem()
    batch = problem.simulate(4, problem.target, problem.target, np.random.default_rng(0))
    by_metric = RobustnessByMetric(problem, batch)
    assert "agm" not in list(by_metric) and set(by_metric) == {"classic", "smooth-cumulative"}
    with_ranges = RobustnessByMetric(
        Problem(
            problem.name,
            problem.simulate,
            problem.target,
            problem.formula,
            problem.signals,
            signal_ranges={"d": (-5.0, 40.0)},
        ),
        batch,
    )
    assert "agm" in list(with_ranges)
    assert batch.observations.shape[1] == T and isinstance(Crosswalk.observation_names[0], str)
