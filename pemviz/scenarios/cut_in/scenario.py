"""The cut-in scenario: constants, names, the ego's ACC on tracked objects, and the safe-distance rule R_G1.

A straight three-lane highway (highway-env's ``straight_road_network``). The ego drives in the middle lane with an
adaptive cruise control; vehicle 0 of the M others changes lanes in front of it (the **cut-in**) at a scripted time;
none reacts to the ego. Its camera detects each object and measures it with range and lateral errors (a PEM draws
both), a Kalman tracker per object (:mod:`pemviz.stack.tracker`) estimates it, and the ACC follows the nearest
tracked vehicle ahead in its lane with highway-env's IDM (:func:`idm_acceleration`). The failure
(:data:`FAILURE_FORMULA`): a collision, or a violation of the safe-distance rule R_G1 of Maierhofer et al. 2020
(:func:`safe_distance`) outside ``cut_in_grace_s`` after a cut-in.

Units: metres, seconds, m/s, m/s^2, radians."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np

from pemviz.core import libm
from pemviz.pem.encoding import INPUT_COLUMNS
from pemviz.stack.tracker import TrackerParams

LANE_WIDTH_M = 4.0
"""highway-env's ``StraightLane.DEFAULT_WIDTH`` (the lane width of ``straight_road_network``)."""
N_LANES = 3
EGO_LANE = 1
"""The ego drives in the middle lane; lane ``i`` is centred at ``y = i * LANE_WIDTH_M``, lane 0 the leftmost."""
NO_VEHICLE_M = 200.0
"""What distance signals read when there is no vehicle to measure (no front vehicle, no vehicle beside): far enough
never to bind the rule, finite so that robustness stays finite."""
ROAD_LENGTH_M = 10000.0

OBSERVATION_NAMES: tuple[str, ...] = (
    "gap_m",
    "safe_margin_m",
    "cut_in_recent",
    "clearance_m",
    "ego_speed_mps",
    "ego_accel_mps2",
    "front_speed_mps",
    "front_index",
    "followed_index",
    "followed_gap_m",
    "ego_x_m",
)
"""Scene signals, [F], true state unless said otherwise:

- ``gap_m``: from the ego's front bumper to the rear of the front vehicle (the nearest one ahead whose box overlaps
  the ego's lane), metres; :data:`NO_VEHICLE_M` when there is none;
- ``safe_margin_m``: ``gap_m`` minus the safe distance of R_G1 (:func:`safe_distance`) to the front vehicle;
- ``cut_in_recent``: 1.0 if the front vehicle cut in within the last ``cut_in_grace_s`` (R_G1 does not apply), else
  0.0;
- ``clearance_m``: the smallest longitudinal separation to a vehicle whose box overlaps the ego's box laterally
  (negative: the boxes overlap, a collision);
- ``ego_speed_mps``; ``ego_accel_mps2`` (applied over the last step);
- ``front_speed_mps``: the front vehicle's velocity along the road (the ego's speed when there is none);
- ``front_index``: the front vehicle's object index, -1 when none;
- ``followed_index``: the object the ACC followed at the last step (its tracked estimate in the ego's lane), -1 none;
- ``followed_gap_m``: the ESTIMATED gap to it (tracked centre minus half a vehicle length minus the ego's front);
- ``ego_x_m``: the ego's position along the road (centre)."""

SALIENT_NAMES: tuple[str, ...] = tuple(INPUT_COLUMNS)
"""The 11 KITTI salient variables of an object, in the PEMs' raw-input order
(:data:`pemviz.pem.encoding.INPUT_COLUMNS`). The three dimension columns hold KITTI's (height, width, length), the order
of the KITTI labels and of the salient files' values (their header calls them dim_w, dim_l, dim_h)."""
SALIENT_COLUMNS = slice(1, 1 + len(SALIENT_NAMES))
"""Where the salient variables sit in an object row: ``rows[..., SALIENT_COLUMNS]`` are a PEM's raw inputs."""

OBJECT_NAMES: tuple[str, ...] = (
    "range_m",
    *SALIENT_NAMES,
    "gap_m",
    "rel_speed_mps",
    "lateral_speed_mps",
    "occluded_fraction",
    "visible",
    "in_ego_lane",
    "tracked",
    "track_err_x_m",
    "track_err_y_m",
    "followed",
    "ego_speed_mps",
    "ego_accel_mps2",
)
"""Columns of one object row, [G]: ``range_m`` (camera to the object's centre on the ground); the 11 salient
variables (:data:`SALIENT_NAMES`, KITTI's camera frame); ``gap_m`` (object rear minus ego front, negative beside or
behind); ``rel_speed_mps`` and ``lateral_speed_mps``; ``occluded_fraction``; ``visible`` (1.0 if the camera can see
it at all: a PEM detector gives other rows p(detect) = 0); ``in_ego_lane``; ``tracked`` (a confirmed track the ACC
may follow) and its errors ``track_err_x_m``, ``track_err_y_m`` (0 without a track); ``followed`` (by the ACC at the
last step); ``ego_speed_mps``, ``ego_accel_mps2``."""


FAILURE_FORMULA = "G(safe_margin_m + 1000 * cut_in_recent >= 0) & G(clearance_m >= 0)"
"""The failure, in pemviz's STL over :data:`OBSERVATION_NAMES`: at some step the ego is closer to the vehicle in
front than the safe distance while that vehicle did not cut in within ``cut_in_grace_s`` (R_G1 of Maierhofer et al.
2020), or it collides. R_G1 is written with arithmetic, ``G(cut_in_recent > 0.5 | safe_margin_m >= 0)`` failing on
the same traces, so that its robustness stays the margin in metres during a waiver (classic semantics)."""


@dataclass(frozen=True)
class OtherVehicle:
    """One vehicle of the traffic at t = 0: its lane (0, 1 or 2), the gap from the ego's front bumper to its rear
    (metres, along the road) and its speed (m/s). It keeps its lane and speed (highway-env ``ControlledVehicle``)."""

    lane: int
    gap_m: float
    speed_mps: float


DEFAULT_TRAFFIC: tuple[OtherVehicle, ...] = (
    OtherVehicle(lane=0, gap_m=12.0, speed_mps=27.0),
    OtherVehicle(lane=2, gap_m=45.0, speed_mps=23.0),
    OtherVehicle(lane=0, gap_m=55.0, speed_mps=28.0),
    OtherVehicle(lane=2, gap_m=80.0, speed_mps=24.0),
    OtherVehicle(lane=1, gap_m=120.0, speed_mps=28.0),
)
"""The vehicles after the cut-in vehicle, in object order 1, 2, ...; :attr:`CutInParams.n_objects` takes the first
``n_objects - 1`` of them. With the default 5 objects the ego's lane is free until the cut-in, so the ACC cruises at
its set speed whatever the camera reports of the other lanes; the sixth is a lead far ahead in the ego's lane."""


@dataclass(frozen=True)
class IDMParams:
    """highway-env's ``IDMVehicle`` constants (``highway_env/vehicle/behavior.py``, 1.12), the ACC's defaults.

    ``distance_wanted_m`` is centre to centre (highway-env: 5 m + a vehicle length); accelerations in m/s^2."""

    comfort_acc_max_mps2: float = 3.0
    comfort_acc_min_mps2: float = -5.0
    distance_wanted_m: float = 10.0
    time_wanted_s: float = 1.5
    delta: float = 4.0
    acc_max_mps2: float = 6.0


MAX_STEPS = 10_000
"""The most steps T of a cut-in rollout (1,000 s at the default 0.1 s step)."""


CUT_IN_TRACKER = TrackerParams(init_speed_std_x_mps=5.0)
"""The cut-in's tracker: the library's defaults, but a new track's velocity prior sure to 5 m/s of the ego's speed
(the cut-in's cars all move with the ego; the library's default, 15 m/s, is for scenes where an object may stand)."""


@dataclass(frozen=True)
class CutInParams:
    """Every constant of the cut-in scenario.

    Attributes:
        dt_s, n_steps: the step (s) and the number of steps T of a rollout.
        n_objects: M, the other vehicles (3 to 6): the cut-in vehicle, then the first ``M - 1`` of ``traffic``.
        ego_speed0_mps, ego_target_speed_mps: the ego's start speed and its ACC's set speed.
        cut_in_lane: the lane the cut-in vehicle starts in (0 left or 2 right of the ego's).
        cut_in_gap_m: the gap from the ego's front bumper to the cut-in vehicle's rear at t = 0.
        cut_in_speed_mps: its speed (kept through the lane change).
        cut_in_time_s: when it starts to change lanes.
        cut_in_lateral_time_s: the time constant of its lateral controller (highway-env's ``TAU_LATERAL``).
        traffic: the other vehicles (:data:`DEFAULT_TRAFFIC`).
        vehicle_length_m, vehicle_width_m, vehicle_height_m: every vehicle's box.
        camera_offset_m, camera_height_m: the camera ahead of the ego's centre and above the road.
        occlusion_partly, occlusion_largely, occlusion_hidden: the occluded shares of the 2D box from which an
            object is partly occluded (KITTI level 1), largely (level 2) and hidden; the Caltech bins (Dollar et al.
            2012, "Pedestrian Detection: An Evaluation of the State of the Art", IEEE TPAMI 34(4), Sec. 2.2).
        idm: the ACC's IDM constants.
        tracker: the tracker's noise model and track management (:data:`CUT_IN_TRACKER`).
        ego_a_min_mps2, other_a_min_mps2, reaction_time_s, cut_in_grace_s: R_G1's parameters
            (:func:`safe_distance`): the assumed braking of the ego and of the vehicle in front, the ego's reaction
            time and the time ``t_c`` after a cut-in during which the rule is waived.
    Raises:
        ValueError: a value outside its range (the message names the field, what is allowed and what was given)."""

    dt_s: float = 0.1
    n_steps: int = 100
    n_objects: int = 5
    ego_speed0_mps: float = 25.0
    ego_target_speed_mps: float = 25.0
    cut_in_lane: int = 2
    cut_in_gap_m: float = 20.0
    cut_in_speed_mps: float = 17.4
    cut_in_time_s: float = 1.0
    cut_in_lateral_time_s: float = 1.0
    traffic: tuple[OtherVehicle, ...] = DEFAULT_TRAFFIC
    vehicle_length_m: float = 5.0
    vehicle_width_m: float = 2.0
    vehicle_height_m: float = 1.5
    camera_offset_m: float = 2.0
    camera_height_m: float = 1.65
    occlusion_partly: float = 0.01
    occlusion_largely: float = 0.35
    occlusion_hidden: float = 0.8
    idm: IDMParams = field(default_factory=IDMParams)
    tracker: TrackerParams = field(default_factory=lambda: CUT_IN_TRACKER)
    ego_a_min_mps2: float = -10.0
    other_a_min_mps2: float = -10.5
    reaction_time_s: float = 0.3
    cut_in_grace_s: float = 3.0

    def __post_init__(self) -> None:
        def bad(what: str, allowed: str, value: object) -> ValueError:
            return ValueError(f"CutInParams: {what} must be {allowed}, got {value!r}")

        if not (isinstance(self.n_steps, int) and 1 <= self.n_steps <= MAX_STEPS):
            raise bad("n_steps", f"an integer in 1..{MAX_STEPS}", self.n_steps)
        if not (isinstance(self.n_objects, int) and 3 <= self.n_objects <= 1 + len(self.traffic)):
            raise bad(
                "n_objects",
                f"an integer in 3..{min(6, 1 + len(self.traffic))} (the cut-in vehicle and "
                "the first n_objects - 1 of traffic)",
                self.n_objects,
            )
        if self.n_objects > 6:
            raise bad("n_objects", "at most 6", self.n_objects)
        if self.cut_in_lane not in (EGO_LANE - 1, EGO_LANE + 1):
            raise bad("cut_in_lane", f"{EGO_LANE - 1} or {EGO_LANE + 1} (a lane beside the ego's)", self.cut_in_lane)
        for v in self.traffic:
            if v.lane not in range(N_LANES):
                raise bad("traffic lane", f"one of 0..{N_LANES - 1}", v.lane)
        positive = (
            "dt_s",
            "ego_speed0_mps",
            "ego_target_speed_mps",
            "cut_in_speed_mps",
            "cut_in_lateral_time_s",
            "vehicle_length_m",
            "vehicle_width_m",
            "vehicle_height_m",
            "camera_height_m",
            "reaction_time_s",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise bad(name, "finite and > 0", value)
        for name in ("cut_in_gap_m", "cut_in_time_s", "cut_in_grace_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise bad(name, "finite and >= 0", value)
        if not math.isfinite(self.camera_offset_m):
            raise bad("camera_offset_m", "finite", self.camera_offset_m)
        if not (0 < self.occlusion_partly < self.occlusion_largely < self.occlusion_hidden <= 1):
            raise bad(
                "occlusion thresholds",
                "0 < partly < largely < hidden <= 1",
                (self.occlusion_partly, self.occlusion_largely, self.occlusion_hidden),
            )
        if not (
            self.ego_a_min_mps2 < 0
            and self.other_a_min_mps2 < 0
            and math.isfinite(self.ego_a_min_mps2)
            and math.isfinite(self.other_a_min_mps2)
        ):
            raise bad(
                "ego_a_min_mps2 and other_a_min_mps2", "finite and < 0", (self.ego_a_min_mps2, self.other_a_min_mps2)
            )
        if not (self.camera_height_m > self.vehicle_height_m):
            raise bad(
                "camera_height_m", "above vehicle_height_m (the camera sees over the cars' roofs)", self.camera_height_m
            )

    @property
    def ego_y_m(self) -> float:
        """The ego's lateral position: the centre of its lane."""
        return EGO_LANE * LANE_WIDTH_M

    @property
    def cut_in_step(self) -> int:
        """The step at which the cut-in vehicle is told to change lanes: ``round(cut_in_time_s / dt_s)``."""
        return int(round(self.cut_in_time_s / self.dt_s))

    @property
    def cut_in_grace_steps(self) -> int:
        """R_G1's ``t_c`` in steps: ``round(cut_in_grace_s / dt_s)`` (30 at 0.1 s, as in ``once[0, 30]``)."""
        return int(round(self.cut_in_grace_s / self.dt_s))

    @property
    def vehicles(self) -> tuple[OtherVehicle, ...]:
        """The M objects at t = 0, in object order: the cut-in vehicle, then the traffic."""
        cut_in = OtherVehicle(self.cut_in_lane, self.cut_in_gap_m, self.cut_in_speed_mps)
        return (cut_in, *self.traffic[: self.n_objects - 1])


class RaritySetting(TypedDict):
    """The :class:`CutInParams` fields a rarity setting of :data:`RARITY_SETTINGS` sets."""

    cut_in_gap_m: float
    cut_in_speed_mps: float


RARITY_SETTINGS: dict[str, RaritySetting] = {
    "moderate": {"cut_in_gap_m": 20.0, "cut_in_speed_mps": 17.4},
    "rare": {"cut_in_gap_m": 22.5, "cut_in_speed_mps": 17.4},
}
"""The rarity knob's two settings (:class:`CutInParams` fields; ``moderate`` is the default): the cut-in vehicle's
gap to the ego at t = 0, its speed 7.6 m/s below the ego's. Under the shipped PEMs p is 7.95e-5 at ``moderate``
(:data:`MONTE_CARLO_REFERENCE`) and about 1e-7 at ``rare`` (docs/validation.md)."""


def moderate_params() -> CutInParams:
    """The ``cut-in`` scenario's defaults: the ``moderate`` rarity setting (about 9e-5)."""
    return CutInParams(**RARITY_SETTINGS["moderate"])


def rare_params() -> CutInParams:
    """The ``cut-in-rare`` scenario's defaults: the ``rare`` rarity setting (about 1e-7)."""
    return CutInParams(**RARITY_SETTINGS["rare"])


MONTE_CARLO_REFERENCE: dict[str, tuple[int, int]] = {"moderate": (1176, 14_800_000)}
"""The plain Monte Carlo reference of a rarity setting under the shipped PEMs: (failures, rollouts) of the engine's
own plain rollouts (``benchmarks/cut_in_mc.py`` and ten adaptive runs' plain Monte Carlo, every failure a collision;
docs/validation.md), 7.95e-5 [7.50e-5, 8.41e-5] at ``moderate``; ``rare`` has none (it would need some 10^9
rollouts)."""


def safe_distance(params: CutInParams, ego_speed_mps: np.ndarray, front_speed_mps: np.ndarray) -> np.ndarray:
    """The safe distance (metres) from the ego to the vehicle in front, elementwise over speeds ``[...]`` (m/s):

        d_safe = v_ego^2 / (2 |a_ego|) - v_front^2 / (2 |a_front|) + v_ego t_react.

    Keeping at least this gap lets the ego stop behind the vehicle in front if it brakes fully after its reaction
    time. Source: Maierhofer et al. 2020, "Formalization of Interstate Traffic Rules in Temporal Logic", IEEE IV,
    rule R_G1's ``keeps_safe_distance_prec``, with the parameters of the authors' CommonRoad monitor
    (commonroad-stl-monitor, ``crmonitor/config.yaml``)."""
    v, vf = ego_speed_mps, front_speed_mps
    ego_stop = v * v / (2.0 * -params.ego_a_min_mps2)
    return ego_stop - vf * vf / (2.0 * -params.other_a_min_mps2) + v * params.reaction_time_s


def idm_acceleration(
    idm: IDMParams,
    target_speed_mps: float,
    speed_mps: np.ndarray,
    distance_m: np.ndarray,
    closing_speed_mps: np.ndarray,
) -> np.ndarray:
    """The IDM acceleration of highway-env's ``IDMVehicle.acceleration``, elementwise, clipped to ``+-acc_max``:

        a = a_max (1 - (v / v0)^delta - (d* / d)^2),  d* = d0 + v T + v dv / (2 sqrt(a_max b)),

    ``d`` the centre-to-centre distance to the vehicle followed (``inf``: none), ``dv`` the closing speed. Source:
    Treiber, Hennecke & Helbing 2000, "Congested traffic states in empirical observations and microscopic
    simulations", Phys. Rev. E 62, eq. (1)-(2), as highway-env 1.12 writes it.

    Args:
        idm: the IDM's constants (:class:`IDMParams`).
        target_speed_mps: v0, the desired speed (m/s).
        speed_mps: float64 ``[N]``, v (m/s).
        distance_m: float64 ``[N]``, d (metres; ``inf``: no vehicle followed).
        closing_speed_mps: float64 ``[N]``, dv (m/s).
    Returns:
        float64 ``[N]``, m/s^2."""
    a_max = idm.comfort_acc_max_mps2
    acc = a_max * (1.0 - libm.power(np.maximum(speed_mps, 0.0) / target_speed_mps, idm.delta))
    ab = -a_max * idm.comfort_acc_min_mps2
    d_star = idm.distance_wanted_m + speed_mps * idm.time_wanted_s + speed_mps * closing_speed_mps / (2.0 * np.sqrt(ab))
    ratio = d_star / np.maximum(distance_m, 0.01)
    acc = acc - a_max * (ratio * ratio)
    return np.clip(acc, -idm.acc_max_mps2, idm.acc_max_mps2)


def acc_control(
    params: CutInParams,
    track_x: np.ndarray,
    track_y: np.ndarray,
    track_vx: np.ndarray,
    active: np.ndarray,
    ego_x_m: np.ndarray,
    ego_speed_mps: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The ego's ACC on the tracked objects: follow the nearest (confirmed) track whose estimated centre is ahead of the
    ego's centre and within its lane (``|y - y_ego| < lane width / 2``), with :func:`idm_acceleration` at the estimated
    centre distance and closing speed; the free-road IDM term when none.

    Args:
        params: the scenario's constants (lane, IDM, ego's set speed, dt).
        track_x: float64 ``[M, N]`` the tracks' estimated centres along the road (object-major; metres).
        track_y: float64 ``[M, N]`` across the road (metres).
        track_vx: float64 ``[M, N]`` their estimated speeds along the road (m/s).
        active: bool ``[M, N]``, the tracks the ACC may follow.
        ego_x_m: float64 ``[N]`` the ego's position along the road (metres).
        ego_speed_mps: float64 ``[N]`` its speed (m/s).
    Returns:
        (followed int64 ``[N]``: the object followed, -1 when none; acceleration float64 ``[N]``, m/s^2, never below
        ``-speed / dt`` so that the ego does not reverse)."""
    ahead = track_x - ego_x_m
    candidate = active & (np.abs(track_y - params.ego_y_m) < LANE_WIDTH_M / 2) & (ahead > 0.0)
    distance = np.where(candidate, ahead, np.inf)
    followed = np.argmin(distance, axis=0)
    rows = np.arange(distance.shape[1])
    d = distance[followed, rows]
    has = np.isfinite(d)
    closing = np.where(has, ego_speed_mps - track_vx[followed, rows], 0.0)
    accel = idm_acceleration(params.idm, params.ego_target_speed_mps, ego_speed_mps, d, closing)
    accel = np.maximum(accel, -ego_speed_mps / params.dt_s)
    return np.where(has, followed, -1), accel
