"""The cut-in scenario on highway-env vehicles and roads, one rollout stepped as a black box.

The ego is a :class:`highway_env.vehicle.kinematics.Vehicle` driven by the ACC (no steering); the others are
:class:`highway_env.vehicle.controller.ControlledVehicle` objects, the cut-in vehicle told ``"LANE_LEFT"`` or
``"LANE_RIGHT"`` at ``CutInParams.cut_in_step``. Vehicles are stepped one by one (``act`` then ``step(dt)``), so
highway-env applies no collision response: collisions are read from the geometry. Perception, tracker and ACC are
the array functions of :mod:`pemviz.scenarios.cut_in.scene` with N = 1, so the batched twin gives the same bits.

Units: metres, seconds, m/s."""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pemviz.scenarios.cut_in.scenario import (
    EGO_LANE,
    LANE_WIDTH_M,
    N_LANES,
    OBJECT_NAMES,
    OBSERVATION_NAMES,
    ROAD_LENGTH_M,
    CutInParams,
)
from pemviz.scenarios.cut_in.scene import (
    CameraView,
    CutInMemory,
    Traffic,
    camera_view,
    decide,
    object_rows,
    scene_signals,
    traffic_at,
)
from pemviz.stack import tracker
from pemviz.stack.detector import NOISE_NAMES

if TYPE_CHECKING:
    from highway_env.road.road import Road
    from highway_env.vehicle.controller import ControlledVehicle
    from highway_env.vehicle.kinematics import Vehicle


def build_road(params: CutInParams, with_ego: bool = True) -> tuple[Road, Vehicle | None, list[ControlledVehicle]]:
    """A fresh highway-env road with the traffic at t = 0 (and the ego at x = 0 in the middle lane).

    Returns:
        ``(road, ego or None, [vehicle 0 (the cut-in), vehicle 1, ...])``."""
    from highway_env.road.road import Road, RoadNetwork
    from highway_env.vehicle.controller import ControlledVehicle
    from highway_env.vehicle.kinematics import Vehicle

    net = RoadNetwork.straight_road_network(lanes=N_LANES, length=ROAD_LENGTH_M, speed_limit=None)
    road = Road(network=net)
    length, width = params.vehicle_length_m, params.vehicle_width_m
    ego = None
    if with_ego:
        ego = Vehicle(road, [0.0, params.ego_y_m], heading=0.0, speed=params.ego_speed0_mps)
        road.vehicles.append(ego)
    others = []
    for spec in params.vehicles:
        x = length / 2 + spec.gap_m + length / 2  # ego front at +L/2; the vehicle's rear gap_m ahead of it
        v = ControlledVehicle(
            road, [x, spec.lane * LANE_WIDTH_M], heading=0.0, speed=spec.speed_mps, target_speed=spec.speed_mps
        )
        others.append(v)
        road.vehicles.append(v)
    for v in ([ego] if ego is not None else []) + others:
        v.LENGTH, v.WIDTH = length, width
    cut_in = others[0]
    cut_in.TAU_LATERAL = params.cut_in_lateral_time_s
    cut_in.KP_LATERAL = 1.0 / params.cut_in_lateral_time_s
    return road, ego, others


def step_traffic(params: CutInParams, others: list, step: int) -> None:
    """Advance the traffic one step: the cut-in vehicle is told to change lanes at ``params.cut_in_step``."""
    lane_change = "LANE_LEFT" if params.cut_in_lane > EGO_LANE else "LANE_RIGHT"
    for i, v in enumerate(others):
        v.act(lane_change if (i == 0 and step == params.cut_in_step) else None)
    for v in others:
        v.step(params.dt_s)


def vehicle_state(others: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(x, y, heading, speed)`` float64 ``[M]`` of highway-env vehicles."""
    return (
        np.array([v.position[0] for v in others]),
        np.array([v.position[1] for v in others]),
        np.array([float(v.heading) for v in others]),
        np.array([float(v.speed) for v in others]),
    )


_SNAPSHOT_FIELDS = ("road", "ego", "others", "t", "tracks", "followed", "accel", "_memory", "traffic")
"""What :meth:`CutInScenario.snapshot` copies and :meth:`CutInScenario.restore` puts back."""


@dataclass(frozen=True)
class TrafficTrajectory:
    """The traffic at steps 0..T, shared by every rollout: ``traffic[t]`` is a :class:`Traffic` (arrays ``[M]``)."""

    traffic: tuple[Traffic, ...]


def traffic_trajectory(params: CutInParams) -> TrafficTrajectory:
    """The traffic's states at steps 0..T from highway-env vehicles on a road without the ego (they never react to
    it), with the geometry of :func:`pemviz.scenarios.cut_in.scene.traffic_at` at each step."""
    _, _, others = build_road(params, with_ego=False)
    memory = CutInMemory.initial(len(others))
    out = []
    for t in range(params.n_steps + 1):
        traffic, memory = traffic_at(params, t, *vehicle_state(others), memory)
        out.append(traffic)
        if t < params.n_steps:
            step_traffic(params, others, t)
    return TrafficTrajectory(tuple(out))


class CutInScenario:
    """One rollout of the cut-in scenario on highway-env vehicles (module docstring).

    Protocol: ``objects()`` float64 ``[M, G]`` (:data:`OBJECT_NAMES`), ``observation()`` float64 ``[F]``
    (:data:`OBSERVATION_NAMES`), then ``step(detected bool [M], noise float64 [M, 2] | None)``
    (:data:`NOISE_NAMES`: range and lateral errors, metres, used where detected); ``params.n_steps`` steps."""

    observation_names = OBSERVATION_NAMES
    object_names = OBJECT_NAMES
    noise_names = NOISE_NAMES

    def __init__(self, params: CutInParams | None = None) -> None:
        self.params = params or CutInParams()
        self.n_objects = self.params.n_objects
        self.reset()

    def reset(self) -> None:
        """Every vehicle at its start; no tracks."""
        p = self.params
        self.road, ego, self.others = build_road(p)
        assert ego is not None  # built with the ego
        self.ego = ego
        self.t = 0
        self.tracks = tracker.Tracks.empty((p.n_objects, 1))
        self.followed = np.full(1, -1, dtype=np.int64)
        self.accel = np.zeros(1)
        self._memory = CutInMemory.initial(p.n_objects)
        self._observe_traffic()

    def _observe_traffic(self) -> None:
        self.traffic, self._memory = traffic_at(self.params, self.t, *vehicle_state(self.others), self._memory)
        self._view: CameraView | None = None

    @property
    def done(self) -> bool:
        return self.t >= self.params.n_steps

    def _ego(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array([self.ego.position[0]]), np.array([float(self.ego.speed)])

    def view(self) -> CameraView:
        """The camera's view at this step (``[M, 1]`` arrays)."""
        if self._view is None:
            self._view = camera_view(self.params, self.traffic, self._ego()[0])
        return self._view

    def objects(self) -> np.ndarray:
        """The M object rows at this step, float64 ``[M, G]``."""
        x, v = self._ego()
        return np.ascontiguousarray(
            object_rows(self.params, self.traffic, self.view(), x, v, self.accel, self.tracks, self.followed)[0]
        )

    def observation(self) -> np.ndarray:
        """The scene signals at this step, float64 ``[F]``."""
        x, v = self._ego()
        return scene_signals(self.params, self.traffic, x, v, self.accel, self.tracks, self.followed)[0]

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None:
        """Advance one step of ``dt`` seconds given this step's detections and measurement errors.

        Args:
            detected: bool ``[M]`` the cars detected.
            noise: float64 ``[M, 2]`` (range, lateral error; metres) or None (no error).
        Raises:
            RuntimeError: the rollout is over (``n_steps`` steps taken).
            ValueError: ``detected`` or ``noise`` of the wrong shape."""
        p = self.params
        if self.done:
            raise RuntimeError(f"CutInScenario.step: rollout over after {p.n_steps} steps; call reset()")
        detected = np.asarray(detected, dtype=bool)
        m = p.n_objects
        if detected.shape != (m,):
            raise ValueError(f"CutInScenario.step: detected must be bool [{m}], got shape {detected.shape}")
        if noise is not None:
            noise = np.asarray(noise, dtype=np.float64)
            if noise.shape != (m, 2):
                raise ValueError(
                    f"CutInScenario.step: noise must be float64 [{m}, 2] (range, lateral error; metres), "
                    f"got shape {noise.shape}"
                )
            noise = noise[:, None, :]
        x, v = self._ego()
        self.tracks, self.followed, accel = decide(p, self.view(), x, v, self.tracks, detected[:, None], noise)
        self.ego.act({"steering": 0.0, "acceleration": float(accel[0])})
        self.ego.step(p.dt_s)
        self.ego.speed = max(self.ego.speed, 0.0)  # v + (-v/dt) dt can round to -1e-16
        self.accel = np.array([self.ego.action["acceleration"]])  # after highway-env's clip_actions
        step_traffic(p, self.others, self.t)
        self.tracks = tracker.predict(self.tracks, p.dt_s, p.tracker)
        self.t += 1
        self._observe_traffic()

    def snapshot(self) -> tuple:
        """A deep copy of the road, the vehicles and the ego's memory (tracks, ACC, cut-in memory)."""
        return copy.deepcopy(tuple(getattr(self, name) for name in _SNAPSHOT_FIELDS))

    def restore(self, state: tuple) -> None:
        """Put back a :meth:`snapshot` (copied again, so it can be restored more than once)."""
        for name, value in zip(_SNAPSHOT_FIELDS, copy.deepcopy(state), strict=True):
            setattr(self, name, value)
        self._view = None
