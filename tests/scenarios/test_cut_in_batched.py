"""The cut-in scenario's batched twin against its simulator on highway-env vehicles: the same observations and object
rows bit for bit for the same detections and measurement errors; snapshots; the scenario's story on fixed inputs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pemviz.scenarios.cut_in.batched import BatchedCutIn, cached_trajectory, replay
from pemviz.scenarios.cut_in.highway import CutInScenario
from pemviz.scenarios.cut_in.scenario import (
    FAILURE_FORMULA,
    LANE_WIDTH_M,
    NO_VEHICLE_M,
    OBJECT_NAMES,
    OBSERVATION_NAMES,
    CutInParams,
)
from pemviz.stl import robustness

P = CutInParams()
NEAR_MISS = dataclasses.replace(P, cut_in_gap_m=20.0, cut_in_speed_mps=17.4)
"""A cut-in that the ACC avoids by under a metre when it sees it: random inputs make some rollouts fail."""
OBS = {name: k for k, name in enumerate(OBSERVATION_NAMES)}


def highway_env_replay(params: CutInParams, detected: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Observations [N, T, F] and object rows [N, T, M, G] of the highway-env simulator on fixed inputs."""
    sim = CutInScenario(params)
    n, n_steps, m = detected.shape
    obs = np.empty((n, n_steps, len(OBSERVATION_NAMES)))
    objs = np.empty((n, n_steps, m, len(OBJECT_NAMES)))
    for i in range(n):
        sim.reset()
        for t in range(n_steps):
            obs[i, t] = sim.observation()
            objs[i, t] = sim.objects()
            sim.step(detected[i, t], noise[i, t])
    return obs, objs


def random_inputs(params: CutInParams, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Detections at a per-rollout rate in (0.5, 1) with runs of misses, and Student-t errors (metres)."""
    rng = np.random.default_rng(seed)
    shape = (n, params.n_steps, params.n_objects)
    detected = rng.random(shape) < rng.uniform(0.5, 1.0, (n, 1, 1))
    start = rng.integers(5, 30, n)
    for i in range(0, n, 2):  # half the rollouts miss the cut-in vehicle for a while during its lane change
        detected[i, start[i] : start[i] + rng.integers(1, 15), 0] = False
    noise = rng.standard_t(3.0, shape + (2,)) * np.array([0.6, 0.05])
    noise[~detected] = np.nan  # errors of missed objects are never read
    return detected, noise


def test_highway_env_and_batched_twin_give_the_same_bits_for_random_detections_and_errors():
    detected, noise = random_inputs(NEAR_MISS, 24, seed=7)
    obs_he, objs_he = highway_env_replay(NEAR_MISS, detected, noise)
    obs_tw, objs_tw = replay(NEAR_MISS, detected, noise)
    assert obs_tw.shape == (24, P.n_steps, len(OBSERVATION_NAMES)) and objs_tw.shape == objs_he.shape
    np.testing.assert_array_equal(obs_tw, obs_he)
    np.testing.assert_array_equal(objs_tw, objs_he)
    # the inputs exercise the story: failures and safe rollouts, gated and restarted tracks, hidden objects
    signals = {name: obs_tw[:, :, k] for name, k in OBS.items()}
    failed = robustness(FAILURE_FORMULA, signals) < 0
    assert 3 <= failed.sum() <= 21, failed.sum()
    assert (objs_tw[:, :, :, OBJECT_NAMES.index("visible")] == 0).any()
    assert (obs_tw[:, :, OBS["followed_index"]] == 0).any(axis=1).sum() >= 12


@pytest.mark.parametrize("m", [3, 6])
def test_three_and_six_objects_are_step_identical_too(m):
    params = dataclasses.replace(NEAR_MISS, n_objects=m)
    detected, noise = random_inputs(params, 4, seed=m)
    obs_he, objs_he = highway_env_replay(params, detected, noise)
    obs_tw, objs_tw = replay(params, detected, noise)
    assert objs_tw.shape == (4, params.n_steps, m, len(OBJECT_NAMES))
    np.testing.assert_array_equal(obs_tw, obs_he)
    np.testing.assert_array_equal(objs_tw, objs_he)


def test_other_traffic_from_highway_env_changes_lanes_once_and_keeps_its_speed():
    traj = cached_trajectory(P).traffic
    assert len(traj) == P.n_steps + 1
    y = np.array([t.y_m for t in traj])
    speed = np.array([t.speed_mps for t in traj])
    assert y[0, 0] == 2 * LANE_WIDTH_M and abs(y[-1, 0] - LANE_WIDTH_M) < 0.05  # the cut-in vehicle ends in the lane
    assert np.all(y[: P.cut_in_step + 1, 0] == y[0, 0])  # ... and starts to move at its scripted step
    np.testing.assert_array_equal(y[:, 1:], np.broadcast_to(y[0, 1:], y[:, 1:].shape))  # the others keep their lanes
    np.testing.assert_allclose(speed, np.broadcast_to(speed[0], speed.shape), rtol=0, atol=1e-9)
    assert speed[0].tolist() == [P.cut_in_speed_mps] + [v.speed_mps for v in P.traffic[: P.n_objects - 1]]


def test_a_perceived_cut_in_is_followed_and_a_missed_one_ends_in_a_collision():
    params = NEAR_MISS
    detected = np.ones((2, params.n_steps, params.n_objects), dtype=bool)
    detected[1, 10:30, 0] = False  # rollout 1 misses the cut-in vehicle for 2 s from the start of its lane change
    obs, _ = replay(params, detected)
    seen, missed = obs[0], obs[1]
    assert np.all(seen[: params.cut_in_step, OBS["ego_speed_mps"]] == params.ego_speed0_mps)  # cruising, lane free
    assert seen[:, OBS["followed_index"]].max() == 0 and seen[:, OBS["ego_accel_mps2"]].min() == -6.0
    assert seen[:, OBS["clearance_m"]].min() > 0.5
    assert missed[:, OBS["clearance_m"]].min() < -4.0  # not braking until the track starts: a collision
    first = np.flatnonzero(seen[:, OBS["followed_index"]] == 0)[0]
    assert 12 < first < 25 and np.all(missed[:31, OBS["followed_index"]] == -1)  # never seen, never followed
    signals = {name: obs[:, :, k] for name, k in OBS.items()}
    assert (robustness(FAILURE_FORMULA, signals) < 0).tolist() == [False, True]
    assert seen[0, OBS["gap_m"]] == NO_VEHICLE_M and seen[0, OBS["front_index"]] == -1


@pytest.mark.parametrize("make", [lambda: CutInScenario(P), lambda: BatchedCutIn(P, 3)])
def test_restoring_a_snapshot_continues_the_rollouts_bit_for_bit(make):
    sim = make()
    batched = isinstance(sim, BatchedCutIn)
    detected, noise = random_inputs(P, 3, seed=2)
    per_step = zip(detected.transpose(1, 0, 2), noise.transpose(1, 0, 2, 3), strict=False)
    inputs = [(d, e) if batched else (d[0], e[0]) for d, e in per_step]

    def run(from_step: int, to_step: int) -> list[np.ndarray]:
        out = []
        for t in range(from_step, to_step):
            out.append(np.concatenate([sim.observation().ravel(), sim.objects().ravel()]))
            sim.step(*inputs[t])
        return out

    run(0, 20)
    state = sim.snapshot()
    first = run(20, 40)
    run(40, 50)
    sim.restore(state)
    again = run(20, 40)
    sim.restore(state)
    assert [np.array_equal(a, b) for a, b in zip(first, again, strict=False)] == [True] * 20
    assert sim.t == 20


def test_a_selected_state_continues_the_chosen_rollouts_in_a_batch_of_their_own():
    detected, noise = random_inputs(NEAR_MISS, 4, seed=5)
    full = BatchedCutIn(NEAR_MISS, 4)
    for t in range(15):
        full.step(detected[:, t], noise[:, t])
    branch = BatchedCutIn(NEAR_MISS, 3)
    branch.restore(full.snapshot().select(np.array([2, 0, 2])))
    for t in range(15, 30):
        assert np.array_equal(branch.objects(), full.objects()[[2, 0, 2]])
        full.step(detected[:, t], noise[:, t])
        branch.step(detected[[2, 0, 2], t], noise[[2, 0, 2], t])
    assert np.array_equal(branch.observation(), full.observation()[[2, 0, 2]])


def test_bad_steps_raise_one_clear_error():
    sim = BatchedCutIn(dataclasses.replace(P, n_steps=1), 2)
    with pytest.raises(ValueError, match=r"detected must be bool \[2, 5\], got shape \(2, 4\)"):
        sim.step(np.ones((2, 4), dtype=bool))
    with pytest.raises(ValueError, match=r"noise must be float64 \[2, 5, 2\]"):
        sim.step(np.ones((2, 5), dtype=bool), np.zeros((2, 5)))
    sim.step(np.ones((2, 5), dtype=bool))
    with pytest.raises(RuntimeError, match="rollouts over after 1 steps"):
        sim.step(np.ones((2, 5), dtype=bool))
    with pytest.raises(ValueError, match="n must be an integer >= 1, got 0"):
        BatchedCutIn(P, 0)
    one = CutInScenario(dataclasses.replace(P, n_steps=1))
    with pytest.raises(ValueError, match=r"detected must be bool \[5\]"):
        one.step(np.ones(3, dtype=bool))
    with pytest.raises(ValueError, match=r"noise must be float64 \[5, 2\]"):
        one.step(np.ones(5, dtype=bool), np.zeros(5))
    with pytest.raises(ValueError, match=r"detected must be bool \[N >= 1, T <= 100, 5\]"):
        replay(P, np.ones((1, 101, 5), dtype=bool))
