"""The state features a scene reports (pemviz.core.features): the crossing's, through the library's tracker, replayed
from a batch's events; a single-rollout simulator's, through pemviz.scenarios.simulate and state_replay; and
check_scenario's features check, passing on the crossing (tests/scenarios/test_crossing_scene.py) and failing, in one
line naming the feature, rollout and step, on scenes whose features are not finite or depend on the chunk size."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pemviz.core.detectors import ConstantDetector
from pemviz.core.features import check_features, feature_replay, replay_features
from pemviz.scenarios import simulate, state_replay
from pemviz.scenarios.crossing.problem import crossing_problem
from pemviz.scenarios.crossing.scene import FEATURE_NAMES, OBJECT_NAMES, BatchedCrossing, CrossingParams
from pemviz.scenarios.registry import Scenario
from pemviz.scenarios.toy import ToyBraking
from pemviz.stack import tracker
from pemviz.testing import ConformanceError, check_scenario


@pytest.fixture(scope="module")
def crossing():
    problem = crossing_problem()
    return problem, problem.simulate(48, problem.target, problem.target, np.random.default_rng(3))


def test_the_crossing_reports_the_trackers_state_of_each_pedestrian_at_every_step(crossing):
    problem, batch = crossing
    f = problem.features(batch, None)
    assert f.ego.shape == (48, 50, len(FEATURE_NAMES)) and f.objects.shape == (48, 50, 2, len(tracker.FEATURE_NAMES))
    assert f.feature_names == FEATURE_NAMES and f.object_feature_names == tracker.FEATURE_NAMES
    # the tracker's confirmed flag is the one the object rows report (the AEB's input), at every step
    np.testing.assert_array_equal(
        f.object_feature("track_confirmed"), batch.objects[..., OBJECT_NAMES.index("tracked")]
    )
    np.testing.assert_array_equal(f.feature("ego_speed_mps"), batch.signal("ego_speed_mps"))
    np.testing.assert_allclose(f.feature("time_s")[0], 0.1 * np.arange(50), rtol=1e-12)
    age = f.object_feature("track_age_steps")
    assert (age[:, 0] == 0).all() and age.max() >= 40  # no track before the first step; tracks kept for 4 s
    assert check_features(problem.features, batch, 7) is None


def test_the_features_are_those_of_the_same_rollouts_simulated_in_another_batch(crossing):
    problem, batch = crossing
    part = batch.select(np.array([5, 17]))
    f_all, f_part = problem.features(batch, None), problem.features(part, 1)
    np.testing.assert_array_equal(f_part.objects, f_all.objects[[5, 17]])
    assert replay_features(lambda n: object(), batch.detected, None) is None  # a simulator that reports none


class NotFinite(BatchedCrossing):
    def state_features(self):
        ego, objects = super().state_features()
        if self.t == 3:
            objects[0, 1, tracker.FEATURE_NAMES.index("track_range_m")] = np.nan
        return ego, objects


class ChunkDependent(BatchedCrossing):
    def state_features(self):
        ego, objects = super().state_features()
        ego[:, 0] = self.v.mean()  # every rollout's speed averaged: depends on which rollouts are stepped together
        return ego, objects


def broken(sim: type) -> Scenario:
    def factory(config, params):
        p = params or CrossingParams()
        return dataclasses.replace(crossing_problem(p), features=feature_replay(lambda n: sim(p, n)))

    return Scenario("broken-crossing", "the crossing with broken features", CrossingParams, factory)


@pytest.mark.parametrize(
    ("sim", "says"),
    [
        (
            NotFinite,
            "check_scenario('broken-crossing'): features: rollouts drawn by the target (PEM): object feature "
            "'track_range_m' is nan at rollout 0, step 3, object 1 (every feature must be finite)",
        ),
        (
            ChunkDependent,
            "check_scenario('broken-crossing'): features: rollouts drawn by the target (PEM): ego feature "
            "'ego_speed_mps' at rollout 0, step ",
        ),
    ],
)
def test_check_scenario_names_the_broken_feature(sim, says):
    with pytest.raises(ConformanceError) as err:
        check_scenario(broken(sim))
    message = str(err.value)
    assert message.startswith(says) and "\n" not in message
    if sim is ChunkDependent:
        assert "replayed in chunks of 21 rollouts" in message and message.endswith("own events)")


class MissCounter:
    """A single-rollout simulator (pemviz.scenarios.simulate) whose controller remembers the steps since the last
    detection: its state feature ``since`` (ego, F = 1; no object feature)."""

    observation_names, feature_names, object_feature_names = ("gap_m",), ("since",), ()

    def __init__(self):
        self.reset()

    def reset(self):
        self.gap, self.since = 20.0, 0

    def observation(self):
        return np.array([self.gap])

    def state_features(self):  # ego [F], objects [M = 1, 0]
        return np.array([float(self.since)]), np.zeros((1, 0))

    def step(self, detected):
        self.since = 0 if detected else self.since + 1
        self.gap -= 0.1


class NoThirdMiss:
    """A sampler that reads the state: a fair coin, but certain to detect after two misses in a row."""

    reads_state = True

    def detect_logit(self, rows):  # rows [R, 1 + 1]: the gap, then ``since``
        return np.where(rows[:, 1] >= 2.0, 50.0, 0.0)


def test_a_single_rollout_simulator_reports_its_state_to_the_sampler_and_to_the_problem():
    target = ConstantDetector(0.5)
    batch = simulate(MissCounter, 64, NoThirdMiss(), target, np.random.default_rng(5), 30)
    misses = ~batch.detected[:, :, 0]
    three = misses[:, 2:] & misses[:, 1:-1] & misses[:, :-2]
    assert not three.any() and (misses[:, 1:] & misses[:, :-1]).any()  # the sampler read `since` at every step
    features = state_replay(MissCounter)(batch, None)
    since = np.zeros((64, 30))  # by hand: misses in a row before each step
    for t in range(1, 30):
        since[:, t] = np.where(misses[:, t - 1], since[:, t - 1] + 1.0, 0.0)
    np.testing.assert_array_equal(features.feature("since"), since)
    assert features.objects.shape == (64, 30, 1, 0) and features.feature_names == ("since",)
    assert check_features(state_replay(MissCounter), batch, 7) is None
    assert state_replay(lambda: ToyBraking())(batch, None) is None  # a simulator that reports none
