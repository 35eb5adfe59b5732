"""The automated-braking scenario of Innes & Ramamoorthy (2022) on highway-env vehicles.

A lead car drives at 8.04 m/s and stops for a red light; the ego follows with a stripped-down CARLA BasicAgent: it
brakes hard when the detector sees the lead within 10 m, else a PID drives it toward 27 km/h; the brake does not
latch. The only randomness is the detector's output, so a rollout is a deterministic function of the detection
sequence.

The ego's longitudinal response is fitted to the authors' CARLA logs (``scripts/calibrate_braking.py``): one step of
actuation lag on the emergency brake, brake deceleration as a function of speed (``brake_decel_mps2`` at
``brake_knots_mps``), throttle acceleration ``(a0 - a1 * v) * throttle / max_throttle``, and the PID's integral as
an exponentially-windowed sum of km/h errors (leak 0.9).

Units: metres, seconds, m/s."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LEAD_SPEED_PROFILE_MPS: tuple[float, ...] = (
    (8.038,) * 20 + (8.01, 7.89, 7.69, 7.44, 7.16, 6.87, 5.72, 4.40, 3.06, 1.74, 0.43, 0.006) + (0.0,) * 68
)
"""Lead speed at step t = 0..99 (the authors' CARLA logs; 8.038 m/s is the logged start speed)."""

OBSERVATION_NAMES: tuple[str, ...] = ("gap_m", "ego_speed_mps", "lead_speed_mps", "brake_pending")
"""Columns of :meth:`BrakingScenario.observation`: what the scenario reports with each detector query. The PEM reads
the gap; ``brake_pending`` (1.0 or 0.0: the emergency brake commanded at the last step, applied at this one after
the actuation lag) is the controller's memory that decides this step's deceleration, so that a proposal over
the observation sees the Markov state that matters (the PID integral moves slowly with the speed)."""

BRAKING_SIGNALS = {"d": "gap_m", "v": "ego_speed_mps", "vl": "lead_speed_mps"}
"""STL signal name -> braking rollout observation column (metres, m/s): the braking problem's ``signals``."""

BRAKING_SIGNAL_RANGES = {"d": (0.0, 15.0), "v": (0.0, 10.0), "vl": (0.0, 10.0)}
"""Signal ranges for AGM's normalisation of predicates into [-1, 1]: ``d >= 2`` becomes (d - 2) / 13 as
in the authors' code. Gaps above 15 m never occur in the scenario (it starts at 12.3 m)."""

BRAKING_UNITS = {"d": "m", "v": "m/s", "vl": "m/s"}
"""STL signal name -> unit of the braking rollouts' signals."""


@dataclass(frozen=True)
class BrakingParams:
    """Every constant of the braking scenario, fitted to the CARLA logs.

    Distances in metres, speeds in m/s, accelerations in m/s^2, time in seconds.

    A start inside the failure set (``gap0_m`` below ``crash_gap_m``) is a scene whose every rollout fails at step 0
    (p = 1); a start in contact (``gap0_m <= contact_gap_m``) is refused: its collision has no step into contact, so
    no impact speed (:func:`pemviz.core.severity.severity_of_signal`).

    Raises:
        ValueError: a value outside its range (the message names the field, what is allowed and what was given)."""

    dt_s: float = 0.05
    n_steps: int = 100
    gap0_m: float = 12.2932
    ego_speed0_mps: float = 7.7649
    lead_speed_profile_mps: tuple[float, ...] = LEAD_SPEED_PROFILE_MPS
    camera_offset_m: float = 2.0
    camera_height_m: float = 1.76
    lead_length_m: float = 4.96
    ego_length_m: float = 4.96
    vehicle_width_m: float = 2.0
    braking_distance_m: float = 10.0
    crash_gap_m: float = 2.0
    contact_gap_m: float = 0.7  # CARLA logs: after a collision the gap stays at 0.69-0.72 m
    # controller (CARLA BasicAgent, longitudinal PID on km/h error)
    target_speed_kmh: float = 27.0
    kp: float = 1.0
    ki: float = 0.05
    kd: float = 0.0
    max_throttle: float = 0.75
    max_pid_brake: float = 0.3
    emergency_brake: float = 0.5
    integral_leak: float = 0.9
    # fitted longitudinal response (scripts/calibrate_braking.py)
    actuation_lag_steps: int = 1
    brake_knots_mps: tuple[float, ...] = (0.0, 5.0, 5.5, 5.9, 6.4, 6.7, 9.0)
    brake_decel_mps2: tuple[float, ...] = (27.5, 27.5, 22.0, 9.2, 9.2, 3.7, 3.7)
    throttle_accel0_mps2: float = 4.0
    throttle_accel_slope_per_s: float = 0.36
    latched_brake: bool = False

    def __post_init__(self) -> None:
        def bad(what: str, allowed: str, value: object) -> ValueError:
            return ValueError(f"BrakingParams: {what} must be {allowed}, got {value!r}")

        if not (isinstance(self.n_steps, int) and 1 <= self.n_steps <= len(self.lead_speed_profile_mps)):
            raise bad(
                "n_steps",
                f"an integer in 1..{len(self.lead_speed_profile_mps)} (the values of " "lead_speed_profile_mps)",
                self.n_steps,
            )
        if self.actuation_lag_steps not in (0, 1):
            raise bad("actuation_lag_steps", "0 or 1", self.actuation_lag_steps)
        ranges = (
            (
                "dt_s gap0_m lead_length_m ego_length_m vehicle_width_m camera_height_m target_speed_kmh",
                "> 0",
                lambda x: x > 0,
            ),
            (
                "ego_speed0_mps braking_distance_m crash_gap_m contact_gap_m kp ki kd throttle_accel0_mps2 "
                "throttle_accel_slope_per_s",
                ">= 0",
                lambda x: x >= 0,
            ),
            ("max_throttle emergency_brake", "in (0, 1]", lambda x: 0 < x <= 1),
            ("max_pid_brake integral_leak", "in [0, 1]", lambda x: 0 <= x <= 1),
            ("camera_offset_m", "any number", lambda x: True),
        )
        for names, allowed, ok in ranges:
            for name in names.split():
                value = getattr(self, name)
                if not (isinstance(value, (int, float)) and math.isfinite(value) and ok(value)):
                    raise bad(name, f"finite and {allowed}" if allowed != "any number" else "finite", value)
        if self.gap0_m <= self.contact_gap_m:  # a start inside the failure set above contact is a failure (p = 1)
            raise bad(
                "gap0_m",
                f"above contact_gap_m = {self.contact_gap_m:g} m (at or below it the cars start in contact: a "
                "collision with no impact speed)",
                self.gap0_m,
            )

    @property
    def lead_accel_mps2(self) -> np.ndarray:
        """Lead acceleration per step [n_steps] so that its speed follows the profile exactly."""
        profile = self.lead_speed_profile_mps
        v = np.array(profile[: self.n_steps] + (profile[min(self.n_steps, len(profile) - 1)],), dtype=np.float64)
        return (v[1:] - v[:-1]) / self.dt_s


@dataclass
class ControllerState:
    """The ego controller's memory, [N] each: PID integral (km/h s) and last step's emergency-brake command."""

    integral_kmh_s: np.ndarray
    pending_brake: np.ndarray


def initial_controller_state(n: int) -> ControllerState:
    """Controller memory at the start of ``n`` rollouts: zero integral, no brake command."""
    return ControllerState(np.zeros(n), np.zeros(n, dtype=bool))


def ego_acceleration(
    params: BrakingParams,
    detected: np.ndarray,
    gap_m: np.ndarray,
    ego_speed_mps: np.ndarray,
    ctrl: ControllerState,
) -> tuple[np.ndarray, ControllerState]:
    """One control step of the ego, vectorised over rollouts.

    Args:
        params: the scenario's constants.
        detected: bool [N], the detector's output at this step.
        gap_m: [N] gap from the ego's camera to the lead's rear (metres).
        ego_speed_mps: [N] ego speed (m/s).
        ctrl: controller memory before this step.
    Returns:
        (acceleration [N] in m/s^2, never below -speed/dt so the ego never reverses; new memory).
        In contact with the lead (gap <= ``contact_gap_m``) the ego is stopped, as after a CARLA collision.

    Source: Innes & Ramamoorthy (2022), Sec. V (CARLA BasicAgent emergency stop + PIDLongitudinalController, K_P 1.0,
    K_I 0.05, K_D 0 on the km/h error, max throttle 0.75, PID brake at most 0.3)."""
    p = params
    integral, full_brake, accel_pid = ego_commands(p, ego_speed_mps, ctrl.integral_kmh_s)
    emergency = np.asarray(detected, dtype=bool) & (gap_m < p.braking_distance_m)
    if p.latched_brake:  # the latched variant: once started, braking never stops
        emergency = emergency | ctrl.pending_brake
    applied = ctrl.pending_brake if p.actuation_lag_steps == 1 else emergency
    accel = ego_limited(p, gap_m, ego_speed_mps, np.where(applied, -full_brake, accel_pid))
    return accel, ControllerState(integral, emergency)


def ego_commands(
    params: BrakingParams, ego_speed_mps: np.ndarray, integral_kmh_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The parts of :func:`ego_acceleration` that do not depend on the brake applied, vectorised over rollouts.

    Args:
        params: the scenario's constants.
        ego_speed_mps: [N] ego speed (m/s).
        integral_kmh_s: [N] the PID integral before this step (km/h s).
    Returns:
        (the PID integral after this step [N] (km/h s), the full brake's deceleration [N] (m/s^2, >= 0), the PID's
        acceleration [N] (m/s^2): throttle minus its brake)."""
    p = params
    v = ego_speed_mps
    error = p.target_speed_kmh - 3.6 * v
    integral = p.integral_leak * integral_kmh_s + error * p.dt_s
    command = p.kp * error + p.ki * integral
    throttle = np.clip(command, 0.0, p.max_throttle)
    pid_brake = np.clip(-command, 0.0, p.max_pid_brake)
    full_brake = np.interp(v, p.brake_knots_mps, p.brake_decel_mps2)
    accel_throttle = (p.throttle_accel0_mps2 - p.throttle_accel_slope_per_s * v) * throttle / p.max_throttle
    return integral, full_brake, accel_throttle - full_brake * pid_brake / p.emergency_brake


def ego_limited(params: BrakingParams, gap_m: np.ndarray, ego_speed_mps: np.ndarray, accel: np.ndarray) -> np.ndarray:
    """The commanded acceleration [N] (m/s^2) as the ego takes it: never below -speed/dt (it never reverses), and
    -speed/dt in contact with the lead (gap <= ``contact_gap_m``), as after a CARLA collision.

    Args:
        params: the scenario's constants.
        gap_m: [N] gap (metres).
        ego_speed_mps: [N] ego speed (m/s).
        accel: [N] the commanded acceleration (m/s^2): the full brake's or the PID's (:func:`ego_commands`)."""
    stop = -ego_speed_mps / params.dt_s
    accel = np.maximum(accel, stop)
    return np.where(gap_m <= params.contact_gap_m, stop, accel)


def lead_speeds(params: BrakingParams) -> np.ndarray:
    """Lead speed at steps 0..T (m/s), float64 [T + 1], accumulated exactly as highway-env does
    (``speed += acceleration * dt`` with :attr:`BrakingParams.lead_accel_mps2`)."""
    acc = params.lead_accel_mps2
    v = np.empty(params.n_steps + 1)
    v[0] = params.lead_speed_profile_mps[0]
    for t in range(params.n_steps):
        v[t + 1] = v[t] + acc[t] * params.dt_s
    return v


def ego_step(params: BrakingParams, ego_speed_mps: np.ndarray, accel_mps2: np.ndarray) -> np.ndarray:
    """The ego's speed one step later [N] (m/s), vectorised over rollouts: highway-env ``Vehicle.step``'s explicit
    Euler update ``v' = max(v + a dt, 0)`` with a [N] (m/s^2) from :func:`ego_acceleration`. The ego's position
    moves by ``v dt`` with the speed before the update (``Vehicle.step`` moves first), so the gap moves by
    ``(v_lead - v) dt``."""
    speed = ego_speed_mps + accel_mps2 * params.dt_s
    return np.maximum(speed, 0.0, out=speed)  # v + (-v/dt) dt can round to -1e-16


def braking_step(
    params: BrakingParams,
    lead_speed_mps: float,
    gap_m: np.ndarray,
    speed_mps: np.ndarray,
    integral: np.ndarray,
    pending: np.ndarray,
    detected: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One step of the braking scenario for many states at once.

    Args:
        params: the scenario's constants.
        lead_speed_mps: the lead's speed at this step (m/s).
        gap_m: float64 [...] the gap at this step (metres).
        speed_mps: float64 [...] the ego's speed (m/s).
        integral: float64 [...] the PID integral (km/h s).
        pending: bool [...] the emergency-brake command of the previous step.
        detected: bool [...], the detector's output at this step.
    Returns:
        the state at the next step (same shapes): gap' = gap + (v_lead - v) dt; v' = max(v + a dt, 0).
    Source: :func:`ego_step` (:func:`ego_acceleration` and highway-env ``Vehicle.step``), written on the gap
    instead of positions; it replays highway-env rollouts to ~1e-13 m (``tests/scenarios/test_truth.py``)."""
    shape = np.shape(gap_m)
    g = np.asarray(gap_m, dtype=np.float64).ravel()
    v = np.asarray(speed_mps, dtype=np.float64).ravel()
    ctrl = ControllerState(np.asarray(integral, dtype=np.float64).ravel(), np.asarray(pending, dtype=bool).ravel())
    a = np.broadcast_to(np.asarray(detected, dtype=bool), shape).ravel()
    accel, ctrl2 = ego_acceleration(params, a, g, v, ctrl)
    v2 = ego_step(params, v, accel)
    g2 = g + (lead_speed_mps - v) * params.dt_s
    return g2.reshape(shape), v2.reshape(shape), ctrl2.integral_kmh_s.reshape(shape), ctrl2.pending_brake.reshape(shape)


def braking_replay(params: BrakingParams, detected: np.ndarray) -> np.ndarray:
    """Gaps of rollouts with given detection sequences, float64 [N, T] (metres), deterministic.

    Args:
        params: the scenario's constants.
        detected: bool [N, T] (or [N, <T]: missing steps count as misses)."""
    detected = np.atleast_2d(np.asarray(detected, dtype=bool))
    n, T = detected.shape[0], params.n_steps
    vl = lead_speeds(params)
    g = np.full(n, params.gap0_m)
    v = np.full(n, params.ego_speed0_mps)
    i = np.zeros(n)
    b = np.zeros(n, dtype=bool)
    out = np.empty((n, T))
    for t in range(T):
        out[:, t] = g
        a = detected[:, t] if t < detected.shape[1] else np.zeros(n, dtype=bool)
        g, v, i, b = braking_step(params, vl[t], g, v, i, b, a)
    return out


class BrakingScenario:
    """One rollout of the braking scenario on highway-env vehicles, stepped as a black box: ``obs =
    sim.observation()`` (float64 [4], :data:`OBSERVATION_NAMES`), ask a detector, ``sim.step(detected)``, for
    ``params.n_steps`` steps."""

    observation_names = OBSERVATION_NAMES

    def __init__(self, params: BrakingParams | None = None) -> None:
        self.params = params or BrakingParams()
        self._lead_accel = self.params.lead_accel_mps2
        self.reset()

    def reset(self) -> None:
        """Put both cars at the logged CARLA start."""
        from highway_env.road.lane import StraightLane
        from highway_env.road.road import Road, RoadNetwork
        from highway_env.vehicle.kinematics import Vehicle

        p = self.params
        net = RoadNetwork()
        net.add_lane("a", "b", StraightLane([0.0, 0.0], [1000.0, 0.0], width=4.0))
        self.road = Road(network=net)
        self.ego = Vehicle(self.road, [0.0, 0.0], heading=0.0, speed=p.ego_speed0_mps)
        lead_x = p.camera_offset_m + p.gap0_m + p.lead_length_m / 2
        self.lead = Vehicle(self.road, [lead_x, 0.0], heading=0.0, speed=p.lead_speed_profile_mps[0])
        for vehicle, length in ((self.ego, p.ego_length_m), (self.lead, p.lead_length_m)):
            vehicle.LENGTH = length
            vehicle.WIDTH = p.vehicle_width_m
        self.road.vehicles.extend([self.ego, self.lead])
        self.t = 0
        self._ctrl = initial_controller_state(1)

    @property
    def gap_m(self) -> float:
        """Distance from the ego's camera to the lead's rear (metres)."""
        p = self.params
        return float(self.lead.position[0] - p.lead_length_m / 2 - (self.ego.position[0] + p.camera_offset_m))

    def observation(self) -> np.ndarray:
        """The state reported with each detector query: float64 [4] (:data:`OBSERVATION_NAMES`): gap (m), ego and
        lead speeds (m/s), brake pending (1.0 or 0.0)."""
        return np.array(
            [self.gap_m, self.ego.speed, self.lead.speed, float(self._ctrl.pending_brake[0])], dtype=np.float64
        )

    @property
    def done(self) -> bool:
        return self.t >= self.params.n_steps

    def snapshot(self) -> tuple:
        """A deep copy of the highway-env road and both vehicles, the step and the controller's memory
        (snapshot/restore capability of :class:`~pemviz.core.rollouts.Snapshotting`)."""
        import copy

        return copy.deepcopy((self.road, self.ego, self.lead, self.t, self._ctrl))

    def restore(self, state: tuple) -> None:
        """Put back a :meth:`snapshot` (copied again, so it can be restored more than once)."""
        import copy

        self.road, self.ego, self.lead, self.t, self._ctrl = copy.deepcopy(state)

    def step(self, detected: bool) -> None:
        """Advance one step of ``dt`` seconds given the detector's output at the current state.

        Raises:
            RuntimeError: if the rollout is already over (``n_steps`` steps taken)."""
        if self.done:
            raise RuntimeError(f"BrakingScenario.step: rollout over after {self.params.n_steps} steps; call reset()")
        accel, self._ctrl = ego_acceleration(
            self.params,
            np.array([bool(detected)]),
            np.array([self.gap_m]),
            np.array([self.ego.speed]),
            self._ctrl,
        )
        self.ego.act({"steering": 0.0, "acceleration": float(accel[0])})
        self.lead.act({"steering": 0.0, "acceleration": float(self._lead_accel[self.t])})
        dt = self.params.dt_s
        self.ego.step(dt)
        self.lead.step(dt)
        self.ego.speed = max(self.ego.speed, 0.0)  # v + (-v/dt) dt can round to -1e-16
        self.t += 1
