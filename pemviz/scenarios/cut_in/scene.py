"""The cut-in scenario's geometry at one step: the traffic, the ego camera's view of it, the measurements, the object
rows and the scene signals, for N rollouts at once in numpy float64.

The other vehicles' state (:class:`Traffic`, ``[M]``) is the same in every rollout, the ego's position (``[N]``) is
not, so the view is ``[M, N]``. Both simulators call these functions (the highway-env one with N = 1), so their
arithmetic is the same element by element. The camera is :mod:`pemviz.stack.camera`'s KITTI pinhole,
``camera_offset_m`` ahead of the ego's centre and ``camera_height_m`` above the road; truncation, the occluded share
(:func:`pemviz.stack.camera.occluded_share`) and its level, visibility and measurement (:func:`measure`) follow that
module, with the thresholds of :class:`~pemviz.scenarios.cut_in.scenario.CutInParams`.

Units: metres, seconds, m/s, radians."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pemviz.core import libm
from pemviz.pem.camera import MIN_RANGE_M
from pemviz.scenarios.cut_in.scenario import (
    LANE_WIDTH_M,
    NO_VEHICLE_M,
    OBJECT_NAMES,
    OBSERVATION_NAMES,
    CutInParams,
    acc_control,
    safe_distance,
)
from pemviz.stack import camera, tracker
from pemviz.stack.camera import IMAGE_BOUNDS
from pemviz.stack.tracker import Tracks

_MIN_DEPTH_M = 0.1
"""Corner depths are clamped to at least this before dividing (an object reaching behind the camera is largely
truncated; it is not visible unless its centre is :data:`MIN_RANGE_M` ahead)."""
_NEVER = -(10**9)


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles in [-3 pi, 3 pi) into [-pi, pi), in place (one turn added or taken off)."""
    np.subtract(angle, 2.0 * np.pi, out=angle, where=angle >= np.pi)
    np.add(angle, 2.0 * np.pi, out=angle, where=angle < -np.pi)
    return angle


@dataclass(frozen=True)
class Traffic:
    """The M other vehicles at one step, the same in every rollout: arrays ``[M]``, or ``[M, 1]`` where marked;
    ``x_m``, ``rear_m`` and ``front_m`` may be ``[M, N]`` (the cut-in vehicle moved per rollout).

    Attributes:
        x_m, y_m, heading_rad, speed_mps: highway-env's vehicle state (centre; heading from the road's direction).
        vx_mps, vy_mps: velocity along and across the road.
        half_x_m, half_y_m: half extents of the box's axis-aligned bounding box on the ground.
        rear_m, front_m: ``[M, 1]`` the box's extent along the road.
        loc_x_lo_m, loc_x_hi_m: ``[M, 1]`` its lateral extent in the camera frame.
        rot_y_rad: KITTI's rotation of the object about the camera's y axis (``heading - pi / 2``).
        in_ego_lane: bool, the box overlaps the ego's lane.
        beside_ego: bool ``[M, 1]``, the box overlaps the ego's box laterally.
        cutting_in: bool, R_G1's cut-in predicate: in the ego's lane and another, moving towards the ego's lane
            centre.
        cut_in_recent: bool, a cut-in began within the last ``cut_in_grace_steps`` steps.
        occluder_pairs: ``(i, j)`` pairs with ``i`` nearer the camera than ``j`` whose image boxes can overlap, in a
            fixed order."""

    x_m: np.ndarray
    y_m: np.ndarray
    heading_rad: np.ndarray
    speed_mps: np.ndarray
    vx_mps: np.ndarray
    vy_mps: np.ndarray
    half_x_m: np.ndarray
    half_y_m: np.ndarray
    rear_m: np.ndarray
    front_m: np.ndarray
    loc_x_lo_m: np.ndarray
    loc_x_hi_m: np.ndarray
    rot_y_rad: np.ndarray
    in_ego_lane: np.ndarray
    beside_ego: np.ndarray
    cutting_in: np.ndarray
    cut_in_recent: np.ndarray
    occluder_pairs: tuple[tuple[int, int], ...]


@dataclass(frozen=True)
class CutInMemory:
    """What R_G1's cut-in exemption remembers of the past, ``[M]``: whether each vehicle was cutting in at the last
    step, and the step at which its latest cut-in began (a large negative number: never)."""

    was_cutting_in: np.ndarray
    last_start: np.ndarray

    @classmethod
    def initial(cls, m: int) -> CutInMemory:
        return cls(np.zeros(m, dtype=bool), np.full(m, _NEVER, dtype=np.int64))


def traffic_at(
    params: CutInParams,
    step: int,
    x_m: np.ndarray,
    y_m: np.ndarray,
    heading_rad: np.ndarray,
    speed_mps: np.ndarray,
    memory: CutInMemory,
) -> tuple[Traffic, CutInMemory]:
    """The :class:`Traffic` of vehicles in the given state (float64 ``[M]`` each) at ``step``, and the cut-in memory
    for the next step: a cut-in begins where ``cutting_in`` rises and is recent while ``step - start <=
    cut_in_grace_steps`` (R_G1's ``once[0, t_c](cut_in & prev(!cut_in))``)."""
    x, y, h, s = (np.asarray(a, dtype=np.float64) for a in (x_m, y_m, heading_rad, speed_mps))
    cos, sin = np.cos(h), np.sin(h)
    half_l, half_w = params.vehicle_length_m / 2.0, params.vehicle_width_m / 2.0
    half_x = np.abs(half_l * cos) + np.abs(half_w * sin)  # the rotated box's corners' largest offsets
    half_y = np.abs(half_l * sin) + np.abs(half_w * cos)
    lane_lo, lane_hi = params.ego_y_m - LANE_WIDTH_M / 2, params.ego_y_m + LANE_WIDTH_M / 2
    lo, hi = y - half_y, y + half_y
    in_lane = (hi > lane_lo) & (lo < lane_hi)
    ego_lo, ego_hi = params.ego_y_m - params.vehicle_width_m / 2, params.ego_y_m + params.vehicle_width_m / 2
    beside = (hi > ego_lo) & (lo < ego_hi)
    vy = s * sin
    straddles = (lo < lane_lo) | (hi > lane_hi)
    cutting_in = in_lane & straddles & (vy * (params.ego_y_m - y) > 0.0)
    last_start = np.where(cutting_in & ~memory.was_cutting_in, step, memory.last_start)
    recent = step - last_start <= params.cut_in_grace_steps
    loc_lo, loc_hi = lo - params.ego_y_m, hi - params.ego_y_m
    m = x.shape[0]
    pairs = tuple(
        (i, j)
        for j in range(m)
        for i in range(m)
        if x[i] < x[j] and not (loc_hi[i] < 0.0 < loc_lo[j] or loc_hi[j] < 0.0 < loc_lo[i])
    )
    col = lambda a: a[:, None]  # noqa: E731
    traffic = Traffic(
        x,
        y,
        h,
        s,
        s * cos,
        vy,
        half_x,
        half_y,
        col(x - half_x),
        col(x + half_x),
        col(loc_lo),
        col(loc_hi),
        _wrap(h - np.pi / 2.0),
        in_lane,
        col(beside),
        cutting_in,
        recent,
        pairs,
    )
    return traffic, CutInMemory(cutting_in, last_start)


@dataclass(frozen=True)
class CameraView:
    """What the ego's camera sees of each object: arrays ``[M, N]`` (object-major: one row per object).

    Attributes:
        loc_x_m: ``[M, 1]`` camera-frame centre to the right (the same for every rollout: the ego keeps its lane);
        loc_z_m: camera-frame centre forward.
        truncation, occluded_fraction: shares of the 2D box outside the image and covered by nearer objects.
        inside: area of the 2D box inside the image (normalised image units).
        visible: bool."""

    loc_x_m: np.ndarray
    loc_z_m: np.ndarray
    truncation: np.ndarray
    occluded_fraction: np.ndarray
    inside: np.ndarray
    visible: np.ndarray


def _column(x: np.ndarray) -> np.ndarray:
    """``[M]`` as a column ``[M, 1]`` to broadcast against the rollouts' ``[M, N]``; ``[M, N]`` as it is (each rollout's
    own positions: :class:`pemviz.scenarios.cut_in.batched.BatchedCutIn`'s ``gap_shift_m``)."""
    return x[:, None] if x.ndim == 1 else x


def camera_view(params: CutInParams, traffic: Traffic, ego_x_m: np.ndarray) -> CameraView:
    """The camera's view of the traffic from ego positions ``ego_x_m`` ``[N]`` (module docstring), the 2D box that
    of the vehicle's axis-aligned footprint (:attr:`Traffic.half_x_m`, ``half_y_m``): ``u_hi = max(X_hi / Z_near,
    X_hi / Z_far)``, ``u_lo = min(X_lo / Z_near, X_lo / Z_far)``."""
    cam_x = ego_x_m + params.camera_offset_m
    loc_z = _column(traffic.x_m) - cam_x
    z_near = np.maximum(loc_z - traffic.half_x_m[:, None], _MIN_DEPTH_M)
    z_far = np.maximum(loc_z + traffic.half_x_m[:, None], _MIN_DEPTH_M)
    x_lo, x_hi = traffic.loc_x_lo_m, traffic.loc_x_hi_m
    u_hi = np.maximum(x_hi / z_near, x_hi / z_far)
    u_lo = np.minimum(x_lo / z_near, x_lo / z_far)
    v_top = (params.camera_height_m - params.vehicle_height_m) / z_far
    v_bot = params.camera_height_m / z_near
    area = (u_hi - u_lo) * (v_bot - v_top)
    left, right, _, bottom = IMAGE_BOUNDS  # the roofs are below the camera: v_top > 0 > the image's top
    inside = np.maximum(np.minimum(u_hi, right) - np.maximum(u_lo, left), 0.0) * np.maximum(
        np.minimum(v_bot, bottom) - v_top, 0.0
    )
    # the pairs in a fixed order: the same sums whatever N
    occluded = camera.occluded_share(camera.ImageBox(u_lo, u_hi, v_top, v_bot), pairs=traffic.occluder_pairs)
    visible = (loc_z >= MIN_RANGE_M) & (inside > 0.0) & (occluded < params.occlusion_hidden)
    return CameraView((traffic.y_m - params.ego_y_m)[:, None], loc_z, 1.0 - inside / area, occluded, inside, visible)


def measure(
    params: CutInParams, view: CameraView, ego_x_m: np.ndarray, noise: np.ndarray, measured: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The measured positions of the objects (module docstring), ``[M, N]`` each.

    Args:
        params: the scenario's constants.
        view: the camera's view of the objects (:func:`camera_view`).
        ego_x_m: float64 ``[N]`` the ego's position along the road (metres).
        noise: float64 ``[M, N, 2]`` (range error, lateral error; metres), read only where ``measured``.
        measured: bool ``[M, N]`` (detected and visible).
    Returns:
        ``(z_x, z_y, z_range)``: the measured centre along and across the road (m) and the measured range ``Z_m``
        along the camera axis (at least :data:`MIN_RANGE_M`: the pinhole reads no range behind the camera); the true
        values (no error) where not measured, so that every entry is finite."""
    d_range = np.where(measured, noise[..., 0], 0.0)
    d_lat = np.where(measured, noise[..., 1], 0.0)
    z_true = np.maximum(view.loc_z_m, MIN_RANGE_M)
    z_meas = np.maximum(z_true + d_range, MIN_RANGE_M)
    x_meas = (view.loc_x_m + d_lat) * (z_meas / z_true)
    return (ego_x_m + params.camera_offset_m) + z_meas, params.ego_y_m + x_meas, z_meas


def object_rows(
    params: CutInParams,
    traffic: Traffic,
    view: CameraView,
    ego_x_m: np.ndarray,
    ego_speed_mps: np.ndarray,
    ego_accel_mps2: np.ndarray,
    tracks: Tracks,
    followed: np.ndarray,
) -> np.ndarray:
    """The object rows at this step, float64 ``[N, M, G]`` (:data:`~pemviz.scenarios.cut_in.scenario.OBJECT_NAMES`): a
    transposed view of a ``[G, N, M]`` array (each column written in one pass), so that its ``reshape(N M, G)``, the
    rows of every rollout's objects together, is a view too.

    Args:
        params: the scenario's constants.
        traffic: the other vehicles at this step.
        view: the camera's view of them (:func:`camera_view`).
        ego_x_m: float64 ``[N]`` the ego's position along the road (metres).
        ego_speed_mps: float64 ``[N]`` its speed (m/s).
        ego_accel_mps2: float64 ``[N]`` its acceleration (m/s^2).
        tracks: the trackers' predictions ``[M, N]`` for this step.
        followed: int ``[N]``, the object the ACC followed at the last step (-1 none)."""
    m, n = view.loc_z_m.shape
    cols = np.empty((len(OBJECT_NAMES), n, m)).transpose(0, 2, 1)  # [G, M, N] views of [N, M] columns
    loc_x, loc_z = view.loc_x_m, view.loc_z_m
    cols[0] = np.sqrt(loc_x * loc_x + loc_z * loc_z)
    cols[1] = 0.0  # class: Car
    cols[2] = view.truncation
    cols[3] = camera.occlusion_level(view.occluded_fraction, params.occlusion_partly, params.occlusion_largely)
    np.subtract(traffic.rot_y_rad[:, None], libm.atan2(loc_x, loc_z), out=cols[4])  # alpha: rot_y minus the ray angle
    _wrap(cols[4])
    cols[5] = params.vehicle_height_m
    cols[6] = params.vehicle_width_m
    cols[7] = params.vehicle_length_m
    cols[8] = loc_x
    cols[9] = params.camera_height_m  # the box's bottom centre on the road, below the camera
    cols[10] = loc_z
    cols[11] = traffic.rot_y_rad[:, None]
    cols[12] = traffic.rear_m - (ego_x_m + params.vehicle_length_m / 2)
    cols[13] = traffic.vx_mps[:, None] - ego_speed_mps
    cols[14] = traffic.vy_mps[:, None]
    cols[15] = view.occluded_fraction
    cols[16] = view.visible
    cols[17] = traffic.in_ego_lane[:, None]
    cols[18] = tracks.confirmed
    np.multiply(tracks.x - _column(traffic.x_m), tracks.active, out=cols[19])
    np.multiply(tracks.y - traffic.y_m[:, None], tracks.active, out=cols[20])
    cols[21] = followed == np.arange(m)[:, None]
    cols[22] = ego_speed_mps
    cols[23] = ego_accel_mps2
    return cols.transpose(2, 1, 0)


def scene_signals(
    params: CutInParams,
    traffic: Traffic,
    ego_x_m: np.ndarray,
    ego_speed_mps: np.ndarray,
    ego_accel_mps2: np.ndarray,
    tracks: Tracks,
    followed: np.ndarray,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """The scene signals ``[N, F]`` (:data:`~pemviz.scenarios.cut_in.scenario.OBSERVATION_NAMES`) at this step.

    Args: as :func:`object_rows`; ``out``: optional float64 ``[N, F]`` to fill."""
    n = ego_x_m.shape[0]
    obs = np.empty((n, len(OBSERVATION_NAMES))) if out is None else out
    rows = np.arange(n)
    half_l = params.vehicle_length_m / 2
    ego_front, ego_rear = ego_x_m + half_l, ego_x_m - half_l
    ahead = traffic.in_ego_lane[:, None] & (_column(traffic.x_m) > ego_x_m)
    gaps = np.where(ahead, traffic.rear_m - ego_front, np.inf)
    front_index = np.argmin(gaps, axis=0)
    gap = gaps[front_index, rows]
    has_front = np.isfinite(gap)
    front_speed = np.where(has_front, traffic.vx_mps[front_index], ego_speed_mps)
    separation = np.maximum(traffic.rear_m - ego_front, ego_rear - traffic.front_m)
    clearance = np.where(traffic.beside_ego, separation, np.inf).min(axis=0)
    followed_x = tracks.x[np.maximum(followed, 0), rows]
    obs[:, 0] = np.where(has_front, gap, NO_VEHICLE_M)
    obs[:, 1] = np.where(has_front, gap - safe_distance(params, ego_speed_mps, front_speed), NO_VEHICLE_M)
    obs[:, 2] = has_front & traffic.cut_in_recent[front_index]
    obs[:, 3] = np.where(np.isfinite(clearance), clearance, NO_VEHICLE_M)
    obs[:, 4] = ego_speed_mps
    obs[:, 5] = ego_accel_mps2
    obs[:, 6] = front_speed
    obs[:, 7] = np.where(has_front, front_index, -1)
    obs[:, 8] = followed
    obs[:, 9] = np.where(followed >= 0, followed_x - half_l - ego_front, NO_VEHICLE_M)
    obs[:, 10] = ego_x_m
    return obs


def decide(
    params: CutInParams,
    view: CameraView,
    ego_x_m: np.ndarray,
    ego_speed_mps: np.ndarray,
    tracks: Tracks,
    detected: np.ndarray,
    noise: np.ndarray | None,
) -> tuple[Tracks, np.ndarray, np.ndarray]:
    """The ego's decision at this step: measure the detected visible objects (:func:`measure`), fold the measurements
    into the tracks (:func:`pemviz.stack.tracker.update`) and run the ACC on the tracks
    (:func:`~pemviz.scenarios.cut_in.scenario.acc_control`) on the confirmed tracks.

    Args:
        params: the scenario's constants.
        view: the camera's view of the objects (:func:`camera_view`).
        ego_x_m: float64 ``[N]`` the ego's position along the road (metres).
        ego_speed_mps: float64 ``[N]`` its speed (m/s).
        tracks: the trackers' predictions for this step ``[M, N]``.
        detected: bool ``[M, N]`` the objects detected.
        noise: float64 ``[M, N, 2]`` measurement errors (metres; read where detected), or None (no error).
    Returns:
        (the tracks after the update, followed int64 ``[N]`` (-1 none), the ACC's acceleration ``[N]`` in m/s^2)."""
    measured = detected & view.visible
    if noise is None:
        noise = np.zeros(measured.shape + (2,))
    z_x, z_y, z_range = measure(params, view, ego_x_m, noise, measured)
    tracks = tracker.update(tracks, measured, z_x, z_y, z_range, ego_speed_mps, params.tracker)
    followed, accel = acc_control(params, tracks.x, tracks.y, tracks.vx, tracks.confirmed, ego_x_m, ego_speed_mps)
    return tracks, followed, accel
