"""The crossing scenario's scene: an ego car approaching a pedestrian crossing, pedestrians stepping out, an emergency
brake acting on tracked pedestrians. Built only from the library's perception stack (:mod:`pemviz.stack`), as a
scene of one's own would be.

The ego (4.5 m x 1.8 m) drives at ``ego_speed_mps`` towards a crossing ``crossing_m`` ahead; pedestrian 0 steps out
from the left kerb at ``step_out_s`` and walks across at ``walk_speed_mps``, pedestrian 1 (``n_pedestrians = 2``)
from the right kerb ``second_delay_s`` later; they do not react to the ego. The camera (:mod:`pemviz.stack.camera`)
perceives each pedestrian through the detection and noise PEMs (:func:`pemviz.stack.detector.camera_detector`) and a
Kalman tracker per pedestrian (:mod:`pemviz.stack.tracker`) estimates it. The **emergency brake** brakes at
``brake_mps2`` from the first step a confirmed track threatens: ``ttc = gap / speed`` at most ``brake_ttc_s`` and
the track, moved on for ``ttc``, within ``corridor_m`` of the lane's centre.

The failure: ``G(clearance >= 0)``, the signed separation of the ego's and a pedestrian's boxes (``clearance_m``).

Units: metres, seconds, m/s, m/s^2, radians."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pemviz.stack import camera, tracker
from pemviz.stack.camera import PEDESTRIAN, SALIENT_NAMES

EGO_LENGTH_M, EGO_WIDTH_M = 4.5, 1.8
"""The ego's box (m)."""
CAMERA_HEIGHT_M = 1.65
"""The camera above the road (m; KITTI's)."""
NO_PEDESTRIAN_M = 100.0
"""What the distance signals read with no pedestrian to measure: finite, so that robustness stays finite."""
SECOND_OFFSET_M = 1.5
"""Pedestrian 1 crosses this much further along the road than pedestrian 0 (m)."""

OBSERVATION_NAMES: tuple[str, ...] = ("gap_m", "clearance_m", "ego_speed_mps", "braking", "ego_x_m")
"""The scene's signals [F]: the distance along the road from the ego's front to the nearest pedestrian still ahead of
it (m; :data:`NO_PEDESTRIAN_M` when none), the smallest signed separation of the ego's box from a pedestrian's (m;
negative: they overlap), the ego's speed, 1.0 once the AEB brakes, and the ego's position along the road."""

OBJECT_NAMES: tuple[str, ...] = (
    "range_m",
    *SALIENT_NAMES,
    "visible",
    "lateral_m",
    "ttc_s",
    "tracked",
    "braking",
    "ego_speed_mps",
)
"""Each pedestrian's row [G]: its range from the camera (the window's column), the 11 salient variables
(:data:`pemviz.stack.camera.SALIENT_NAMES`), visible, its lateral position (m), the time for the ego to reach it (s,
at most 10), track confirmed, and the ego's state (braking, speed)."""

FEATURE_NAMES: tuple[str, ...] = ("ego_speed_mps", "ego_braking", "time_s")
"""The ego's state features [F] (:meth:`BatchedCrossing.state_features`): its speed (m/s), 1.0 once the AEB brakes,
the time since the scene's start (s). Each pedestrian's are the tracker's (:data:`pemviz.stack.tracker.FEATURE_NAMES`),
its range measured from the ego's front plus half a pedestrian's width, as the AEB measures its gap."""

PEDESTRIAN_TRACKER = tracker.TrackerParams(
    accel_std_x_mps2=0.5, accel_std_y_mps2=1.0, init_speed_std_x_mps=0.5, init_speed_std_y_mps=1.5, max_coast_steps=3
)
"""The tracker tuned for pedestrians: little motion along the road, a walking speed across it unknown at the start
(std 1.5 m/s); a track is dropped after 3 predictions without an update."""


@dataclass(frozen=True)
class CrossingParams:
    """The crossing scenario's constants (module docstring).

    Raises:
        ValueError: a value out of its range."""

    ego_speed_mps: float = 12.0
    crossing_m: float = 40.0
    kerb_m: float = 3.5
    walk_speed_mps: float = 1.4
    step_out_s: float = 1.0
    n_pedestrians: int = 2
    second_delay_s: float = 0.8
    brake_ttc_s: float = 1.3
    brake_mps2: float = 8.0
    corridor_m: float = 1.5
    camera_offset_m: float = 1.0
    dt_s: float = 0.1
    n_steps: int = 50
    tracker: tracker.TrackerParams = field(default=PEDESTRIAN_TRACKER)

    def __post_init__(self) -> None:
        ranges = {
            "ego_speed_mps": (1.0, 30.0),
            "crossing_m": (5.0, 150.0),
            "kerb_m": (1.5, 10.0),
            "walk_speed_mps": (0.3, 4.0),
            "step_out_s": (0.0, 20.0),
            "second_delay_s": (0.0, 20.0),
            "brake_ttc_s": (0.1, 10.0),
            "brake_mps2": (1.0, 12.0),
            "corridor_m": (0.5, 5.0),
            "camera_offset_m": (-2.0, 2.25),
            "dt_s": (0.01, 0.5),
        }
        for name, (lo, hi) in ranges.items():
            value = getattr(self, name)
            if not lo <= value <= hi:
                raise ValueError(f"CrossingParams.{name} must be in [{lo:g}, {hi:g}], got {value!r}")
        if self.n_pedestrians not in (1, 2) or not 5 <= self.n_steps <= 1000:
            raise ValueError(
                f"CrossingParams: n_pedestrians must be 1 or 2 and n_steps in [5, 1000], got "
                f"{self.n_pedestrians}, {self.n_steps}"
            )

    def pedestrians(self, step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The pedestrians at ``step``: ``(x_m, y_m, vy_mps, rot_y_rad)``, arrays [M] (road frame; KITTI's rotation,
        0 walking to the right, pi to the left). Each walks from its kerb to the other and stops there."""
        m = self.n_pedestrians
        x = self.EGO_FRONT0 + self.crossing_m + SECOND_OFFSET_M * np.arange(m)
        side = np.array([1.0, -1.0])[:m]  # +1 walks to the right (from the left kerb)
        start = self.step_out_s + self.second_delay_s * np.arange(m)
        walked = np.clip(step * self.dt_s - start, 0.0, 2.0 * self.kerb_m / self.walk_speed_mps) * self.walk_speed_mps
        moving = (step * self.dt_s > start) & (walked < 2.0 * self.kerb_m)
        return (
            x,
            side * (walked - self.kerb_m),
            np.where(moving, side * self.walk_speed_mps, 0.0),
            np.where(side > 0, 0.0, np.pi),
        )

    EGO_FRONT0 = EGO_LENGTH_M / 2
    """The ego's front at t = 0 (its centre at x = 0)."""


PER_ROLLOUT: tuple[str, ...] = ("brake_ttc_s", "brake_mps2")
"""The AEB's parameters a rollout may have of its own (over an operating design domain: ``--param
brake_ttc_s~uniform(1.3, 1.5)``): they decide only when the AEB brakes and how hard, so the scene is the same."""


class BatchedCrossing:
    """n rollouts of the crossing scene stepped together (a :class:`pemviz.core.rollouts.BatchedSimulator` of M
    pedestrians with measurement errors): ``objects()`` float64 ``[n, M, G]``, ``observation()`` float64 ``[n, F]``,
    ``step(detected bool [n, M], noise float64 [n, M, 2] | None)``; ``per_rollout`` gives each rollout its own
    :data:`PER_ROLLOUT` parameters (float64 [n]; absent: ``params``').

    Raises:
        ValueError: ``n`` < 1, or another parameter in ``per_rollout``."""

    observation_names = OBSERVATION_NAMES
    object_names = OBJECT_NAMES
    feature_names = FEATURE_NAMES
    object_feature_names = tracker.FEATURE_NAMES

    def __init__(self, params: CrossingParams, n: int, per_rollout: dict[str, np.ndarray] | None = None) -> None:
        if n < 1:
            raise ValueError(f"BatchedCrossing: n must be >= 1, got {n}")
        if set(per_rollout or {}) - set(PER_ROLLOUT):
            raise ValueError(f"BatchedCrossing: per_rollout may set {PER_ROLLOUT}, got {sorted(per_rollout or {})}")
        self.p, self.n, self.n_objects = params, int(n), params.n_pedestrians
        own = per_rollout or {}
        self.brake_ttc_s, self.brake_mps2 = (
            np.asarray(own[k], dtype=np.float64).reshape(self.n) if k in own else np.full(self.n, getattr(params, k))
            for k in PER_ROLLOUT
        )
        self.t = 0
        self.x, self.v = np.zeros(n), np.full(n, params.ego_speed_mps)
        self.braking = np.zeros(n, bool)
        self.tracks = tracker.Tracks.empty((self.n_objects, self.n))
        self._seen: tuple[int, tuple[np.ndarray, np.ndarray, camera.CameraView, np.ndarray]] | None = None
        """The step and its :meth:`_view` (asked by ``objects`` and then by ``step``; the state moves only in
        ``step``)."""

    def _view(self) -> tuple[np.ndarray, np.ndarray, camera.CameraView, np.ndarray]:
        """The pedestrians seen from every rollout's camera: (loc_x [M, n], loc_z [M, n], view, their x [M])."""
        if self._seen is not None and self._seen[0] == self.t:
            return self._seen[1]
        x_p, y_p, _, rot = self.p.pedestrians(self.t)
        loc_z = x_p[:, None] - (self.x + self.p.camera_offset_m)
        loc_x = np.broadcast_to(y_p[:, None], loc_z.shape)
        seen = loc_x, loc_z, camera.view(PEDESTRIAN, loc_x, loc_z, rot[:, None], CAMERA_HEIGHT_M), x_p
        self._seen = (self.t, seen)
        return seen

    def _gaps(self, x_p: np.ndarray, y_p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(longitudinal, lateral) gaps [M, n] between the ego's box and each pedestrian's (m)."""
        dx = np.abs(x_p[:, None] - self.x) - (EGO_LENGTH_M + PEDESTRIAN.width_m) / 2
        dy = np.abs(y_p)[:, None] - (EGO_WIDTH_M + PEDESTRIAN.length_m) / 2 + 0.0 * self.x
        return dx, dy

    def objects(self) -> np.ndarray:
        """float64 [n, M, G] (:data:`OBJECT_NAMES`)."""
        loc_x, loc_z, view, x_p = self._view()
        ahead = x_p[:, None] - PEDESTRIAN.width_m / 2 - (self.x + EGO_LENGTH_M / 2)
        ttc = np.where(ahead > 0, np.minimum(ahead / np.maximum(self.v, 0.1), 10.0), 0.0)
        cols = [
            view.range_m[..., None],
            view.salient,
            view.visible[..., None],
            loc_x[..., None],
            ttc[..., None],
            self.tracks.confirmed[..., None],
            np.broadcast_to(self.braking, loc_z.shape)[..., None],
            np.broadcast_to(self.v, loc_z.shape)[..., None],
        ]
        return np.concatenate([np.asarray(c, dtype=np.float64) for c in cols], axis=-1).transpose(1, 0, 2)

    def state_features(self) -> tuple[np.ndarray, np.ndarray]:
        """The state the AEB acts on: float64 [n, F] (:data:`FEATURE_NAMES`) and [n, M, G] (the tracker's,
        :func:`pemviz.stack.tracker.features`)."""
        ego = np.stack([self.v, self.braking.astype(np.float64), np.full(self.n, self.t * self.p.dt_s)], axis=1)
        front = self.x + EGO_LENGTH_M / 2 + PEDESTRIAN.width_m / 2
        return ego, tracker.features(self.tracks, front, self.v)

    def observation(self) -> np.ndarray:
        """float64 [n, F] (:data:`OBSERVATION_NAMES`)."""
        x_p, y_p, _, _ = self.p.pedestrians(self.t)
        dx, dy = self._gaps(x_p, y_p)
        clearance = np.maximum(dx, dy).min(axis=0)
        ahead = x_p[:, None] - PEDESTRIAN.width_m / 2 - (self.x + EGO_LENGTH_M / 2)
        gap = np.where(ahead >= 0.0, ahead, np.inf).min(axis=0)
        return np.stack(
            [
                np.minimum(gap, NO_PEDESTRIAN_M),
                np.minimum(clearance, NO_PEDESTRIAN_M),
                self.v,
                self.braking.astype(np.float64),
                self.x,
            ],
            axis=1,
        )

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None:
        """Advance every rollout one step: measure the detected pedestrians, update the tracks, brake on a threat.

        Args:
            detected: bool [n, M] the pedestrians detected.
            noise: float64 [n, M, 2] (range, lateral error; metres) or None."""
        p = self.p
        loc_x, loc_z, view, _ = self._view()
        measured = np.asarray(detected, dtype=bool).T & view.visible
        x_m, z_m = camera.measure(
            loc_x, loc_z, None if noise is None else np.asarray(noise).transpose(1, 0, 2), measured
        )
        tracks = tracker.update(self.tracks, measured, self.x + p.camera_offset_m + z_m, x_m, z_m, 0.0, p.tracker)
        self.braking = self.braking | self._threat(tracks).any(axis=0)
        speed = np.where(self.braking, np.maximum(self.v - self.brake_mps2 * p.dt_s, 0.0), self.v)
        self.x = self.x + 0.5 * (self.v + speed) * p.dt_s
        self.v = speed
        self.tracks = tracker.predict(tracks, p.dt_s, p.tracker)
        self.t += 1

    def _threat(self, tracks: tracker.Tracks) -> np.ndarray:
        """bool [M, n]: the confirmed tracks the AEB brakes for (module docstring)."""
        p = self.p
        gap = tracks.x - PEDESTRIAN.width_m / 2 - (self.x + EGO_LENGTH_M / 2)
        ttc = gap / np.maximum(self.v, 0.1)
        in_path = (np.abs(tracks.y + tracks.vy * ttc) <= p.corridor_m) | (np.abs(tracks.y) <= p.corridor_m)
        return tracks.confirmed & (gap > -EGO_LENGTH_M) & (ttc <= self.brake_ttc_s) & in_path


def pedestrian_ahead_rows(params: CrossingParams, grid: np.ndarray) -> np.ndarray:
    """Object rows float64 [R, G] of a pedestrian walking across the ego's lane centre at each range of ``grid`` (m)
    from the camera, the ego at its speed and not braking: where the PEM's detection curve is drawn."""
    grid = np.asarray(grid, dtype=np.float64)
    view = camera.view(PEDESTRIAN, np.zeros_like(grid), grid, 0.0, CAMERA_HEIGHT_M)
    gap = grid + params.camera_offset_m - PEDESTRIAN.width_m / 2 - EGO_LENGTH_M / 2
    ttc = np.clip(gap / params.ego_speed_mps, 0.0, 10.0)
    zeros = np.zeros_like(grid)
    return np.column_stack(
        [view.range_m, view.salient, view.visible, zeros, ttc, zeros, zeros, np.full_like(grid, params.ego_speed_mps)]
    )
