"""The tracker's state as features (pemviz.stack.tracker.features) against values computed by hand on one track:
its start, its confirmation by a second measurement, its misses counted, its age, its variances after a prediction,
and its predicted time to collision, range / closing speed, capped."""

from __future__ import annotations

import numpy as np
import pytest
from pemviz.stack import tracker
from pemviz.stack.tracker import FEATURE_NAMES, TTC_CAP_S, TrackerParams, Tracks

DT = 0.1
PARAMS = TrackerParams()  # accel std 3 m/s^2 along the road; measurement std 0.3 + 0.0015 Z^2 m; prior std 15 m/s


def named(tracks: Tracks, ego_x_m: float = 0.0, ego_speed_mps: float = 12.0) -> dict[str, float]:
    """Object 0 of rollout 0's features by name."""
    f = tracker.features(tracks, ego_x_m, ego_speed_mps)
    assert f.shape == (1, 1, len(FEATURE_NAMES)) and f.dtype == np.float64
    return dict(zip(FEATURE_NAMES, f[0, 0].tolist(), strict=True))


def measure(tracks: Tracks, seen: bool, x: float = 30.0) -> Tracks:
    one = np.ones((1, 1))
    return tracker.update(tracks, np.array([[seen]]), x * one, 1.0 * one, x * one, 0.0, PARAMS)


def test_a_track_is_counted_from_its_start_confirmed_by_its_second_measurement_and_its_misses_counted():
    tracks = Tracks.empty((1, 1))
    f = named(tracks)
    assert f == {**dict.fromkeys(FEATURE_NAMES, 0.0), "track_ttc_s": TTC_CAP_S}  # no track: zeros, the cap
    tracks = tracker.predict(measure(tracks, True), DT, PARAMS)  # step 0: a tentative track at 30 m, vx prior 0
    f = named(tracks)
    r_x = (0.3 + 0.0015 * 30.0**2) ** 2  # 1.65^2 m^2: the start's position variance
    assert (f["track_active"], f["track_confirmed"], f["track_age_steps"], f["track_misses"]) == (1.0, 0.0, 1.0, 0.0)
    assert f["track_range_m"] == pytest.approx(30.0) and f["track_vx_mps"] == 0.0 and f["track_y_m"] == 1.0
    # P' = F P F^T + Q: var_x = r + dt^2 * 15^2 + 3^2 dt^4 / 4; var_vx = 15^2 + 3^2 dt^2
    assert f["track_var_x_m2"] == pytest.approx(r_x + 0.01 * 225.0 + 9.0 * 1e-4 / 4.0, rel=1e-12)
    assert f["track_var_vx_m2ps2"] == pytest.approx(225.0 + 9.0 * 0.01, rel=1e-12)
    assert f["track_ttc_s"] == pytest.approx(30.0 / 12.0, rel=1e-12)  # range / (ego speed - vx)
    tracks = tracker.predict(measure(tracks, True), DT, PARAMS)  # step 1: inside the gate, confirmed
    f = named(tracks)
    assert (f["track_confirmed"], f["track_age_steps"], f["track_misses"]) == (1.0, 2.0, 0.0)
    for misses in (1.0, 2.0, 3.0):  # steps 2-4 missed: one more miss each, older by one
        tracks = tracker.predict(measure(tracks, False), DT, PARAMS)
        f = named(tracks)
        assert (f["track_confirmed"], f["track_age_steps"], f["track_misses"]) == (1.0, 2.0 + misses, misses)
    for _ in range(PARAMS.max_coast_steps):  # missed until dropped: no track, its features zero again
        tracks = tracker.predict(measure(tracks, False), DT, PARAMS)
    assert named(tracks) == {**dict.fromkeys(FEATURE_NAMES, 0.0), "track_ttc_s": TTC_CAP_S}


def established(x: float, vx: float) -> Tracks:
    return tracker.start_confirmed(Tracks.empty((1, 1)), True, x_m=x, vx_mps=vx, y_m=0.0)


def test_the_time_to_collision_is_range_over_closing_speed_capped_and_zero_at_or_behind_the_reference():
    f = named(established(30.0, 2.0))
    assert f["track_ttc_s"] == pytest.approx(30.0 / (12.0 - 2.0), rel=1e-12)  # 3.0 s
    assert (f["track_var_x_m2"], f["track_var_vx_m2ps2"], f["track_age_steps"]) == (0.3, 0.8, 0.0)
    f = named(tracker.predict(established(30.0, 2.0), DT, PARAMS), ego_x_m=1.2)  # 30.2 m, 29.0 m ahead of 1.2 m
    assert f["track_range_m"] == pytest.approx(29.0, rel=1e-12) and f["track_ttc_s"] == pytest.approx(2.9, rel=1e-12)
    assert f["track_var_x_m2"] == pytest.approx(0.3 + 0.01 * 0.8 + 9.0 * 1e-4 / 4.0, rel=1e-12)
    assert f["track_misses"] == 0.0 and f["track_age_steps"] == 1.0
    assert named(established(300.0, 2.0))["track_ttc_s"] == TTC_CAP_S  # 30 s, capped
    assert named(established(30.0, 15.0))["track_ttc_s"] == TTC_CAP_S  # faster than the ego: never closes
    assert named(established(-1.0, 0.0))["track_ttc_s"] == 0.0  # behind the reference point


def test_features_are_rollout_major_and_refuse_a_cap_that_is_not_positive():
    tracks = tracker.start_confirmed(Tracks.empty((2, 3)), np.array([[True], [False]]), x_m=20.0, vx_mps=0.0, y_m=0.0)
    f = tracker.features(tracks, np.array([0.0, 5.0, 10.0]), np.array([10.0, 10.0, 5.0]))
    assert f.shape == (3, 2, len(FEATURE_NAMES))
    np.testing.assert_allclose(f[:, 0, FEATURE_NAMES.index("track_ttc_s")], [2.0, 1.5, 2.0], rtol=1e-12)
    assert (f[:, 1, FEATURE_NAMES.index("track_active")] == 0.0).all()
    with pytest.raises(ValueError, match="ttc_cap_s must be finite and > 0"):
        tracker.features(tracks, 0.0, 10.0, ttc_cap_s=0.0)
