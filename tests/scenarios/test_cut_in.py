"""The cut-in scenario's pieces against independent truth: highway-env's IDM, hand-computed camera geometry
(occlusion, truncation, measurement along the ray), the safe distance and the R_G1 formula on hand-made traces."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from pemviz.pem.encoding import encode_salient
from pemviz.scenarios.cut_in.scenario import (
    FAILURE_FORMULA,
    OBJECT_NAMES,
    SALIENT_COLUMNS,
    CutInParams,
    IDMParams,
    acc_control,
    idm_acceleration,
    safe_distance,
)
from pemviz.scenarios.cut_in.scene import CutInMemory, camera_view, measure, object_rows, traffic_at
from pemviz.stack import tracker
from pemviz.stl import robustness

P = CutInParams()


# -- the ACC: highway-env's IDM ----------------------------------------------------------------------------------


def test_idm_constants_are_highway_env_idm_vehicle_constants():
    from highway_env.vehicle.behavior import IDMVehicle

    idm = IDMParams()
    assert (idm.comfort_acc_max_mps2, idm.comfort_acc_min_mps2, idm.time_wanted_s, idm.delta, idm.acc_max_mps2) == (
        IDMVehicle.COMFORT_ACC_MAX,
        IDMVehicle.COMFORT_ACC_MIN,
        IDMVehicle.TIME_WANTED,
        IDMVehicle.DELTA,
        IDMVehicle.ACC_MAX,
    )
    assert idm.distance_wanted_m == IDMVehicle.DISTANCE_WANTED == 5.0 + 5.0


def test_idm_acceleration_equals_highway_env_idm_vehicle_acceleration():
    from highway_env.road.road import Road, RoadNetwork
    from highway_env.vehicle.behavior import IDMVehicle
    from highway_env.vehicle.kinematics import Vehicle

    road = Road(network=RoadNetwork.straight_road_network(lanes=3, speed_limit=None))
    rng = np.random.default_rng(0)
    v = rng.uniform(0.0, 35.0, 200)
    d = rng.uniform(3.0, 120.0, 200)
    vf = rng.uniform(0.0, 35.0, 200)
    expected = np.empty(200)
    for i in range(200):
        ego = IDMVehicle(road, [0.0, 4.0], speed=v[i], target_speed=25.0, enable_lane_change=False)
        front = Vehicle(road, [d[i], 4.0], speed=vf[i])
        expected[i] = np.clip(ego.acceleration(ego, front), -ego.ACC_MAX, ego.ACC_MAX)
    got = idm_acceleration(IDMParams(), 25.0, v, d, v - vf)
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)
    assert (got == -6.0).sum() > 20 and (np.abs(got) < 6.0).sum() > 20  # both the clip and the formula are exercised
    free = IDMVehicle(road, [0.0, 4.0], speed=20.0, target_speed=25.0, enable_lane_change=False)
    assert idm_acceleration(IDMParams(), 25.0, np.array([20.0]), np.array([np.inf]), np.zeros(1))[0] == pytest.approx(
        free.acceleration(free, None), rel=1e-12
    )


def test_acc_follows_the_nearest_estimate_in_the_ego_lane_only():
    # tracks [M = 3, N = 2]: object 0 just outside the lane (y = 6.1), object 1 in the lane 30 m ahead, object 2 in the
    # lane 15 m ahead but inactive in rollout 1
    x = np.array([[10.0, 10.0], [30.0, 30.0], [15.0, 15.0]])
    y = np.array([[6.1, 5.9], [4.0, 4.0], [4.5, 4.5]])
    vx = np.full((3, 2), 20.0)
    active = np.array([[True, True], [True, True], [True, False]])
    followed, accel = acc_control(P, x, y, vx, active, np.zeros(2), np.full(2, 25.0))
    assert followed.tolist() == [2, 0]  # rollout 1: object 0 at y = 5.9 is in the lane (|5.9 - 4| < 2)
    np.testing.assert_allclose(
        accel, idm_acceleration(P.idm, 25.0, np.full(2, 25.0), np.array([15.0, 10.0]), np.full(2, 5.0))
    )
    none, free = acc_control(P, x, y + 10.0, vx, active, np.zeros(2), np.full(2, 25.0))
    assert none.tolist() == [-1, -1] and np.all(free == 0.0)  # free road at the set speed: no acceleration


# -- camera geometry ----------------------------------------------------------------------------------------------


def traffic(x: list[float], y: list[float], heading: list[float] | None = None, step: int = 0, params: CutInParams = P):
    h = np.zeros(len(x)) if heading is None else np.array(heading)
    t, _ = traffic_at(params, step, np.array(x), np.array(y), h, np.full(len(x), 20.0), CutInMemory.initial(len(x)))
    return t


def test_a_car_behind_another_in_the_same_lane_is_hidden_by_its_image_box():
    # ego at x = 0 (camera at 2 m); a car 10 m and one 30 m ahead of the ego's front bumper, both in the ego's lane
    tr = traffic([15.0, 35.0], [4.0, 4.0])
    view = camera_view(P, tr, np.zeros(1))
    # near car: depths 10.5 .. 15.5 m; far car: 30.5 .. 35.5 m; both 2 m wide, centred on the camera axis
    v_top_near, v_bot_far, v_top_far = 0.15 / 15.5, 1.65 / 30.5, 0.15 / 35.5
    expected = (v_bot_far - v_top_near) / (v_bot_far - v_top_far)  # the far box is inside the near one across
    assert view.occluded_fraction[1, 0] == pytest.approx(expected, rel=1e-12)
    assert expected == pytest.approx(0.8907, abs=1e-4)
    assert view.occluded_fraction[0, 0] == 0.0 and view.visible[0, 0]
    assert not view.visible[1, 0]  # more than 80 % covered: hidden
    rows = object_rows(
        P, tr, view, np.zeros(1), np.full(1, 25.0), np.zeros(1), tracker.Tracks.empty((2, 1)), np.full(1, -1)
    )
    assert rows[0, :, OBJECT_NAMES.index("occlusion")].tolist() == [0.0, 2.0]


def test_a_car_in_the_next_lane_beside_a_nearer_car_is_partly_occluded_by_hand():
    # near car in the ego lane 10 m ahead; a car in the right lane 20 m ahead: overlap only across u
    tr = traffic([15.0, 25.0], [4.0, 8.0])
    view = camera_view(P, tr, np.zeros(1))
    u_hi_near = 1.0 / 10.5
    u_lo_far, u_hi_far = 3.0 / 25.5, 5.0 / 20.5
    assert u_hi_near < u_lo_far  # the boxes do not overlap across: not occluded
    assert view.occluded_fraction[1, 0] == 0.0
    tr = traffic([15.0, 30.0], [4.0, 7.0])  # the far car 3 m to the right: its left part is behind the near car
    view = camera_view(P, tr, np.zeros(1))
    u_lo_far, u_hi_far = 2.0 / 30.5, 4.0 / 25.5  # left edge smallest at the far face, right edge at the near one
    du = u_hi_near - u_lo_far
    dv = 1.65 / 25.5 - 0.15 / 15.5
    area = (u_hi_far - u_lo_far) * (1.65 / 25.5 - 0.15 / 30.5)
    assert view.occluded_fraction[1, 0] == pytest.approx(du * dv / area, rel=1e-12)
    assert 0.01 < du * dv / area < 0.35 and view.visible[1, 0]  # partly occluded (KITTI level 1)


def test_a_close_car_beside_the_camera_is_truncated_by_the_image_edges_by_hand():
    tr = traffic([8.0], [8.0])  # right lane, centre 6 m ahead of the camera: faces at 3.5 and 8.5 m
    view = camera_view(P, tr, np.zeros(1))
    u_lo, u_hi = 3.0 / 8.5, 5.0 / 3.5
    v_top, v_bot = 0.15 / 8.5, 1.65 / 3.5
    right = (1242 - 609.5593) / 721.5377
    bottom = (375 - 172.854) / 721.5377
    expected = 1.0 - (right - u_lo) * (bottom - v_top) / ((u_hi - u_lo) * (v_bot - v_top))
    assert view.truncation[0, 0] == pytest.approx(expected, rel=1e-12)
    assert view.visible[0, 0]  # its centre is 6 m ahead of the camera and part of it is in the image
    behind = camera_view(P, traffic([2.5], [8.0]), np.zeros(1))
    assert not behind.visible[0, 0]  # centre beside the camera: the pinhole sees nothing of it


def test_a_detection_is_moved_along_the_ray_by_the_range_error_and_across_it_by_the_lateral_error():
    tr = traffic([22.0], [8.0])  # centre 20 m ahead of the camera, 4 m to the right
    view = camera_view(P, tr, np.zeros(1))
    noise = np.array([[[2.0, 0.1]]])
    z_x, z_y, z_range = measure(P, view, np.zeros(1), noise, np.array([[True]]))
    assert z_range[0, 0] == 22.0 and z_x[0, 0] == 2.0 + 22.0
    assert z_y[0, 0] == pytest.approx(4.0 + 4.1 * 22.0 / 20.0, rel=1e-15)  # (X + dX) Z_m / Z
    missed = measure(P, view, np.zeros(1), np.full((1, 1, 2), np.nan), np.array([[False]]))
    assert missed[0][0, 0] == 22.0 and missed[1][0, 0] == 8.0  # no error where not measured, even NaN noise


def test_object_rows_hold_kitti_salient_variables_a_pem_can_encode():
    tr = traffic([15.0, 40.0], [4.0, 0.0])
    view = camera_view(P, tr, np.zeros(1))
    rows = object_rows(
        P, tr, view, np.zeros(1), np.full(1, 25.0), np.zeros(1), tracker.Tracks.empty((2, 1)), np.full(1, -1)
    )[0]
    col = {name: rows[:, k] for k, name in enumerate(OBJECT_NAMES)}
    assert col["class"].tolist() == [0.0, 0.0] and col["loc_y"].tolist() == [1.65, 1.65]
    assert col["loc_z"].tolist() == [13.0, 38.0] and col["loc_x"].tolist() == [0.0, -4.0]
    assert col["rot_y"].tolist() == [-math.pi / 2] * 2
    assert col["alpha"][0] == -math.pi / 2 and col["alpha"][1] == pytest.approx(-math.pi / 2 + math.atan2(4.0, 38.0))
    assert col["range_m"][1] == pytest.approx(math.hypot(4.0, 38.0), rel=1e-15)
    assert col["gap_m"].tolist() == [10.0, 35.0]
    assert (col["dim_w"][0], col["dim_l"][0], col["dim_h"][0]) == (1.5, 2.0, 5.0)  # KITTI's (height, width, length)
    from pemviz.pem import load_pem

    pem = load_pem()
    features = encode_salient(rows[:, SALIENT_COLUMNS], pem.norm)
    assert features.shape == (2, 14) and np.all(np.isfinite(pem.logit_features(features)))


def test_cut_in_begins_when_the_box_straddles_into_the_ego_lane_and_stays_recent_for_the_grace_time():
    memory = CutInMemory.initial(1)
    recent = []
    for step, (y, h) in enumerate([(8.0, 0.0), (7.3, -0.1), (6.5, -0.1), (5.0, -0.05), (4.0, 0.0)] + [(4.0, 0.0)] * 40):
        tr, memory = traffic_at(P, step, np.array([30.0]), np.array([y]), np.array([h]), np.array([20.0]), memory)
        recent.append(bool(tr.cut_in_recent[0]))
        if step in (0, 1, 2):
            # the box (heading -0.1) reaches 1.245 m across: at y = 7.3 its edge is at 6.055, at 6.5 past y = 6
            assert tr.cutting_in[0] == (step == 2)
    assert recent == [False, False] + [True] * 31 + [False] * 12  # steps 2 .. 2 + 30


# -- the rule and the failure ---------------------------------------------------------------------------------------


def test_safe_distance_by_hand():
    # Maierhofer et al. 2020 with a_ego = -10, a_front = -10.5 m/s^2 and t_react = 0.3 s
    assert safe_distance(P, np.array(20.0), np.array(15.0)) == pytest.approx(400 / 20 - 225 / 21 + 6.0, rel=1e-15)
    assert safe_distance(P, np.array(0.0), np.array(10.0)) == pytest.approx(-100 / 21, rel=1e-15)


def signals(margin: list[float], recent: list[float], clearance: list[float]) -> dict[str, np.ndarray]:
    return {
        "safe_margin_m": np.array([margin]),
        "cut_in_recent": np.array([recent]),
        "clearance_m": np.array([clearance]),
    }


def test_rule_g1_waives_the_safe_distance_right_after_a_cut_in_only():
    waived = signals([5.0, -3.0, -1.0, 2.0], [0.0, 1.0, 1.0, 0.0], [8.0, 4.0, 3.0, 6.0])
    assert robustness(FAILURE_FORMULA, waived)[0] == 2.0  # min(5, 997, 999, 2, clearances)
    late = signals([5.0, -3.0, -1.0, -0.5], [0.0, 1.0, 1.0, 0.0], [8.0, 4.0, 3.0, 6.0])
    assert robustness(FAILURE_FORMULA, late)[0] == -0.5  # too close once the grace time is over
    crash = signals([5.0, -3.0, 1.0, 2.0], [0.0, 1.0, 1.0, 0.0], [8.0, -0.2, 3.0, 6.0])
    assert robustness(FAILURE_FORMULA, crash)[0] == pytest.approx(-0.2)  # a collision fails whatever the rule


def test_the_formula_fails_exactly_when_the_boolean_rule_g1_or_a_collision_does():
    rng = np.random.default_rng(1)
    margin = rng.normal(3.0, 2.0, (500, 12))
    recent = (rng.random((500, 12)) < 0.3).astype(float)
    clearance = rng.normal(4.0, 1.5, (500, 12))
    sig = {"safe_margin_m": margin, "cut_in_recent": recent, "clearance_m": clearance}
    boolean = robustness("G(cut_in_recent > 0.5 | safe_margin_m >= 0) & G(clearance_m >= 0)", sig) < 0
    assert np.array_equal(robustness(FAILURE_FORMULA, sig) < 0, boolean)
    assert 50 < boolean.sum() < 450


# -- parameters ----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"n_objects": 2}, "n_objects must be an integer in 3..6"),
        ({"cut_in_lane": 1}, "cut_in_lane must be 0 or 2"),
        ({"dt_s": 0.0}, "dt_s must be finite and > 0"),
        ({"occlusion_largely": 0.9}, "occlusion thresholds must be 0 < partly < largely < hidden <= 1"),
        ({"camera_height_m": 1.2}, "camera_height_m must be above vehicle_height_m"),
    ],
)
def test_bad_parameters_raise_one_clear_error(change, message):
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(CutInParams(), **change)
