"""The library's constant-velocity tracker (pemviz.stack.tracker) against filterpy's KalmanFilter (the oracle), and
its gate and track management on hand-made cases."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from pemviz.stack import tracker
from pemviz.stack.tracker import TrackerParams, Tracks
from scipy.linalg import block_diag

DT = 0.1


def oracle_filter(params: TrackerParams, x0: float, y0: float, v0: float, r0: tuple[float, float]) -> KalmanFilter:
    """filterpy's 4-state CV filter [x, vx, y, vy] started as the tracker starts a track."""
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.F = block_diag([[1.0, DT], [0.0, 1.0]], [[1.0, DT], [0.0, 1.0]])
    kf.H = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
    kf.Q = block_diag(
        Q_discrete_white_noise(2, DT, params.accel_std_x_mps2**2),
        Q_discrete_white_noise(2, DT, params.accel_std_y_mps2**2),
    )
    kf.x = np.array([[x0], [v0], [y0], [0.0]])
    kf.P = np.diag([r0[0], params.init_speed_std_x_mps**2, r0[1], params.init_speed_std_y_mps**2])
    return kf


def as_state(tr: Tracks, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Track i's state [4] and covariance [4, 4] in filterpy's order [x, vx, y, vy]."""
    x = np.array([tr.x[i], tr.vx[i], tr.y[i], tr.vy[i]])
    p = np.zeros((4, 4))
    p[:2, :2] = [[tr.pxx[i], tr.pxv[i]], [tr.pxv[i], tr.pvvx[i]]]
    p[2:, 2:] = [[tr.pyy[i], tr.pyv[i]], [tr.pyv[i], tr.pvvy[i]]]
    return x, p


def test_tracks_follow_filterpy_kalman_filter_through_detections_and_misses():
    params = TrackerParams(gate_chi2=np.inf, max_coast_steps=100)
    rng = np.random.default_rng(3)
    n, n_steps = 6, 60
    truth_x = 20.0 + 22.0 * DT * np.arange(n_steps)[:, None] + rng.normal(0, 0.5, (1, n))
    truth_y = 4.0 + 0.5 * np.sin(0.2 * np.arange(n_steps))[:, None] * rng.random(n)
    measured = rng.random((n_steps, n)) < 0.7
    measured[0] = True  # every track starts at step 0
    ego_speed = np.full(n, 25.0)
    tracks = Tracks.empty((n,))
    oracles: list[KalmanFilter] = []
    for t in range(n_steps):
        z_range = truth_x[t] - 2.0 * t * DT
        z_x = truth_x[t] + rng.normal(0, 0.4, n)
        z_y = truth_y[t] + rng.normal(0, 0.1, n)
        tracks = tracker.update(tracks, measured[t], z_x, z_y, z_range, ego_speed, params)
        r_x, r_y = params.measurement_variances(z_range)
        for i in range(n):
            if t == 0:
                oracles.append(oracle_filter(params, z_x[i], z_y[i], 25.0, (r_x[i], r_y[i])))
            elif measured[t, i]:
                oracles[i].update(np.array([[z_x[i]], [z_y[i]]]), R=np.diag([r_x[i], r_y[i]]))
            x, p = as_state(tracks, i)
            np.testing.assert_allclose(x, oracles[i].x[:, 0], rtol=0, atol=1e-9)
            np.testing.assert_allclose(p, oracles[i].P, rtol=1e-9, atol=1e-12)
        tracks = tracker.predict(tracks, DT, params)
        for kf in oracles:
            kf.predict()
    assert tracks.active.all()
    assert (~measured[1:]).sum() > 50  # the comparison covers coasting steps, not only updates


def start_one(params: TrackerParams, x: float = 30.0) -> Tracks:
    tracks = Tracks.empty((1,))
    tracks = tracker.update(
        tracks, np.array([True]), np.array([x]), np.array([4.0]), np.array([20.0]), np.array([25.0]), params
    )
    return tracker.predict(tracks, DT, params)


def test_a_measurement_outside_the_gate_leaves_the_prediction_and_coasts():
    params = TrackerParams()
    pred = start_one(params)
    s_x = pred.pxx[0] + params.measurement_variances(np.array([20.0]))[0][0]
    far = pred.x[0] + 1.01 * np.sqrt(params.gate_chi2 * s_x)  # just outside the 1-degree-of-freedom gate
    near = pred.x[0] + 0.99 * np.sqrt(params.gate_chi2 * s_x)
    args = (np.array([4.0]), np.array([20.0]), np.array([25.0]), params)
    out = tracker.update(pred, np.array([True]), np.array([far]), *args)
    assert out.x[0] == pred.x[0] and out.pxx[0] == pred.pxx[0] and out.coast[0] == pred.coast[0] == 1
    inside = tracker.update(pred, np.array([True]), np.array([near]), *args)
    assert inside.x[0] > pred.x[0] and inside.pxx[0] < pred.pxx[0] and inside.coast[0] == 0
    ungated = tracker.update(pred, np.array([True]), np.array([far]), *args[:-1], TrackerParams(gate_chi2=np.inf))
    gain = pred.pxx[0] / s_x
    assert ungated.x[0] == pytest.approx(pred.x[0] + gain * (far - pred.x[0]), rel=1e-12)


def test_a_track_that_missed_a_step_restarts_at_a_measurement_outside_its_gate_keeping_its_velocity():
    params = TrackerParams()
    pred = tracker.predict(start_one(params), DT, params)  # one step without an update: last update 2 steps old
    assert pred.coast[0] == params.restart_after_steps == 2
    s_x = pred.pxx[0] + params.measurement_variances(np.array([20.0]))[0][0]
    far = pred.x[0] + 1.5 * np.sqrt(params.gate_chi2 * s_x)
    out = tracker.update(
        pred, np.array([True]), np.array([far]), np.array([4.5]), np.array([20.0]), np.array([30.0]), params
    )
    assert out.x[0] == far and out.y[0] == 4.5 and out.coast[0] == 0
    assert out.vx[0] == pred.vx[0] == 25.0  # the velocity estimate is kept, not the ego's 30 m/s
    assert out.pvvx[0] == params.init_speed_std_x_mps**2 and out.pxv[0] == 0.0


def test_a_track_is_tentative_until_a_measurement_inside_its_gate_confirms_it():
    params = TrackerParams()
    pred = start_one(params)
    assert pred.active[0] and not pred.confirmed[0]
    confirmed = tracker.update(
        pred, np.array([True]), pred.x.copy(), np.array([4.0]), np.array([20.0]), np.array([25.0]), params
    )
    assert confirmed.confirmed[0]
    coasted = tracker.predict(tracker.predict(confirmed, DT, params), DT, params)
    restarted = tracker.update(
        coasted, np.array([True]), coasted.x + 100.0, np.array([4.0]), np.array([20.0]), np.array([25.0]), params
    )
    assert restarted.active[0] and not restarted.confirmed[0]  # a restart is tentative again


def test_a_track_is_dropped_after_max_coast_steps_and_restarts_at_the_next_detection():
    params = TrackerParams(max_coast_steps=3)
    tracks = start_one(params)
    for _ in range(2):
        tracks = tracker.predict(tracks, DT, params)
    assert tracks.active[0] and tracks.coast[0] == 3
    tracks = tracker.predict(tracks, DT, params)
    assert not tracks.active[0] and tracks.coast[0] == 0
    restarted = tracker.update(
        tracks, np.array([True]), np.array([55.0]), np.array([3.0]), np.array([20.0]), np.array([24.0]), params
    )
    assert restarted.active[0] and restarted.x[0] == 55.0 and restarted.vx[0] == 24.0 and restarted.vy[0] == 0.0
    r_x, r_y = params.measurement_variances(np.array([20.0]))
    assert restarted.pxx[0] == r_x[0] and restarted.pyy[0] == r_y[0]
    assert restarted.pvvx[0] == params.init_speed_std_x_mps**2


def test_measurement_variances_grow_with_range_as_documented():
    params = TrackerParams()
    r_x, r_y = params.measurement_variances(np.array([10.0, 40.0]))
    np.testing.assert_allclose(np.sqrt(r_x), [0.3 + 0.0015 * 100, 0.3 + 0.0015 * 1600], rtol=1e-12)
    np.testing.assert_allclose(np.sqrt(r_y), [0.1 + 0.003 * 10, 0.1 + 0.003 * 40], rtol=1e-12)


def test_bad_tracker_parameters_raise_one_clear_error():
    with pytest.raises(ValueError, match="accel_std_x_mps2 must be finite and >= 0, got -1.0"):
        TrackerParams(accel_std_x_mps2=-1.0)
    with pytest.raises(ValueError, match="a measurement is never exact"):
        TrackerParams(meas_std_x0_m=0.0)


def test_a_track_started_confirmed_is_followed_from_the_first_step_as_filterpy_follows_it():
    params = TrackerParams(gate_chi2=np.inf)
    tracks = tracker.start_confirmed(
        Tracks.empty((2, 3)), np.array([[True], [False]]), 30.0, 20.0, 4.0, 0.5, 0.3, 0.8, 0.01, 0.1
    )
    assert tracks.confirmed.tolist() == [[True] * 3, [False] * 3] and tracks.active[0].all()
    assert (
        tracks.x[0].tolist() == [30.0] * 3 and tracks.vx[0].tolist() == [20.0] * 3 and tracks.x[1].tolist() == [0] * 3
    )
    kf = oracle_filter(params, 30.0, 4.0, 20.0, (0.3, 0.01))
    kf.x[3, 0], kf.P[1, 1], kf.P[3, 3] = 0.5, 0.8, 0.1
    tracks = tracker.predict(tracks, DT, params)
    kf.predict()
    assert tracks.confirmed[0].all()  # still confirmed after a prediction without an update
    tracks = tracker.update(
        tracks, np.ones((2, 3), bool), np.full((2, 3), 32.5), np.full((2, 3), 4.1), np.full((2, 3), 25.0), 0.0, params
    )
    r_x, r_y = params.measurement_variances(np.array(25.0))
    kf.update(np.array([[32.5], [4.1]]), R=np.diag([r_x, r_y]))
    x, p = as_state(Tracks(*(getattr(tracks, f)[0] for f in tracks.__dataclass_fields__)), 1)
    np.testing.assert_allclose(x, kf.x[:, 0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(p, kf.P, rtol=1e-9, atol=1e-12)
    assert tracks.confirmed[0].all() and not tracks.confirmed[1].any()  # the other object only started a track


def test_start_confirmed_refuses_a_variance_of_zero_where_it_starts():
    with pytest.raises(ValueError, match="var_vx_m2ps2 must be finite and > 0"):
        tracker.start_confirmed(Tracks.empty((2,)), np.array([True, False]), 1.0, 2.0, 0.0, var_vx_m2ps2=0.0)
    with pytest.raises(ValueError, match="x_m must be finite"):
        tracker.start_confirmed(Tracks.empty((2,)), True, np.array([1.0, np.nan]), 2.0, 0.0)
    tracker.start_confirmed(Tracks.empty((2,)), np.array([True, False]), np.array([1.0, np.nan]), 2.0, 0.0)
