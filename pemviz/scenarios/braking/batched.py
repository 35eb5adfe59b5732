"""The braking scenario's batched twin: N rollouts advance together in numpy float64.

The N rollouts of a batch step together, the detector is asked once per step for the whole batch, and 10^6 rollouts
stream through in chunks of bounded memory. The arithmetic is :class:`BrakingScenario`'s, IEEE-754 operation for
operation (:func:`pemviz.scenarios.braking.simulator.ego_acceleration`, highway-env's explicit Euler on a straight
lane, the gap as :attr:`BrakingScenario.gap_m`), so both give bit-identical trajectories for the same detections
(``tests/scenarios/test_batched.py``).

A detection happens iff ``log u <= log_expit(logit q)``, ``u`` the ``(t * n + i)``-th uniform of ``rng`` for rollout
i at step t (one ``rng.random(n)`` per step, as :func:`pemviz.scenarios.simulate`). With a PCG64 / PCG64DXSM
generator each chunk jumps to its uniforms (``bit_generator.advance``), so the rollouts do not depend on
``chunk_size``; other generators draw chunk after chunk. An Array-RQMC sampler's rollouts are simulated block by
block of :data:`pemviz.core.rng.RQMC_BLOCK` whatever ``chunk_size``.

Units: metres, seconds, m/s; log-probabilities in nats."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from pemviz.core.detectors import Detector
from pemviz.core.lockstep import DEFAULT_CHUNK_SIZE, iter_rollouts, simulate_rollouts
from pemviz.core.rollouts import RolloutBatch
from pemviz.scenarios.braking.simulator import (
    OBSERVATION_NAMES,
    BrakingParams,
    ControllerState,
    ego_acceleration,
    ego_step,
    initial_controller_state,
    lead_speeds,
)


class BatchedBraking:
    """N rollouts of the braking scenario stepped together; the vectorised :class:`BrakingScenario`.

    Usage: ``obs = sim.observation()`` (float64 [N, 4], :data:`OBSERVATION_NAMES`), ask a detector, then
    ``sim.step(detected)`` with bool [N]; after ``params.n_steps`` steps the rollouts are over."""

    observation_names = OBSERVATION_NAMES

    def __init__(
        self, params: BrakingParams | None = None, n: int = 1, starts: dict[str, np.ndarray] | None = None
    ) -> None:
        if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
            raise ValueError(f"BatchedBraking: n (rollouts) must be an integer >= 1, got {n!r}")
        self.params = params or BrakingParams()
        self.n = int(n)
        self.starts = {k: np.asarray(v, dtype=np.float64).reshape(self.n) for k, v in (starts or {}).items()}
        """Per-rollout starts over an operating design domain: ``gap0_m`` and / or ``ego_speed0_mps``, float64 [N]
        each, in place of the params' one value (:mod:`pemviz.scenarios.braking.odd`); empty: the params'."""
        if set(self.starts) - {"gap0_m", "ego_speed0_mps"}:
            raise ValueError(f"BatchedBraking: starts may set gap0_m and ego_speed0_mps, got {sorted(self.starts)}")
        self._lead_speeds = lead_speeds(self.params)
        self.reset()

    def reset(self) -> None:
        """Put both cars of every rollout at the logged CARLA start."""
        p = self.params
        self.ego_x_m = np.zeros(self.n)
        self.ego_speed_mps = np.full(self.n, float(p.ego_speed0_mps))
        self.lead_x_m: float | np.ndarray = p.camera_offset_m + p.gap0_m + p.lead_length_m / 2  # as BrakingScenario's
        if "ego_speed0_mps" in self.starts:
            self.ego_speed_mps = self.starts["ego_speed0_mps"].copy()
        if "gap0_m" in self.starts:  # [N]: each rollout's lead at its own gap
            self.lead_x_m = p.camera_offset_m + self.starts["gap0_m"] + p.lead_length_m / 2
        self.lead_speed_mps = float(p.lead_speed_profile_mps[0])
        self.t = 0
        self._ctrl = initial_controller_state(self.n)
        self._gap: np.ndarray | None = None
        """The gap of the last :meth:`observation`, reused by the next :meth:`step` (None: not asked since)."""

    @property
    def gap_m(self) -> np.ndarray:
        """Distance from each ego's camera to the lead's rear, float64 [N] (metres)."""
        p = self.params
        return (self.lead_x_m - p.lead_length_m / 2) - (self.ego_x_m + p.camera_offset_m)

    def observation(self, out: np.ndarray | None = None) -> np.ndarray:
        """The states reported with each detector query: float64 [N, 4] (:data:`OBSERVATION_NAMES`): gap (m), ego and
        lead speeds (m/s), brake pending (1.0 or 0.0).

        Args:
            out: optional float64 [N, 4] array to write into (returned)."""
        o = np.empty((self.n, len(OBSERVATION_NAMES))) if out is None else out
        o[:, 0] = self._gap = self.gap_m
        o[:, 1] = self.ego_speed_mps
        o[:, 2] = self.lead_speed_mps
        o[:, 3] = self._ctrl.pending_brake
        return o

    @property
    def controller(self) -> ControllerState:
        """Every rollout's controller memory at the current step (PID integral, pending brake; [N] each), read-only."""
        return self._ctrl

    @property
    def done(self) -> bool:
        return self.t >= self.params.n_steps

    def snapshot(self) -> dict:
        """Copies of every rollout's state at the current step (snapshot/restore capability of
        :class:`~pemviz.core.rollouts.Snapshotting`); ``restore`` takes it on a simulator of the same N."""
        c = self._ctrl
        return {
            "ego_x_m": self.ego_x_m.copy(),
            "ego_speed_mps": self.ego_speed_mps.copy(),
            "lead_x_m": np.copy(self.lead_x_m) if np.ndim(self.lead_x_m) else self.lead_x_m,
            "lead_speed_mps": self.lead_speed_mps,
            "t": self.t,
            "ctrl": type(c)(c.integral_kmh_s.copy(), c.pending_brake.copy()),
        }

    def restore(self, state: dict) -> None:
        """Put back a :meth:`snapshot` (copied, so the snapshot can be restored again).

        Raises:
            ValueError: a snapshot of another number of rollouts."""
        if state["ego_x_m"].shape != (self.n,):
            raise ValueError(
                f"BatchedBraking.restore: a snapshot of {state['ego_x_m'].size} rollouts, " f"this has {self.n}"
            )
        c = state["ctrl"]
        self.ego_x_m, self.ego_speed_mps = state["ego_x_m"].copy(), state["ego_speed_mps"].copy()
        self.lead_x_m, self.lead_speed_mps, self.t = state["lead_x_m"], state["lead_speed_mps"], state["t"]
        self._ctrl = type(c)(c.integral_kmh_s.copy(), c.pending_brake.copy())
        self._gap = None

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None:
        """Advance every rollout one step of ``dt`` seconds given the detector outputs.

        Args:
            detected: bool [N] or [N, 1] (its one object, the lead), the detector's output at the current states.
            noise: unused (the detector only detects); must be None.
        Raises:
            RuntimeError: if the rollouts are over (``n_steps`` steps taken).
            ValueError: if ``detected`` is not of shape [N] or [N, 1], or a ``noise`` is given."""
        p = self.params
        if self.done:
            raise RuntimeError(f"BatchedBraking.step: rollouts over after {p.n_steps} steps; call reset()")
        detected = np.asarray(detected, dtype=bool)
        if detected.shape not in ((self.n,), (self.n, 1)) or noise is not None:
            raise ValueError(
                f"BatchedBraking.step: detected must have shape ({self.n},) or ({self.n}, 1) and noise "
                f"None, got {detected.shape}"
            )
        gap = self._gap if self._gap is not None else self.gap_m  # the observation's, when it was just asked
        accel, self._ctrl = ego_acceleration(p, detected.reshape(self.n), gap, self.ego_speed_mps, self._ctrl)
        speed = ego_step(p, self.ego_speed_mps, accel)
        dt = p.dt_s
        # highway-env Vehicle.step: position += speed * dt, then speed += acceleration * dt.
        self.ego_x_m = self.ego_x_m + self.ego_speed_mps * dt
        self.ego_speed_mps = speed
        self.lead_x_m = self.lead_x_m + self.lead_speed_mps * dt
        self.lead_speed_mps = float(self._lead_speeds[self.t + 1])
        self.t += 1
        self._gap = None


def replay(params: BrakingParams | None, detected: np.ndarray) -> np.ndarray:
    """The observations of rollouts driven by fixed detection sequences (no detector, no randomness).

    Args:
        params: scenario constants (None: :class:`BrakingParams` defaults).
        detected: bool [N, T] detector outputs, T <= ``params.n_steps``.
    Returns:
        float64 [N, T, 3] observations (gap_m, ego speed, lead speed) before each step, as
        :class:`BrakingScenario` reports them.
    Raises:
        ValueError: if ``detected`` is not 2-D or has more steps than ``params.n_steps``."""
    p = params or BrakingParams()
    detected = np.asarray(detected, dtype=bool)
    if detected.ndim != 2 or detected.shape[0] < 1 or detected.shape[1] > p.n_steps:
        raise ValueError(f"replay: detected must be bool [N >= 1, T <= {p.n_steps}], got shape {detected.shape}")
    n, n_steps = detected.shape
    sim = BatchedBraking(p, n)
    obs = np.empty((n, n_steps, len(OBSERVATION_NAMES)))
    for t in range(n_steps):
        o = sim.observation()
        obs[:, t] = o
        sim.step(detected[:, t])
    return obs


# -- sampled rollouts ------------------------------------------------------------------------------


def iter_batched(
    params: BrakingParams | None,
    n: int,
    sampler: Detector,
    target: Detector,
    rng: np.random.Generator,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> Iterator[RolloutBatch]:
    """Stream ``n`` braking rollouts (``params`` None: :class:`BrakingParams`' defaults) as :class:`RolloutBatch` chunks
    of at most ``chunk_size`` rollouts each, detections drawn from ``sampler`` and scored under ``target`` (may be
    ``sampler`` itself), ``rng`` consumed as :func:`pemviz.scenarios.simulate` consumes it.

    Memory: about twice one chunk's ``chunk_size * T * 41`` bytes (~70 MB at 8,192 x 100). The chunks together are the
    rollouts :func:`simulate_batched` returns (module docstring: random numbers); with a jumping generator ``rng`` is
    advanced past all ``n * T`` draws once the last chunk is out.

    Raises:
        ValueError: for ``n`` or ``chunk_size`` not an integer >= 1."""
    p = params or BrakingParams()
    return iter_rollouts(lambda m: BatchedBraking(p, m), n, p.n_steps, sampler, target, rng, chunk_size=chunk_size)


def simulate_batched(
    params: BrakingParams | None,
    n: int,
    sampler: Detector,
    target: Detector,
    rng: np.random.Generator,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> RolloutBatch:
    """The ``n`` rollouts of :func:`iter_batched` (same arguments; T = ``params.n_steps``) as one
    :class:`RolloutBatch`, observations [n, T, 3], detected / log_p / log_q [n, T] (``n * T * 41`` bytes): the batched
    twin of ``simulate(lambda: BrakingScenario(params), n, sampler, target, rng, T)``.

    Raises:
        ValueError: for ``n`` or ``chunk_size`` not an integer >= 1."""
    p = params or BrakingParams()
    return simulate_rollouts(lambda m: BatchedBraking(p, m), n, p.n_steps, sampler, target, rng, chunk_size=chunk_size)
