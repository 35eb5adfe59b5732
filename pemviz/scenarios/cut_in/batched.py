"""The cut-in scenario's batched twin: N rollouts advance together in numpy float64.

The traffic, which never reacts to the ego, is computed once with highway-env's vehicles (:func:`cached_trajectory`)
and shared by every rollout; the ego, its trackers and its ACC advance for all N rollouts with the array functions
of :mod:`pemviz.scenarios.cut_in.scene` that the single simulator calls with N = 1, and highway-env's explicit Euler
update, so both give the same observations and object rows bit for bit (``tests/scenarios/test_cut_in_batched.py``).

Units: metres, seconds, m/s."""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import numpy as np

from pemviz.scenarios.cut_in.highway import TrafficTrajectory, traffic_trajectory
from pemviz.scenarios.cut_in.scenario import NO_VEHICLE_M, OBJECT_NAMES, OBSERVATION_NAMES, CutInParams, acc_control
from pemviz.scenarios.cut_in.scene import CameraView, Traffic, camera_view, decide, object_rows, scene_signals
from pemviz.stack import tracker
from pemviz.stack.detector import NOISE_NAMES

MAX_SPEED_MPS = 40.0
"""highway-env's ``Vehicle.MAX_SPEED``: above it ``clip_actions`` caps the acceleration at ``MAX_SPEED - speed``."""


FEATURE_NAMES: tuple[str, ...] = (
    "ego_speed_mps",
    "ego_accel_mps2",
    "acc_has_lead",
    "acc_gap_m",
    "acc_closing_mps",
    "acc_accel_mps2",
    "time_s",
)
"""The ego's state features [F] (:meth:`BatchedCutIn.state_features`): its speed (m/s) and last acceleration
(m/s^2), then what the ACC reads on the tracks predicted for this step: whether it has a lead, the lead track's
centre distance (m, :data:`NO_VEHICLE_M` without) and closing speed (m/s), the acceleration it would command without
a measurement (m/s^2), and the time since the start (s). Each car's are the tracker's
(:data:`pemviz.stack.tracker.FEATURE_NAMES`), its range from the ego's front plus half a car's length."""


@functools.lru_cache(maxsize=8)
def cached_trajectory(params: CutInParams) -> TrafficTrajectory:
    """:func:`~pemviz.scenarios.cut_in.highway.traffic_trajectory`, computed once per parameter set."""
    return traffic_trajectory(params)


def translation_error(params: CutInParams, gap_m: float) -> float:
    """The largest difference, in metres, between the traffic trajectory started at the cut-in gap ``gap_m`` and
    that of ``params`` with its cut-in vehicle moved by ``gap_m - params.cut_in_gap_m`` (every vehicle, every step,
    position and extent), or ``inf`` where anything else differs (speeds, headings, lanes, who occludes whom): what
    ``gap_shift_m`` of :class:`BatchedCutIn` assumes is 0 (rounding)."""
    base = cached_trajectory(params)
    other = traffic_trajectory(dataclasses.replace(params, cut_in_gap_m=float(gap_m)))
    shift = float(gap_m) - params.cut_in_gap_m
    worst = 0.0
    for a, b in zip(base.traffic, other.traffic, strict=True):
        for field in dataclasses.fields(a):
            x, y = getattr(a, field.name), getattr(b, field.name)
            if field.name in ("x_m", "rear_m", "front_m"):
                moved = np.array(x, dtype=np.float64)
                moved[0] += shift
                worst = max(worst, float(np.max(np.abs(np.asarray(y, dtype=np.float64) - moved))))
            elif field.name == "occluder_pairs":
                if x != y:
                    return math.inf
            elif not np.allclose(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64), rtol=0, atol=1e-9):
                return math.inf
    return worst


@dataclass
class CutInBatchState:
    """The state of N rollouts at one step (what :meth:`BatchedCutIn.snapshot` keeps): the step, the ego's position,
    speed and last acceleration ``[N]``, the tracks ``[M, N]`` (object-major) and the object the ACC followed
    ``[N]``."""

    t: int
    ego_x_m: np.ndarray
    ego_speed_mps: np.ndarray
    ego_accel_mps2: np.ndarray
    tracks: tracker.Tracks
    followed: np.ndarray

    def copy(self) -> CutInBatchState:
        return CutInBatchState(
            self.t,
            self.ego_x_m.copy(),
            self.ego_speed_mps.copy(),
            self.ego_accel_mps2.copy(),
            self.tracks.copy(),
            self.followed.copy(),
        )

    def select(self, rows: np.ndarray) -> CutInBatchState:
        """The state of rollouts ``rows`` (int indices, repeats allowed, or a bool mask), copied: restore it on a batch
        of that many rollouts to continue them (branching, as adaptive multilevel splitting does)."""
        return CutInBatchState(
            self.t,
            self.ego_x_m[rows],
            self.ego_speed_mps[rows],
            self.ego_accel_mps2[rows],
            self.tracks.select(rows),
            self.followed[rows],
        )


class BatchedCutIn:
    """N cut-in rollouts in lockstep: ``objects()`` float64 ``[N, M, G]``, ``observation()`` float64 ``[N, F]``,
    ``step(detected bool [N, M], noise float64 [N, M, 2] | None)``.

    ``gap_shift_m`` float64 ``[N]`` (None: none) moves each rollout's cut-in vehicle that many metres along the road
    (start gap ``params.cut_in_gap_m + gap_shift_m``); its trajectory from another start gap is this one translated
    where :func:`translation_error` is small, so rollouts of an ODD over ``cut_in_gap_m``
    (:mod:`pemviz.scenarios.cut_in.odd`) share one traffic trajectory.

    Raises:
        ValueError: ``n`` not an integer >= 1; ``gap_shift_m`` not finite of shape ``[n]``."""

    observation_names = OBSERVATION_NAMES
    object_names = OBJECT_NAMES
    noise_names = NOISE_NAMES
    feature_names = FEATURE_NAMES
    object_feature_names = tracker.FEATURE_NAMES

    def __init__(self, params: CutInParams | None, n: int, gap_shift_m: np.ndarray | None = None) -> None:
        if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
            raise ValueError(f"BatchedCutIn: n must be an integer >= 1, got {n!r}")
        self.params = params or CutInParams()
        self.n = int(n)
        self.n_objects = self.params.n_objects
        self._trajectory = cached_trajectory(self.params)
        self._shift: np.ndarray | None = None
        if gap_shift_m is not None:
            shift = np.asarray(gap_shift_m, dtype=np.float64)
            if shift.shape != (self.n,) or not np.all(np.isfinite(shift)):
                raise ValueError(f"BatchedCutIn: gap_shift_m must be finite float64 [{self.n}], got {shift.shape}")
            self._shift = np.zeros((self.n_objects, self.n))
            self._shift[0] = shift  # the cut-in vehicle only
        self._traffic_at: tuple[int, Traffic] | None = None
        self.reset()

    def traffic(self) -> Traffic:
        """The traffic at this step: the shared trajectory's, with each rollout's cut-in vehicle moved by its
        ``gap_shift_m`` (then ``x_m``, ``rear_m`` and ``front_m`` are ``[M, N]``; computed once a step)."""
        shared = self._trajectory.traffic[self.state.t]
        if self._shift is None:
            return shared
        if self._traffic_at is None or self._traffic_at[0] != self.state.t:
            moved = dataclasses.replace(
                shared,
                x_m=shared.x_m[:, None] + self._shift,
                rear_m=shared.rear_m + self._shift,
                front_m=shared.front_m + self._shift,
            )
            self._traffic_at = (self.state.t, moved)
        return self._traffic_at[1]

    def reset(self) -> None:
        """Every rollout at the start: the ego at x = 0, no tracks."""
        p, n = self.params, self.n
        tracks = tracker.Tracks.empty((p.n_objects, n))
        self.state = CutInBatchState(
            0, np.zeros(n), np.full(n, p.ego_speed0_mps), np.zeros(n), tracks, np.full(n, -1, dtype=np.int64)
        )
        self._view: CameraView | None = None

    @property
    def t(self) -> int:
        return self.state.t

    @property
    def done(self) -> bool:
        return self.state.t >= self.params.n_steps

    def view(self) -> CameraView:
        """The camera's view at this step, ``[M, N]`` arrays (computed once per step)."""
        if self._view is None:
            self._view = camera_view(self.params, self.traffic(), self.state.ego_x_m)
        return self._view

    def objects(self, out: np.ndarray | None = None) -> np.ndarray:
        """The object rows at this step, float64 ``[N, M, G]``: a view of a column-major array, or ``out`` filled."""
        s = self.state
        rows = object_rows(
            self.params,
            self.traffic(),
            self.view(),
            s.ego_x_m,
            s.ego_speed_mps,
            s.ego_accel_mps2,
            s.tracks,
            s.followed,
        )
        if out is None:
            return rows
        out[...] = rows
        return out

    def observation(self, out: np.ndarray | None = None) -> np.ndarray:
        """The scene signals at this step, float64 ``[N, F]`` (into ``out`` when given)."""
        s = self.state
        return scene_signals(
            self.params,
            self.traffic(),
            s.ego_x_m,
            s.ego_speed_mps,
            s.ego_accel_mps2,
            s.tracks,
            s.followed,
            out=out,
        )

    def state_features(self) -> tuple[np.ndarray, np.ndarray]:
        """The state the ACC acts on at this step, before its measurements: float64 ``[N, F]`` (:data:`FEATURE_NAMES`)
        and ``[N, M, G]`` (the tracker's, :func:`pemviz.stack.tracker.features`). Read only: the rollouts are the
        same whether or not it is called."""
        p, s = self.params, self.state
        tracks = s.tracks
        lead, accel = acc_control(p, tracks.x, tracks.y, tracks.vx, tracks.confirmed, s.ego_x_m, s.ego_speed_mps)
        has = lead >= 0
        rows, at = np.arange(self.n), np.maximum(lead, 0)
        gap = np.where(has, tracks.x[at, rows] - s.ego_x_m, NO_VEHICLE_M)
        closing = np.where(has, s.ego_speed_mps - tracks.vx[at, rows], 0.0)
        ego = np.stack(
            [
                s.ego_speed_mps,
                s.ego_accel_mps2,
                has.astype(np.float64),
                gap,
                closing,
                accel,
                np.full(self.n, s.t * p.dt_s),
            ],
            axis=1,
        )
        return ego, tracker.features(tracks, s.ego_x_m + p.vehicle_length_m, s.ego_speed_mps)

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None:
        """Advance every rollout one step of ``dt`` seconds.

        Args:
            detected: bool ``[N, M]`` the cars detected.
            noise: float64 ``[N, M, 2]`` (range, lateral error; metres; read where detected) or None (no error).
        Raises:
            RuntimeError: the rollouts are over.
            ValueError: ``detected`` or ``noise`` of the wrong shape."""
        p, s = self.params, self.state
        if self.done:
            raise RuntimeError(f"BatchedCutIn.step: rollouts over after {p.n_steps} steps; call reset()")
        detected = np.asarray(detected, dtype=bool)
        shape = (self.n, p.n_objects)
        if detected.shape != shape:
            raise ValueError(f"BatchedCutIn.step: detected must be bool {list(shape)}, got shape {detected.shape}")
        if noise is not None:
            noise = np.asarray(noise, dtype=np.float64)
            if noise.shape != shape + (2,):
                raise ValueError(
                    f"BatchedCutIn.step: noise must be float64 {list(shape + (2,))} (range, lateral "
                    f"error; metres), got shape {noise.shape}"
                )
        tracks, followed, accel = decide(
            p,
            self.view(),
            s.ego_x_m,
            s.ego_speed_mps,
            s.tracks,
            detected.T,
            None if noise is None else noise.transpose(1, 0, 2),
        )
        v = s.ego_speed_mps
        accel = np.where(v > MAX_SPEED_MPS, np.minimum(accel, MAX_SPEED_MPS - v), accel)  # Vehicle.clip_actions
        # highway-env Vehicle.step: position += speed * dt, then speed += acceleration * dt.
        x = s.ego_x_m + v * p.dt_s
        speed = v + accel * p.dt_s
        self.state = CutInBatchState(
            s.t + 1, x, np.maximum(speed, 0.0, out=speed), accel, tracker.predict(tracks, p.dt_s, p.tracker), followed
        )
        self._view = None

    def snapshot(self) -> CutInBatchState:
        """A copy of the N rollouts' state (the traffic is a function of the step)."""
        return self.state.copy()

    def restore(self, state: CutInBatchState) -> None:
        """Put back a :meth:`snapshot` of a batch of the same N (copied again, so it can be restored more than once).

        Raises:
            ValueError: a snapshot of another batch size."""
        if state.ego_x_m.shape != (self.n,):
            raise ValueError(
                f"BatchedCutIn.restore: snapshot of {state.ego_x_m.shape[0]} rollouts, this batch has " f"{self.n}"
            )
        self.state = state.copy()
        self._view = None


def replay(
    params: CutInParams | None, detected: np.ndarray, noise: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The observations and object rows of rollouts driven by fixed detections and errors (no randomness).

    Args:
        params: scenario constants (None: :class:`CutInParams` defaults).
        detected: bool ``[N, T, M]`` with T <= ``params.n_steps``.
        noise: float64 ``[N, T, M, 2]`` (range, lateral error; metres) or None (no error).
    Returns:
        ``(observations float64 [N, T, F], objects float64 [N, T, M, G])``, before each step.
    Raises:
        ValueError: shapes other than these."""
    p = params or CutInParams()
    detected = np.asarray(detected, dtype=bool)
    if detected.ndim != 3 or detected.shape[0] < 1 or detected.shape[1] > p.n_steps or detected.shape[2] != p.n_objects:
        raise ValueError(
            f"replay: detected must be bool [N >= 1, T <= {p.n_steps}, {p.n_objects}], got shape " f"{detected.shape}"
        )
    if noise is not None and np.shape(noise) != detected.shape + (2,):
        raise ValueError(f"replay: noise must be float64 {list(detected.shape + (2,))}, got shape {np.shape(noise)}")
    n, n_steps, m = detected.shape
    sim = BatchedCutIn(p, n)
    obs = np.empty((n, n_steps, len(OBSERVATION_NAMES)))
    objs = np.empty((n, n_steps, m, len(OBJECT_NAMES)))
    for t in range(n_steps):
        obs[:, t] = sim.observation()
        objs[:, t] = sim.objects()
        sim.step(detected[:, t], None if noise is None else noise[:, t])
    return obs, objs
