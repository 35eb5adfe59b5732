"""Each rollout's severity (min distance, impact speed at contact) and p(severity | failure), the failures' severity
weighed by their shares of p: hand-computed cases, agreement with the braking scene's own ``severity()`` number for
number, the cut-in's closing speed against its observed speeds, and a small run's distribution by hand."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.core.rollouts import RolloutBatch
from pemviz.core.severity import (
    FailureSeverity,
    SeverityScale,
    contact_level,
    failure_severity,
    rollout_severity,
    severity_of_signal,
    share_text,
)
from pemviz.engine.events import FinalEstimate
from pemviz.engine.experiment import Experiment
from pemviz.scenarios.braking.batched import replay
from pemviz.scenarios.braking.failures import severity
from pemviz.scenarios.braking.simulator import OBSERVATION_NAMES, BrakingParams
from pemviz.scenarios.problems import problem_for
from pemviz.sinks.console import ConsoleSink, final_lines
from pemviz.sinks.population import FailureGroups, grouping_document

GAP = SeverityScale("d", "gap", "m", (1.5, 1.0, 0.5, 0.0), margin=2.0)


@pytest.fixture(scope="module")
def braking():
    return problem_for(ExperimentConfig.of())


def braking_batch(detected: np.ndarray) -> RolloutBatch:
    """Rollouts of the braking scene driven by fixed detections (its batched twin), log p = log q = 0."""
    obs = replay(None, detected)
    zeros = np.zeros(detected.shape)
    return RolloutBatch(obs, detected, zeros, zeros, tuple(OBSERVATION_NAMES))


# ------------------------------------------------------------------------------ one rollout's severity


def test_min_distance_and_impact_speed_by_hand():
    signal = np.array(
        [
            [5.0, 3.0, 1.0, 0.5, 0.2],  # contact (<= 0.7) first at step 3: (1.0 - 0.5) / 0.05 = 10 m/s
            [5.0, 4.0, 3.0, 3.0, 4.0],  # no contact
            [2.0, 1.0, 0.7, 0.7, 0.9],
        ]
    )  # at the level itself: contact at step 2, (1.0 - 0.7) / 0.05 = 6
    dist, speed = severity_of_signal(signal, 0.7, 0.05)
    np.testing.assert_array_equal(dist, [0.2, 3.0, 0.7])
    assert speed[0] == pytest.approx(10.0, rel=1e-12) and speed[2] == pytest.approx(6.0, rel=1e-12)
    assert math.isnan(speed[1])
    assert dist.dtype == speed.dtype == np.float64


def test_a_rollout_in_contact_at_its_first_step_or_a_bad_signal_is_refused():
    with pytest.raises(ValueError, match="rollout 1 is in contact at step 0"):
        severity_of_signal(np.array([[3.0, 2.0], [0.5, 0.4]]), 0.7, 0.05)
    with pytest.raises(ValueError, match="rollout 0 has a non-finite distance"):
        severity_of_signal(np.array([[3.0, np.nan]]), 0.7, 0.05)
    with pytest.raises(ValueError, match=r"float \[N, T >= 1\]"):
        severity_of_signal(np.zeros(4), 0.7, 0.05)
    with pytest.raises(ValueError, match="dt_s"):
        severity_of_signal(np.ones((1, 3)), 0.7, 0.0)


def test_braking_rollouts_agree_with_the_scene_s_severity_number_for_number(braking):
    # 300 replays with detections missed at random, many of them into contact: the gap, the contact at 0.7 m and the
    # closing speed over the step into it are Severity's, bit for bit
    rng = np.random.default_rng(3)
    p = BrakingParams()
    detected = rng.random((300, p.n_steps)) < rng.uniform(0.0, 0.9, (300, 1))
    batch = braking_batch(detected)
    dist, speed = rollout_severity(braking, batch)
    want = [severity(batch.signal("gap_m")[i], p) for i in range(batch.n)]
    np.testing.assert_array_equal(dist, [w.min_gap_m for w in want])
    np.testing.assert_array_equal(speed, [w.contact_speed_mps for w in want])  # NaN where no contact, alike
    assert contact_level(braking) == p.contact_gap_m == 0.7
    contact = np.isfinite(speed)
    assert 30 < contact.sum() < 300 and (speed[contact] > 0).all()


def test_cut_in_impact_speed_is_the_ego_s_closing_speed_on_the_car_it_meets():
    # the cut-in car missed for a while: contact is a clearance <= 0 (the boxes meet); the closing speed over the
    # step into it is the ego's speed minus the front car's at the step before, to 0.1 m/s (the cut-in car turns)
    from pemviz.scenarios.cut_in.batched import replay as replay_cut_in
    from pemviz.scenarios.cut_in.problem import cut_in_params
    from pemviz.scenarios.cut_in.scenario import OBSERVATION_NAMES as NAMES

    problem = problem_for(ExperimentConfig.of(scenario="cut-in"))
    p = cut_in_params("moderate")
    rng = np.random.default_rng(0)
    detected = np.ones((80, p.n_steps, p.n_objects), bool)
    for i in range(80):
        start = rng.integers(0, 40)
        detected[i, start : start + rng.integers(0, 80), 0] = False
    obs, _ = replay_cut_in(p, detected)
    batch = RolloutBatch(obs, detected, np.zeros(obs.shape[:2]), np.zeros(obs.shape[:2]), tuple(NAMES))
    dist, speed = rollout_severity(problem, batch)
    clearance = obs[:, :, NAMES.index("clearance_m")]
    np.testing.assert_array_equal(dist, clearance.min(axis=1))
    contact = np.isfinite(speed)
    assert contact_level(problem) == 0.0 and contact.sum() >= 10
    assert np.array_equal(contact, (clearance <= 0).any(axis=1))
    rows = np.flatnonzero(contact)
    t = (clearance[rows] <= 0).argmax(axis=1)
    closing = obs[rows, t - 1, NAMES.index("ego_speed_mps")] - obs[rows, t - 1, NAMES.index("front_speed_mps")]
    np.testing.assert_allclose(speed[rows], closing, atol=0.1)


# ------------------------------------------------------------------------------ p(severity | failure)


def test_the_distribution_of_four_failures_by_hand():
    # shares 0.4, 0.3, 0.2, 0.1: no contact, 1 m/s, 3 m/s, 7.5 m/s; min gaps sorted 0.3 (0.2), 0.6 (0.1), 1.2 (0.3):
    # the cumulative share first reaches 1/2 at 1.2 m
    sev = failure_severity(
        GAP, 0.7, np.log([0.4, 0.3, 0.2, 0.1]), np.array([1.9, 1.2, 0.3, 0.6]), np.array([np.nan, 1.0, 3.0, 7.5])
    )
    np.testing.assert_allclose(sev.shares(), [0.4, 0.3, 0.2, 0.1], rtol=1e-12)
    assert sev.shares().sum() == pytest.approx(1.0, rel=1e-14)
    assert sev.counts().tolist() == [1, 1, 1, 1] and sev.labels() == ["no contact", "0-2 m/s", "2-5 m/s", "> 5 m/s"]
    assert sev.median_min_distance() == 1.2 and sev.covered == pytest.approx(1.0, rel=1e-14)
    assert sev.line() == (
        "failures by impact speed, share of p (failures; contact: gap <= 0.7 m): no contact 40 % "
        "(1), 0-2 m/s 30 % (1), 2-5 m/s 20 % (1), > 5 m/s 10 % (1); median min gap 1.20 m"
    )
    # a speed on an edge falls in the bin above it: [0, 2), [2, 5), [5, inf)
    edge = failure_severity(GAP, 0.7, np.log([0.5, 0.5]), np.array([0.5, 0.5]), np.array([2.0, 5.0]))
    assert edge.counts().tolist() == [0, 0, 1, 1]


def test_failures_not_kept_are_left_out_and_the_others_renormalised():
    sev = failure_severity(
        GAP,
        0.7,
        np.log([0.4, 0.3, 0.2, 0.1]),
        np.array([1.9, np.nan, 0.3, 0.6]),
        np.array([np.nan, np.nan, 3.0, 7.5]),
        kept=np.array([True, False, True, True]),
    )
    np.testing.assert_allclose(sev.shares(), [0.4 / 0.7, 0.0, 0.2 / 0.7, 0.1 / 0.7], rtol=1e-12)
    assert (sev.n, sev.n_failures) == (3, 4) and sev.covered == pytest.approx(0.7, rel=1e-12)
    # kept, sorted: 0.3 (2/7), 0.6 (1/7): 3/7 < 1/2; then 1.9 (4/7)
    assert math.isnan(sev.min_distance[1]) and sev.median_min_distance() == 1.9
    assert sev.line().endswith("(the 3 kept of 4 failures: 70 % of p)")


def test_inconsistent_arrays_and_speeds_are_refused():
    with pytest.raises(ValueError, match="must all be"):
        failure_severity(GAP, 0.7, np.zeros(2), np.ones(3), np.ones(2))
    with pytest.raises(ValueError, match="positive number of m/s"):
        failure_severity(GAP, 0.7, np.zeros(1), np.ones(1), np.array([-1.0]))
    with pytest.raises(ValueError, match="finite min distance"):
        failure_severity(GAP, 0.7, np.zeros(1), np.array([np.nan]), np.array([np.nan]))


def test_share_text_never_rounds_a_share_to_0_or_100_percent():
    assert [share_text(x) for x in (0.0, 1.0, 0.5, 0.972, 0.99998, 2.24e-8, 1 - 3e-16, 1 - 1e-9)] == [
        "0 %",
        "100 %",
        "50 %",
        "97.2 %",
        "99.998 %",
        "2.24e-06 %",
        "100 %",
        "99.9999999 %",
    ]


def test_a_small_run_s_failures_by_share_match_a_hand_computation(braking):
    # a braking run that keeps every rollout: each failure's severity is the scene's severity() of its rollout, and
    # each bin's share the sum of its failures' shares; the console prints the line under the severity curve
    cfg = ExperimentConfig.of(
        n_stages=3, n_per_stage=60, n_final=200, ce_epochs=30, pretrain_epochs=50, pretrain_rollouts=40, seed=4
    )
    groups = FailureGroups(braking.drawing, braking)
    console = ConsoleSink(io.StringIO(), io.StringIO())
    console.failures = groups
    sampled, finals = {}, []

    def keep(event):
        if type(event).__name__ == "RolloutsSampled":
            sampled[event.stage] = event
        elif isinstance(event, FinalEstimate):
            finals.append(event)

    Experiment(cfg, [groups, console, keep], problem=braking).run()
    sev = groups.grouping.severity
    shares = finals[0].failures
    assert isinstance(sev, FailureSeverity) and sev.n == sev.n_failures == shares.n > 20
    assert sev.counts()[0] > 20 and sev.counts()[1:].sum() >= 5  # failures with and without contact
    want = [
        severity(sampled[s].batch.signal("gap_m")[i], braking.drawing.params)
        for s, i in zip(shares.stage, shares.index, strict=False)
    ]
    np.testing.assert_array_equal(sev.min_distance, [w.min_gap_m for w in want])
    np.testing.assert_array_equal(sev.impact_speed, [w.contact_speed_mps for w in want])
    share = np.exp(shares.log_share)
    speed = np.array([w.contact_speed_mps for w in want])
    by_hand = [
        share[np.isnan(speed)].sum(),
        share[speed < 2].sum(),
        share[(speed >= 2) & (speed < 5)].sum(),
        share[speed >= 5].sum(),
    ]
    np.testing.assert_allclose(sev.shares(), by_hand, rtol=1e-9, atol=1e-300)
    assert sev.shares().sum() == pytest.approx(1.0, rel=1e-12)
    order = np.argsort(sev.min_distance, kind="stable")
    median = sev.min_distance[order][np.searchsorted(np.cumsum(share[order]), 0.5)]
    assert sev.median_min_distance() == median
    printed = console.out.getvalue().splitlines()
    assert sev.line() in printed and printed.index(sev.line()) > printed.index(finals[0].severity.lines()[-1])
    assert sev.line() in final_lines(finals[0], cfg, braking.exact_log_p, None, sev)
    doc = grouping_document(groups.grouping)["severity"]
    assert [b["share"] for b in doc["bins"]] == sev.shares().tolist() and doc["contact"] == 0.7
    assert doc["n"] == doc["n_kept"] == shares.n and doc["median_min_distance"] == median
    assert [(b["lo"], b["hi"]) for b in doc["bins"]] == [(None, None), (0.0, 2.0), (2.0, 5.0), (5.0, None)]
