"""The cut-in's state features (BatchedCutIn.state_features, pemviz.core.features): the ACC's inputs are those the
ACC acts on (its acceleration on a step with no measurement is the one the features announced), each car's tracker
range and time to collision are the true bumper gap's when every car is measured exactly, reading them changes no
simulated number, and they pass the kit's features check (finite, replayed the same, at any chunk size)."""

from __future__ import annotations

import numpy as np
import pytest
from pemviz.core.features import check_features
from pemviz.scenarios.cut_in.batched import FEATURE_NAMES, BatchedCutIn
from pemviz.scenarios.cut_in.problem import cut_in_params, cut_in_problem
from pemviz.scenarios.cut_in.scenario import OBSERVATION_NAMES
from pemviz.stack import tracker

P = cut_in_params("moderate")
OBS = OBSERVATION_NAMES.index


def ego(name: str) -> int:
    return FEATURE_NAMES.index(name)


def obj(name: str) -> int:
    return tracker.FEATURE_NAMES.index(name)


def events(seed: int, n: int) -> np.ndarray:
    """Detections [T, n, M]: rollout 0 sees every car, rollout 1 each with probability 0.7, rollout 2 every car on even
    steps and none on odd ones."""
    rng = np.random.default_rng(seed)
    det = np.ones((P.n_steps, n, P.n_objects), bool)
    det[:, 1] = rng.random((P.n_steps, P.n_objects)) < 0.7
    det[1::2, 2] = False
    return det


def test_on_a_step_with_no_measurement_the_acc_does_what_the_features_announced():
    sim, det = BatchedCutIn(P, 3), events(0, 3)
    checked = 0
    for t in range(P.n_steps):
        e, _ = sim.state_features()
        sim.step(det[t], np.zeros((3, P.n_objects, 2)))
        obs = sim.observation()
        for i in np.flatnonzero(~det[t].any(axis=1)):  # the ACC decided on the predicted tracks alone
            assert obs[i, OBS("ego_accel_mps2")] == e[i, ego("acc_accel_mps2")]
            assert (obs[i, OBS("followed_index")] >= 0) == e[i, ego("acc_has_lead")]
            checked += 1
    assert checked >= 45  # rollout 2's odd steps, and rollout 1's where it missed every car


def test_measured_exactly_the_trackers_range_and_the_accs_gap_are_the_true_gap():
    sim = BatchedCutIn(P, 1)
    compared = 0
    for t in range(P.n_steps):
        e, o = sim.state_features()
        obs = sim.observation()[0]
        front = int(obs[OBS("front_index")])
        if front >= 0 and obs[OBS("followed_index")] == front and e[0, ego("acc_has_lead")] == 1.0:
            gap, closing = obs[OBS("gap_m")], obs[OBS("ego_speed_mps")] - obs[OBS("front_speed_mps")]
            assert o[0, front, obj("track_range_m")] == pytest.approx(gap, abs=0.15)  # bumper to bumper
            assert e[0, ego("acc_gap_m")] == pytest.approx(gap + P.vehicle_length_m, abs=0.15)  # centre to centre
            # the velocity estimate lags the hard braking after the cut-in by about 0.1 m/s
            assert e[0, ego("acc_closing_mps")] == pytest.approx(closing, abs=0.15)
            ttc = o[0, front, obj("track_ttc_s")]
            assert ttc == pytest.approx(min(gap / closing, 10.0) if closing > 0.0 else 10.0, rel=0.1, abs=0.05)
            compared += 1
        assert e[0, ego("time_s")] == pytest.approx(0.1 * t, rel=1e-12)
        sim.step(np.ones((1, P.n_objects), bool), np.zeros((1, P.n_objects, 2)))
    assert compared >= 60  # the cut-in car is followed from soon after it cuts in to the end


def test_reading_the_features_changes_no_simulated_number():
    det = events(1, 3)
    rng = np.random.default_rng(2)
    noise = rng.normal(0.0, 1.5, (P.n_steps, 3, P.n_objects, 2))
    read, plain = BatchedCutIn(P, 3), BatchedCutIn(P, 3)
    for t in range(P.n_steps):
        read.state_features()
        np.testing.assert_array_equal(read.observation(), plain.observation())
        np.testing.assert_array_equal(read.objects(), plain.objects())
        read.step(det[t], noise[t])
        plain.step(det[t], noise[t])


def test_the_cut_in_passes_the_features_check_of_the_kit():
    from pemviz.pem import load_pem

    problem = cut_in_problem(load_pem())
    batch = problem.simulate(24, problem.target, problem.target, np.random.default_rng(5))
    f = problem.features(batch, None)
    assert f.ego.shape == (24, P.n_steps, len(FEATURE_NAMES))
    assert f.objects.shape == (24, P.n_steps, P.n_objects, len(tracker.FEATURE_NAMES))
    np.testing.assert_array_equal(f.feature("ego_speed_mps"), batch.signal("ego_speed_mps"))
    np.testing.assert_array_equal(
        f.object_feature("track_confirmed"), batch.objects[..., batch.row_names.index("tracked")]
    )
    assert check_features(problem.features, batch, 7) is None
