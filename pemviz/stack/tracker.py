"""A constant-velocity Kalman tracker per object, for N rollouts x M objects at once, in numpy float64: the tracking
stage of a perception stack, for any scene (the Kalman filter: Kalman 1960, "A new approach to linear filtering and
prediction problems", Trans. ASME, Journal of Basic Engineering 82(1), 35-45).

Use: ``tracks = Tracks.empty((M, N))``, then each step :func:`update`, the controller reading the confirmed tracks,
and :func:`predict` (``docs/realistic-stack.md`` writes a scene on it).

Each track holds a constant-velocity state ``(position, velocity)`` per road axis with a 2 x 2 covariance; the axes
are filtered independently (no cross-axis motion term, diagonal measurement covariance), which is exactly the
4-state filter. Per step:

- **predict**: ``x' = F x``, ``P' = F P F^T + Q``, ``F = [[1, dt], [0, 1]]``, discrete white-noise acceleration ``Q
  = sigma_a^2 [[dt^4/4, dt^3/2], [dt^3/2, dt^2]]`` (Bar-Shalom, Li & Kirubarajan 2001, *Estimation with Applications
  to Tracking and Navigation*, eq. 6.3.3-4);
- **update**: ``S = P00 + r``, ``K = (P00, P01) / S``, ``x += K (z - position)``, ``P -= K (P00, P01)`` (ibid., Ch.
  5, ``H = [1, 0]``);
- **gate** along the road (Bar-Shalom, Daum & Huang 2009, "The probabilistic data association filter", IEEE Control
  Systems Magazine 29(6)): a measurement with ``y_x^2 / S_x > gate_chi2`` (default the 0.9999 chi-square(1)
  quantile, 15.14) is rejected and the track coasts; a track not updated for ``restart_after_steps`` restarts at a
  measurement outside its gate;
- **confirm**: a started track is tentative until a measurement inside its gate updates it; the controller acts on
  confirmed tracks only (Blackman & Popoli 1999, *Design and Analysis of Modern Tracking Systems*, Ch. 6);
- **start**: position = the measurement (variance ``r``), velocity = a prior (``prior_vx_mps`` along the road, 0
  across) with variance ``sigma_v0^2``; **drop** after ``max_coast_steps`` predictions without an update;
  **established** (:func:`start_confirmed`): a track confirmed from the scene's start.

Written here rather than taken from filterpy or simdkalman: the batched twin steps 10^4-10^5 filters per step as
elementwise arithmetic on ``[N, M]`` arrays, which those libraries do about 100 times slower (docs/validation.md);
``tests/stack/test_tracker.py`` checks it against filterpy's ``KalmanFilter``.

Units: metres, seconds, m/s; variances in m^2 and (m/s)^2."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


@dataclass(frozen=True)
class TrackerParams:
    """The tracker's noise model and track management (metres, seconds).

    Attributes:
        accel_std_x_mps2, accel_std_y_mps2: process-noise acceleration std along and across the road (m/s^2).
        meas_std_x0_m, meas_std_x_per_m2: the std of a position measurement along the road, ``meas_std_x0_m +
            meas_std_x_per_m2 * Z^2`` at measured range ``Z`` (m) (pinhole: ``dZ ~ Z^2 e_h / (f H)``).
        meas_std_y0_m, meas_std_y_per_m: the std across the road, ``meas_std_y0_m + meas_std_y_per_m * Z``.
        init_speed_std_x_mps, init_speed_std_y_mps: std of the velocity prior of a new track (m/s); 15 m/s along the
            road by default, wide enough that an object standing still is not taken for one moving with the ego
            (``benchmarks/track_prior.py``).
        max_coast_steps: a track not updated for more than this many predictions is dropped.
        gate_chi2: the validation gate on the normalised innovation squared along the road (1 degree of freedom; the
            lateral innovation is not gated); ``inf``: no gate.
        restart_after_steps: a track whose last update is this many steps old restarts at a measurement outside its
            gate.
    Raises:
        ValueError: a negative or non-finite value, or a measurement std of 0."""

    accel_std_x_mps2: float = 3.0
    accel_std_y_mps2: float = 1.5
    meas_std_x0_m: float = 0.3
    meas_std_x_per_m2: float = 0.0015
    meas_std_y0_m: float = 0.1
    meas_std_y_per_m: float = 0.003
    init_speed_std_x_mps: float = 15.0
    init_speed_std_y_mps: float = 1.0
    max_coast_steps: int = 10
    gate_chi2: float = 15.136705226623606  # scipy.stats.chi2(1).ppf(0.9999)
    restart_after_steps: int = 2

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (value >= 0 and (np.isfinite(value) or f.name == "gate_chi2")):
                raise ValueError(f"TrackerParams.{f.name} must be finite and >= 0, got {value!r}")
        if self.meas_std_x0_m <= 0 or self.meas_std_y0_m <= 0:
            raise ValueError(
                "TrackerParams: meas_std_x0_m and meas_std_y0_m must be > 0 " "(a measurement is never exact)"
            )

    def measurement_variances(self, range_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(r_x, r_y)``: the variances (m^2) of position measurements taken at range ``range_m`` (m), same shape."""
        sx = self.meas_std_x0_m + self.meas_std_x_per_m2 * (range_m * range_m)
        sy = self.meas_std_y0_m + self.meas_std_y_per_m * range_m
        return sx * sx, sy * sy


@dataclass
class Tracks:
    """The tracks of M objects in N rollouts: every array has one shape, ``[M, N]`` in the scenarios (object-major).

    Attributes:
        x, vx, pxx, pxv, pvvx: position (m) and velocity (m/s) along the road and their covariance
            (m^2, m^2/s, m^2/s^2).
        y, vy, pyy, pyv, pvvy: the same across the road.
        active: bool, whether the object has a track.
        confirmed: bool, whether that track has been updated since it started (the controller uses only these).
        coast: int64, predictions since the last update.
        age: int64, predictions since the track started (or restarted); 0 where no track."""

    x: np.ndarray
    vx: np.ndarray
    pxx: np.ndarray
    pxv: np.ndarray
    pvvx: np.ndarray
    y: np.ndarray
    vy: np.ndarray
    pyy: np.ndarray
    pyv: np.ndarray
    pvvy: np.ndarray
    active: np.ndarray
    confirmed: np.ndarray
    coast: np.ndarray
    age: np.ndarray

    @classmethod
    def empty(cls, shape: tuple[int, ...]) -> Tracks:
        """No track yet (the float fields are 0), arrays of ``shape``."""
        zeros = (np.zeros(shape) for _ in range(10))
        flags = (np.zeros(shape, dtype=bool) for _ in range(2))  # active, confirmed
        counts = (np.zeros(shape, dtype=np.int64) for _ in range(2))  # coast, age
        return cls(*zeros, *flags, *counts)

    def copy(self) -> Tracks:
        return Tracks(*(getattr(self, f.name).copy() for f in fields(self)))

    def select(self, rows: np.ndarray) -> Tracks:
        """The tracks of rollouts ``rows`` (int indices or a bool mask on the last axis), copied."""
        return Tracks(*(getattr(self, f.name)[..., rows] for f in fields(self)))


_Axis = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""One axis of a track: position, velocity, and the covariance's three entries (pp, pv, vv)."""


def _predict_axis(
    p: np.ndarray, v: np.ndarray, ppp: np.ndarray, ppv: np.ndarray, pvv: np.ndarray, dt: float, accel_std: float
) -> _Axis:
    """One CV prediction on one axis: ``F = [[1, dt], [0, 1]]``, DWNA ``Q`` (module docstring); arrays ``[...]``."""
    q = accel_std * accel_std
    q_pp, q_pv, q_vv = q * (dt**4 / 4.0), q * (dt**3 / 2.0), q * (dt * dt)
    p2 = p + v * dt
    # F P F^T: [[ppp + 2 dt ppv + dt^2 pvv, ppv + dt pvv], [ppv + dt pvv, pvv]]
    pv_dt = pvv * dt
    ppv2 = ppv + pv_dt
    ppp2 = ppp + dt * (ppv + ppv2) + q_pp
    return p2, v, ppp2, ppv2 + q_pv, pvv + q_vv


def _update_axis(
    p: np.ndarray,
    v: np.ndarray,
    ppp: np.ndarray,
    ppv: np.ndarray,
    pvv: np.ndarray,
    innovation: np.ndarray,
    s: np.ndarray,
    gate: np.ndarray,
) -> tuple[np.ndarray, ...]:
    """One position measurement on one axis, given its innovation ``z - p`` and variance ``s = ppp + r``, with the gain
    multiplied by ``gate`` (float64 1.0 where accepted, 0.0 elsewhere): where the gain is 0 the state and covariance
    keep their values (``p + 0 * y == p`` for finite ``y``)."""
    k0 = ppp / s * gate
    k1 = ppv / s * gate
    return (p + k0 * innovation, v + k1 * innovation, ppp - k0 * ppp, ppv - k0 * ppv, pvv - k1 * ppv)


def predict(tracks: Tracks, dt: float, params: TrackerParams) -> Tracks:
    """Every track one step of ``dt`` seconds ahead (inactive rows too: their values are unused); tracks that reach
    more than ``max_coast_steps`` predictions without an update are dropped.

    Returns:
        new :class:`Tracks` (the input is not modified)."""
    along = _predict_axis(tracks.x, tracks.vx, tracks.pxx, tracks.pxv, tracks.pvvx, dt, params.accel_std_x_mps2)
    across = _predict_axis(tracks.y, tracks.vy, tracks.pyy, tracks.pyv, tracks.pvvy, dt, params.accel_std_y_mps2)
    coast = tracks.coast + 1
    active = tracks.active & (coast <= params.max_coast_steps)
    return Tracks(
        *along,
        *across,
        active,
        tracks.confirmed & active,
        np.where(active, coast, 0),
        np.where(active, tracks.age + 1, 0),
    )


def update(
    tracks: Tracks,
    measured: np.ndarray,
    z_x: np.ndarray,
    z_y: np.ndarray,
    range_m: np.ndarray,
    prior_vx_mps: np.ndarray | float,
    params: TrackerParams,
) -> Tracks:
    """Fold in this step's position measurements: update the objects that have a track (measurements inside the gate),
    start one for the others.

    Args:
        tracks: the tracks' predictions for this step (arrays of one shape, e.g. ``[M, N]``).
        measured: bool, which objects were measured (detected and visible).
        z_x: float64, the measured positions along the road (m); finite everywhere (only the measured entries are
            read).
        z_y: float64, across the road (m), as ``z_x``.
        range_m: float64, the measured range along the camera axis (m), for the measurement variances
            (:meth:`TrackerParams.measurement_variances`).
        prior_vx_mps: float64, broadcastable to the tracks (``[N]``, or a number): the velocity along the road (m/s)
            a new track starts with: the ego's speed for traffic that moves with the ego (cars ahead), 0 for
            objects that stand or cross the road (pedestrians); its std is ``init_speed_std_x_mps`` (15 m/s by
            default: cars ahead that may also stand still, with the ego's speed as the prior).
        params: the noise model and track management (:class:`TrackerParams`).
    Returns:
        new :class:`Tracks`: objects whose measurement was accepted (now confirmed), or that start (or restart) a
        tentative track, have ``coast = 0``; a measurement outside the gate leaves its track as predicted."""
    r_x, r_y = params.measurement_variances(range_m)
    y_x, y_y = z_x - tracks.x, z_y - tracks.y
    s_x, s_y = tracks.pxx + r_x, tracks.pyy + r_y
    inside = y_x * y_x <= params.gate_chi2 * s_x
    upd = measured & tracks.active & inside
    new = measured & ~(tracks.active & (inside | (tracks.coast < params.restart_after_steps)))
    gate = upd.astype(np.float64)
    x, vx, pxx, pxv, pvvx = _update_axis(tracks.x, tracks.vx, tracks.pxx, tracks.pxv, tracks.pvvx, y_x, s_x, gate)
    y, vy, pyy, pyv, pvvy = _update_axis(tracks.y, tracks.vy, tracks.pyy, tracks.pyv, tracks.pvvy, y_y, s_y, gate)
    active = tracks.active | new
    confirmed = (tracks.confirmed | upd) & ~new
    coast = np.where(upd | new, 0, tracks.coast)
    age = np.where(new, 0, tracks.age)
    if not new.any():  # starting no track: copying the start values where new would change nothing
        return Tracks(x, vx, pxx, pxv, pvvx, y, vy, pyy, pyv, pvvy, active, confirmed, coast, age)
    start_vx = np.where(tracks.active, tracks.vx, prior_vx_mps)  # a restart keeps its velocity estimate
    start_vy = np.where(tracks.active, tracks.vy, 0.0)
    sx2, sy2 = params.init_speed_std_x_mps**2, params.init_speed_std_y_mps**2
    for field_value, start in (
        (x, z_x),
        (vx, start_vx),
        (pxx, r_x),
        (pxv, 0.0),
        (pvvx, sx2),
        (y, z_y),
        (vy, start_vy),
        (pyy, r_y),
        (pyv, 0.0),
        (pvvy, sy2),
    ):
        np.copyto(field_value, start, where=new)
    return Tracks(x, vx, pxx, pxv, pvvx, y, vy, pyy, pyv, pvvy, active, confirmed, coast, age)


def start_confirmed(
    tracks: Tracks,
    where: np.ndarray | bool,
    x_m: np.ndarray | float,
    vx_mps: np.ndarray | float,
    y_m: np.ndarray | float,
    vy_mps: np.ndarray | float = 0.0,
    var_x_m2: np.ndarray | float = 0.3,
    var_vx_m2ps2: np.ndarray | float = 0.8,
    var_y_m2: np.ndarray | float = 0.01,
    var_vy_m2ps2: np.ndarray | float = 0.1,
) -> Tracks:
    """Tracks started as established: active, confirmed and just updated where ``where``, at the given state with a
    diagonal covariance; the others as they were. Call it once before a scene's first step, then ``update`` and
    ``predict`` as usual.

    Args:
        tracks: the tracks (arrays of one shape, e.g. ``[M, N]``).
        where: bool, broadcastable to them: which objects start established.
        x_m: float64, broadcastable: the position along the road (m), in the road frame the scene passes to
            ``update``.
        vx_mps: the velocity along the road (m/s).
        y_m: the position across the road (m).
        vy_mps: the velocity across the road (m/s).
        var_x_m2: the variance of ``x_m`` (m^2). The variances' defaults are about the steady state of the default
            :class:`TrackerParams` on an object 25 m ahead measured every 0.1 s (stds 0.55 m and 0.88 m/s along the
            road, 0.10 m and 0.31 m/s across).
        var_vx_m2ps2: the variance of ``vx_mps`` ((m/s)^2).
        var_y_m2: the variance of ``y_m`` (m^2).
        var_vy_m2ps2: the variance of ``vy_mps`` ((m/s)^2).
    Returns:
        new :class:`Tracks` (the input is not modified).
    Raises:
        ValueError: a non-finite value, or a variance not > 0, where ``where``."""
    shape = tracks.x.shape
    mask = np.broadcast_to(np.asarray(where, dtype=bool), shape)
    values = {}
    for name, value in (
        ("x_m", x_m),
        ("vx_mps", vx_mps),
        ("y_m", y_m),
        ("vy_mps", vy_mps),
        ("var_x_m2", var_x_m2),
        ("var_vx_m2ps2", var_vx_m2ps2),
        ("var_y_m2", var_y_m2),
        ("var_vy_m2ps2", var_vy_m2ps2),
    ):
        array = np.broadcast_to(np.asarray(value, dtype=np.float64), shape)
        bad = mask & ~(np.isfinite(array) & ((array > 0.0) if name.startswith("var") else True))
        if bad.any():
            allowed = "finite and > 0" if name.startswith("var") else "finite"
            raise ValueError(f"start_confirmed: {name} must be {allowed} where tracks start, got {array[bad][0]!r}")
        values[name] = array
    out = tracks.copy()
    for field_value, start in (
        (out.x, values["x_m"]),
        (out.vx, values["vx_mps"]),
        (out.pxx, values["var_x_m2"]),
        (out.pxv, 0.0),
        (out.pvvx, values["var_vx_m2ps2"]),
        (out.y, values["y_m"]),
        (out.vy, values["vy_mps"]),
        (out.pyy, values["var_y_m2"]),
        (out.pyv, 0.0),
        (out.pvvy, values["var_vy_m2ps2"]),
        (out.active, True),
        (out.confirmed, True),
        (out.coast, 0),
        (out.age, 0),
    ):
        np.copyto(field_value, start, where=mask)
    return out


FEATURE_NAMES: tuple[str, ...] = (
    "track_active",
    "track_confirmed",
    "track_age_steps",
    "track_misses",
    "track_range_m",
    "track_y_m",
    "track_vx_mps",
    "track_vy_mps",
    "track_var_x_m2",
    "track_var_y_m2",
    "track_var_vx_m2ps2",
    "track_var_vy_m2ps2",
    "track_ttc_s",
)
"""The tracker's state of an object as named features [G] (:func:`features`): has a track, confirmed, age,
consecutive misses, estimated range ahead (m) and lateral position (m), velocities (m/s) and their variances, and
the predicted time to collision (s, capped); 0 without a track, except the time to collision (the cap)."""

TTC_CAP_S = 10.0
"""The predicted time to collision of :func:`features` is at most this (s): finite for a track that does not close."""


def features(
    tracks: Tracks, ego_x_m: np.ndarray | float, ego_speed_mps: np.ndarray | float, ttc_cap_s: float = TTC_CAP_S
) -> np.ndarray:
    """The tracks' state as float64 features ``[N, M, G]`` (rollout-major), named :data:`FEATURE_NAMES`, at a step's
    start (after :func:`predict`, before :func:`update`). The time to collision is ``range / (ego_speed - vx)`` (s),
    at most ``ttc_cap_s`` (the cap where not closing or no track; 0 at or behind ``ego_x_m``).

    Args:
        tracks: the tracks of M objects in N rollouts (arrays ``[M, N]``).
        ego_x_m: float64 ``[N]`` or a number: the road position (m, the tracker's frame along the road) the range is
            measured from, e.g. the ego's front plus half the object's length.
        ego_speed_mps: float64 ``[N]`` or a number: the ego's speed along the road (m/s).
        ttc_cap_s: the time to collision's cap (s), > 0.
    Returns:
        float64 ``[N, M, G]``, finite where the tracks are.
    Raises:
        ValueError: ``ttc_cap_s`` not finite and > 0."""
    if not (np.isfinite(ttc_cap_s) and ttc_cap_s > 0):
        raise ValueError(f"tracker.features: ttc_cap_s must be finite and > 0, got {ttc_cap_s!r}")
    on = tracks.active
    range_m = tracks.x - np.asarray(ego_x_m, dtype=np.float64)
    closing = np.asarray(ego_speed_mps, dtype=np.float64) - tracks.vx
    with np.errstate(divide="ignore", invalid="ignore"):
        ttc = np.where(closing > 0.0, np.minimum(range_m / closing, ttc_cap_s), ttc_cap_s)
    ttc = np.where(on, np.where(range_m > 0.0, ttc, 0.0), ttc_cap_s)
    columns = (
        on,
        tracks.confirmed,
        tracks.age,
        np.maximum(tracks.coast - 1, 0),
        range_m,
        tracks.y,
        tracks.vx,
        tracks.vy,
        tracks.pxx,
        tracks.pyy,
        tracks.pvvx,
        tracks.pvvy,
    )
    out = np.stack([np.where(on, c, 0).astype(np.float64) for c in columns] + [ttc], axis=-1)
    return out.transpose(1, 0, 2)
