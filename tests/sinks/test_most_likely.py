"""One most likely failure: the console's (``MostLikelyFailure``), the panel's (``PanelRun``) and the recording's
(``RerunSink``) are the same rollout with the same log p under the PEM (T - 1 steps, as its weight), to 1e-9; the
console's *why* line states that log p's two parts apart: the log-probability of the detections and, where the PEM
mislocates, the log-density of the measurement errors."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from pemviz.app.runs import PanelRun
from pemviz.config import ExperimentConfig
from pemviz.engine.experiment import Experiment
from pemviz.scenarios.problems import problem_for
from pemviz.sinks.most_likely import MostLikelyFailure
from pemviz.sinks.recording import RerunSink

CONFIGS = {
    "braking": ExperimentConfig.of(
        n_stages=3,
        n_per_stage=100,
        n_final=100,
        ce_epochs=30,
        pretrain_epochs=50,
        pretrain_rollouts=100,
        seed=1,
        plain_fallback=0,  # the stages' failures: no retry, no plain rollout kept by the panel and the recording
    ),
    "cut-in": ExperimentConfig.of(
        scenario="cut-in",
        n_stages=2,
        n_per_stage=60,
        n_final=60,
        ce_epochs=30,
        pretrain_epochs=50,
        pretrain_rollouts=60,
        seed=2,
        plain_fallback=0,
    ),
}


@pytest.mark.parametrize("scene", sorted(CONFIGS))
def test_console_panel_and_recording_agree_on_the_most_likely_failure(scene, tmp_path):
    cfg = CONFIGS[scene]
    problem = problem_for(cfg)
    likely, panel = MostLikelyFailure(), PanelRun(1, cfg)
    panel.problem = problem
    recording = RerunSink.to_file(tmp_path / "r.rrd")
    try:
        Experiment(cfg, [likely, panel, recording], problem=problem).run()
    finally:
        recording.close()
    assert likely.batch is not None, "the run found no failure"
    best = panel.most_likely_failure
    assert (likely.stage, best.stage) == (best.stage, recording.most_likely.stage)
    assert math.isclose(likely.log_p, best.log_p_total, rel_tol=1e-9)
    assert math.isclose(likely.log_p, recording.most_likely_log_p, rel_tol=1e-9)
    assert math.isclose(float(likely.batch.log_p[0, :-1].sum()), likely.log_p, rel_tol=1e-12)  # T - 1 steps


def test_why_says_so_when_every_failure_drawn_is_impossible_under_the_pem():
    """A failure of log p = -inf (an event the PEM cannot produce) is not called "the most likely failure" with
    "-inf nats": the line says that every failure drawn is impossible under the PEM, then which errors decided it."""
    from pemviz.core.detectors import ConstantDetector
    from pemviz.pem import load_pem
    from pemviz.scenarios.cut_in.problem import cut_in_problem

    problem = cut_in_problem(load_pem())
    batch = problem.simulate(64, ConstantDetector(0.5), problem.target, np.random.default_rng(2))
    i = int(np.flatnonzero(problem.failed(batch))[0])
    likely = MostLikelyFailure()
    likely.batch, likely.stage, likely.log_p = batch.select(np.array([i])), 0, -math.inf
    line = likely.why(problem)
    assert line.startswith(
        "why: every failure drawn is impossible under the PEM (the log-probability of its "
        "detections or the log-density of its measurement errors is -inf), so none is likely; one "
        "of them (stage 0): "
    )
    assert "-inf nats" not in line and "decisive alone" in line
    likely.log_p = -42.25
    assert likely.why(problem).startswith("why: the most likely failure (stage 0; over all ")


WHY = re.compile(
    r"^why: the most likely failure \(stage (\d+); over all 99 steps: log-probability of its detections "
    r"(-?\d+\.\d) nats, "
    r"log-density of its measurement errors ([+-]\d+\.\d) nats\): "
)


def test_the_cut_in_why_line_states_the_detections_log_probability_and_the_errors_log_density_apart():
    """On cut-in failures (64 rollouts drawn by a detector that detects each car it can see half the time, weighed
    under the PEMs) the *why* line gives the failure's log p as two figures named for what they are: the
    log-probability of its detections, <= 0 and equal (to its printed rounding) to the sum of log p(a | x) over every
    car and the first T - 1 steps recomputed here from the detection PEM's own network, and the log-density of its
    measurement errors, the noise PEM's density (scipy.stats) of each detected car's error. Their sum is the log p by
    which the failure was chosen (the likeliest of the batch's failures, as before)."""
    from pemviz.core.counterfactuals import failure_log_p, failure_log_p_parts
    from pemviz.core.detectors import ConstantDetector, StageSamplers
    from pemviz.engine.events import RolloutsSampled
    from pemviz.pem import load_pem
    from pemviz.pem.store import load_noise_pem
    from pemviz.scenarios.cut_in.problem import cut_in_problem
    from pemviz.scenarios.cut_in.scenario import OBJECT_NAMES, SALIENT_COLUMNS
    from scipy.special import log_expit

    pem, noise = load_pem(), load_noise_pem("hetero-t")
    problem = cut_in_problem(pem)
    half = StageSamplers(ConstantDetector(0.5), problem.target).plain  # a car the camera cannot see: never detected
    batch = problem.simulate(64, half, problem.target, np.random.default_rng(2))
    rho = problem.robustness(batch, "classic")
    failed = problem.failed(batch, rho)
    assert failed.sum() >= 2 and np.isfinite(failure_log_p(batch, failed)[failed]).all()
    event = RolloutsSampled(4, "ce", batch, rho, {"classic": rho}, failed, batch.log_weight(), target=problem.target)
    likely = MostLikelyFailure()
    likely.on_rollouts_sampled(event)
    i = likely.best.row
    assert i == int(np.argmax(failure_log_p(batch, failed)))  # the choice: the largest log p, as before

    # independently: every car's detection or miss at the first T - 1 steps under the detection PEM's network
    rows = batch.objects[i, :-1].reshape(-1, len(OBJECT_NAMES))
    detected = batch.detected[i, :-1].reshape(-1)
    seen = rows[:, OBJECT_NAMES.index("visible")] > 0.5
    logit = np.full(rows.shape[0], -np.inf)
    logit[seen] = pem.logit(rows[seen][:, SALIENT_COLUMNS])
    want_detections = float(np.where(detected, log_expit(logit), log_expit(-logit)).sum())
    errors = batch.noise[i, :-1].reshape(-1, 2)[detected]
    want_errors = float(noise.log_prob(noise.features(rows[detected][:, SALIENT_COLUMNS]), errors).sum())
    assert want_detections <= 0.0 and detected.any()
    assert math.isclose(want_detections + want_errors, likely.log_p, rel_tol=1e-9)

    line = likely.why(problem)
    match = WHY.match(line)
    assert match is not None, line
    stage, detections, density = int(match[1]), float(match[2]), float(match[3])
    assert stage == 4 and detections <= 0.0
    assert detections == float(f"{want_detections:.1f}") and density == float(f"{want_errors:.1f}")
    assert "log p " not in line and "probability 0" not in line
    got_detections, got_errors = failure_log_p_parts(batch, problem.target)
    assert np.all(got_detections <= 0.0)
    assert math.isclose(float(got_detections[i]), want_detections, rel_tol=1e-9)
    assert math.isclose(float(got_errors[i]), want_errors, rel_tol=1e-9)
    np.testing.assert_allclose(got_detections + got_errors, batch.log_likelihood(), rtol=1e-9)


def test_a_density_above_one_is_a_positive_log_density_and_a_scene_without_errors_states_the_probability_alone():
    """The words of the two parts: a positive log-density keeps its sign and its name; on the braking scenario
    (detections only, no measurement errors) the log p is the log-probability of the detections as it is, and no
    density is named. The braking run prints no *why* line (its rollouts have no object rows), as before."""
    from pemviz.core.counterfactuals import LogPParts, failure_log_p_parts
    from pemviz.engine.events import RolloutsSampled

    words = LogPParts(-63.21, 12.44).words()
    assert words == "log-probability of its detections -63.2 nats, log-density of its measurement errors +12.4 nats"
    assert LogPParts(-63.21, 12.44).total == pytest.approx(-50.77)

    cfg = CONFIGS["braking"]
    problem = problem_for(cfg)
    batch = problem.simulate(200, problem.target, problem.target, np.random.default_rng(0))
    assert batch.noise is None
    detections, errors = failure_log_p_parts(batch, None)  # no target needed: log p holds detections only
    assert errors is None
    np.testing.assert_array_equal(detections, batch.log_likelihood())
    assert np.all(detections <= 0.0)
    rho = problem.robustness(batch, "classic")
    failed = np.zeros(batch.n, bool)
    failed[int(np.argmin(rho))] = True  # the least robust, called a failure here: the words need no failure
    likely = MostLikelyFailure()
    likely.on_rollouts_sampled(RolloutsSampled(1, "ce", batch, rho, {"classic": rho}, failed, batch.log_weight()))
    parts = likely.parts(problem)
    assert parts.errors is None and parts.detections == likely.log_p
    assert parts.words() == f"log-probability of its detections {likely.log_p:.1f} nats"
    assert likely.why(problem) is None
