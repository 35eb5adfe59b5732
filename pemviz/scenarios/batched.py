"""The braking scenario's batched twin: N rollouts advance together in numpy float64.

:class:`BrakingScenario` steps two highway-env vehicles per rollout (~100 us a step); here the N rollouts
of one batch advance together, the detector is asked once per step for the whole batch, and 10^6
rollouts stream through in chunks of bounded memory.

Same scenario, same arithmetic. The ego's control step is :func:`pemviz.scenarios.braking.ego_acceleration`
itself (already vectorised over rollouts); the motion is highway-env's ``Vehicle.step`` on a straight
lane with zero steering and heading (explicit Euler: ``x += v dt`` and then ``v += a dt``, the slip angle
and the heading change being exactly 0), the ego's speed is clamped at 0 after each step, the gap is
``(x_lead - L_lead / 2) - (x_ego + camera_offset)`` as :attr:`BrakingScenario.gap_m` computes it, and the
lead follows :attr:`BrakingParams.lead_accel_mps2`. The lead does not react to anything, so its state is
one pair of scalars shared by all rollouts. Every operation is an IEEE-754 float64 operation in the same
order as the black-box path, so the two give bit-identical trajectories for the same detections
(``tests/scenarios/test_batched.py``). highway-env's speed clip at +-40 m/s never binds (speeds stay
below 9 m/s) and is not repeated here.

Random numbers (the only randomness is the detector's output): a detection happens iff
``log u <= log_expit(logit q)``, ``u ~ U(0, 1)``, as in :func:`pemviz.scenarios.simulate`, which draws
``rng.random(n)`` once per step, so rollout ``i`` at step ``t`` uses the ``(t * n + i)``-th uniform of
the stream. With ``chunk_size >= n`` the batched path draws exactly those arrays, so the same seed gives
the same :class:`RolloutBatch` on both back-ends. With ``chunk_size < n`` and a PCG64 / PCG64DXSM
generator (``np.random.default_rng`` gives PCG64) each chunk jumps to its rollouts' uniforms with
``bit_generator.advance``, so the rollouts do not depend on ``chunk_size`` and ``rng`` ends in the state
``simulate`` leaves it in. Other bit generators cannot jump by draws: their chunks then draw one after
the other (chunk 0's T arrays, then chunk 1's, ...), and the rollouts depend on ``chunk_size``.
Detectors evaluated in numpy (the PEM, constants, windows) give the same bits at any batch size; a torch
proposal may differ in the last bit between batch sizes. An Array-RQMC sampler couples the rollouts of each fixed
block of :data:`pemviz.rng.RQMC_BLOCK` (= :data:`DEFAULT_CHUNK_SIZE`) rollouts, so its rollouts are simulated block by
block whatever ``chunk_size`` (:func:`iter_batched` hands them out in chunks of ``chunk_size``): the same rollouts,
bit for bit, for any chunk size and on any executor.

Units: metres, seconds, m/s; log-probabilities in nats.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterator

import numpy as np
from scipy.special import log_expit

from pemviz.detectors import Detector, step_uniforms
from pemviz.rng import JUMPABLE, RQMC_BLOCK, advance, bit_generator_at
from pemviz.scenarios import RolloutBatch
from pemviz.scenarios.braking import OBSERVATION_NAMES, BrakingParams, ego_step, initial_controller_state, lead_speeds

DEFAULT_CHUNK_SIZE = 8192
"""Rollouts simulated together: one chunk's working set stays in cache-sized [8192] arrays (measured
fastest of 2048..65536 on the 2-core CI machine); its outputs are 34 MB at T = 100."""


class BatchedBraking:
    """N rollouts of the braking scenario stepped together; the vectorised :class:`BrakingScenario`.

    Usage: ``obs = sim.observation()`` (float64 [N, 4], :data:`OBSERVATION_NAMES`), ask a detector, then
    ``sim.step(detected)`` with bool [N]; after ``params.n_steps`` steps the rollouts are over.
    """

    observation_names = OBSERVATION_NAMES

    def __init__(self, params: BrakingParams | None = None, n: int = 1) -> None:
        if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
            raise ValueError(f"BatchedBraking: n (rollouts) must be an integer >= 1, got {n!r}")
        self.params = params or BrakingParams()
        self.n = int(n)
        self._lead_speeds = lead_speeds(self.params)
        self.reset()

    def reset(self) -> None:
        """Put both cars of every rollout at the logged CARLA start."""
        p = self.params
        self.ego_x_m = np.zeros(self.n)
        self.ego_speed_mps = np.full(self.n, float(p.ego_speed0_mps))
        self.lead_x_m = p.camera_offset_m + p.gap0_m + p.lead_length_m / 2  # as BrakingScenario.reset
        self.lead_speed_mps = float(p.lead_speed_profile_mps[0])
        self.t = 0
        self._ctrl = initial_controller_state(self.n)

    @property
    def gap_m(self) -> np.ndarray:
        """Distance from each ego's camera to the lead's rear, float64 [N] (metres)."""
        p = self.params
        return (self.lead_x_m - p.lead_length_m / 2) - (self.ego_x_m + p.camera_offset_m)

    def observation(self, out: np.ndarray | None = None) -> np.ndarray:
        """The states reported with each detector query: float64 [N, 4] (:data:`OBSERVATION_NAMES`): gap (m), ego and
        lead speeds (m/s), brake pending (1.0 or 0.0).

        Args:
            out: optional float64 [N, 4] array to write into (returned).
        """
        o = np.empty((self.n, len(OBSERVATION_NAMES))) if out is None else out
        o[:, 0] = self.gap_m
        o[:, 1] = self.ego_speed_mps
        o[:, 2] = self.lead_speed_mps
        o[:, 3] = self._ctrl.pending_brake
        return o

    @property
    def done(self) -> bool:
        return self.t >= self.params.n_steps

    def snapshot(self) -> dict:
        """Copies of every rollout's state at the current step (snapshot/restore capability of
        :class:`~pemviz.scenarios.Snapshotting`); ``restore`` takes it on a simulator of the same N."""
        c = self._ctrl
        return {"ego_x_m": self.ego_x_m.copy(), "ego_speed_mps": self.ego_speed_mps.copy(), "lead_x_m": self.lead_x_m,
                "lead_speed_mps": self.lead_speed_mps, "t": self.t,
                "ctrl": type(c)(c.integral_kmh_s.copy(), c.pending_brake.copy())}  # fmt: skip

    def restore(self, state: dict) -> None:
        """Put back a :meth:`snapshot` (copied, so the snapshot can be restored again).

        Raises:
            ValueError: a snapshot of another number of rollouts.
        """
        if state["ego_x_m"].shape != (self.n,):
            raise ValueError(f"BatchedBraking.restore: a snapshot of {state['ego_x_m'].size} rollouts, this has {self.n}")
        c = state["ctrl"]
        self.ego_x_m, self.ego_speed_mps = state["ego_x_m"].copy(), state["ego_speed_mps"].copy()
        self.lead_x_m, self.lead_speed_mps, self.t = state["lead_x_m"], state["lead_speed_mps"], state["t"]
        self._ctrl = type(c)(c.integral_kmh_s.copy(), c.pending_brake.copy())

    def step(self, detected: np.ndarray, gap_m: np.ndarray | None = None) -> None:
        """Advance every rollout one step of ``dt`` seconds given the detector outputs.

        Args:
            detected: bool [N], the detector's output at the current states.
            gap_m: the current :attr:`gap_m` [N] if already computed (saves one pass).
        Raises:
            RuntimeError: if the rollouts are over (``n_steps`` steps taken).
            ValueError: if ``detected`` is not of shape [N].
        """
        p = self.params
        if self.done:
            raise RuntimeError(f"BatchedBraking.step: rollouts over after {p.n_steps} steps; call reset()")
        detected = np.asarray(detected, dtype=bool)
        if detected.shape != (self.n,):
            raise ValueError(f"BatchedBraking.step: detected must have shape ({self.n},), got {detected.shape}")
        gap = self.gap_m if gap_m is None else gap_m
        speed, self._ctrl = ego_step(p, detected, gap, self.ego_speed_mps, self._ctrl)
        dt = p.dt_s
        # highway-env Vehicle.step: position += speed * dt, then speed += acceleration * dt.
        self.ego_x_m = self.ego_x_m + self.ego_speed_mps * dt
        self.ego_speed_mps = speed
        self.lead_x_m = self.lead_x_m + self.lead_speed_mps * dt
        self.lead_speed_mps = float(self._lead_speeds[self.t + 1])
        self.t += 1


def replay(params: BrakingParams | None, detected: np.ndarray) -> np.ndarray:
    """The observations of rollouts driven by fixed detection sequences (no detector, no randomness).

    Args:
        params: scenario constants (None: :class:`BrakingParams` defaults).
        detected: bool [N, T] detector outputs, T <= ``params.n_steps``.
    Returns:
        float64 [N, T, 3] observations (gap_m, ego speed, lead speed) before each step, as
        :class:`BrakingScenario` reports them.
    Raises:
        ValueError: if ``detected`` is not 2-D or has more steps than ``params.n_steps``.
    """
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
        sim.step(detected[:, t], o[:, 0])
    return obs


# -- sampled rollouts ------------------------------------------------------------------------------


def _coupled(sampler: Detector) -> bool:
    """Whether ``sampler`` draws by Array-RQMC: its rollouts are then simulated one fixed block of
    :data:`pemviz.rng.RQMC_BLOCK` at a time, whatever ``chunk_size`` (the block's rollouts are coupled)."""
    return bool(getattr(sampler, "array_rqmc", False))


def _check_args(who: str, n: object, chunk_size: object) -> None:
    for name, value in (("n", n), ("chunk_size", chunk_size)):
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{who}: {name} must be an integer >= 1, got {value!r}")


def _uniform_chunks(
    rng: np.random.Generator, n: int, n_steps: int, chunk_size: int
) -> Iterator[tuple[int, int, Iterator[np.ndarray]]]:
    """``(start, stop, per-step uniforms [stop - start])`` for each chunk; see the module docstring.

    With one chunk or a generator that cannot jump, the draws come from ``rng`` itself in order. With
    jumps, each chunk reads its slice ``[t * n + start, t * n + stop)`` of the stream ``simulate`` would
    draw, from a copy of ``rng``'s state, and ``rng`` is finally advanced past all ``n * n_steps`` draws.
    """
    bounds = [(s, min(s + chunk_size, n)) for s in range(0, n, chunk_size)]
    bit_gen = rng.bit_generator
    if len(bounds) == 1 or not isinstance(bit_gen, JUMPABLE):
        for start, stop in bounds:
            yield start, stop, (rng.random(stop - start) for _ in range(n_steps))
        return
    base = bit_gen.state

    def draws(start: int, stop: int) -> Iterator[np.ndarray]:
        bg = bit_generator_at(base, start)
        gen = np.random.Generator(bg)
        for t in range(n_steps):
            if t:
                bg.advance(n - (stop - start))
            yield gen.random(stop - start)

    for start, stop in bounds:
        yield start, stop, draws(start, stop)
    advance(rng, n * n_steps)


def _action_log_prob(logit: np.ndarray, detected: np.ndarray, log_p_detect: np.ndarray | None, out: np.ndarray):
    """:func:`pemviz.detectors.action_log_prob` into ``out``, bit for bit, reusing ``log_expit(logit)``.

    ``log_expit(+logit)`` where detected (given as ``log_p_detect`` when already computed), ``log_expit(-logit)
    = -logaddexp(0, logit)`` elsewhere, evaluated only where missed. A hot path, so written out: numpy's
    ``logaddexp(..., where=missed)`` simulated 20,000 braking rollouts in 0.66 s against 0.74 s for ``log_expit`` on
    every entry (one run each, loaded 2-core machine), and ``scipy.special.log_expit(..., where=...)`` corrupted the heap (scipy 1.17.1: a segfault a few
    calls later).
    """
    if log_p_detect is None:
        log_p_detect = log_expit(logit)
    missed = ~detected
    np.copyto(out, log_p_detect)
    np.logaddexp(0.0, logit, out=out, where=missed)
    np.negative(out, out=out, where=missed)
    return out


def _run_chunk(
    params: BrakingParams,
    sampler: Detector,
    target: Detector,
    uniforms: Iterator[np.ndarray],
    obs: np.ndarray,
    detected: np.ndarray,
    log_p: np.ndarray,
    log_q: np.ndarray,
    forced: tuple[np.ndarray, np.ndarray] | None = None,
) -> None:
    """Simulate ``m = len(obs)`` rollouts, writing into obs [m, T, 3], detected / log_p / log_q [m, T].

    Per step, the arithmetic of :func:`pemviz.scenarios.simulate`: one detector call per batch,
    detect iff ``log u <= log_expit(logit q)``, log-probabilities of the taken actions under q and p.
    ``forced``: optional (detected bool [m, T], until int [m]): rollout i takes the given actions at the steps
    before ``until[i]`` (a replayed prefix, :func:`branch_batched`).
    """
    m, n_steps = detected.shape
    sim = BatchedBraking(params, m)
    # Step-major buffers: each step writes contiguous rows; one transposing copy per chunk at the end.
    obs_t = np.empty((n_steps, m, len(OBSERVATION_NAMES)))
    detected_t = np.empty((n_steps, m), dtype=bool)
    log_p_t = np.empty((n_steps, m))
    log_q_t = np.empty((n_steps, m))
    for t, u in zip(range(n_steps), uniforms):
        o = sim.observation(out=obs_t[t])
        q_logit = sampler.detect_logit(o)
        p_logit = q_logit if target is sampler else target.detect_logit(o)
        u = step_uniforms(u, sampler, q_logit, o)
        # u <= sigmoid(logit)  <=>  log u <= log_expit(logit) (= action_log_prob(logit, True)).
        ls_q = log_expit(q_logit)
        a = np.less_equal(np.log(u, out=u), ls_q, out=detected_t[t])
        if forced is not None:
            np.copyto(a, forced[0][:, t], where=t < forced[1])
        _action_log_prob(q_logit, a, ls_q, out=log_q_t[t])
        if p_logit is q_logit:
            log_p_t[t] = log_q_t[t]
        else:
            _action_log_prob(p_logit, a, None, out=log_p_t[t])
        sim.step(a, o[:, 0])
    obs[...] = obs_t.transpose(1, 0, 2)
    detected[...] = detected_t.T
    log_p[...] = log_p_t.T
    log_q[...] = log_q_t.T


def iter_batched(
    params: BrakingParams | None,
    n: int,
    sampler: Detector,
    target: Detector,
    rng: np.random.Generator,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> Iterator[RolloutBatch]:
    """Stream ``n`` rollouts as :class:`RolloutBatch` chunks of at most ``chunk_size`` rollouts each.

    Memory: about twice one chunk's ``chunk_size * T * 41`` bytes (~70 MB at 8,192 x 100). The
    chunks together are the rollouts :func:`simulate_batched` returns (module docstring: random numbers);
    with a jumping generator ``rng`` is advanced past all ``n * T`` draws once the last chunk is out.
    Raises:
        ValueError: for ``n`` or ``chunk_size`` not an integer >= 1.
    """
    _check_args("iter_batched", n, chunk_size)
    p = params or BrakingParams()
    n_steps = p.n_steps
    if _coupled(sampler) and chunk_size != RQMC_BLOCK:  # simulated block by block, handed out chunk by chunk
        for batch in iter_batched(p, n, sampler, target, rng, chunk_size=RQMC_BLOCK):
            for a in range(0, batch.n, int(chunk_size)):
                yield batch if batch.n <= chunk_size else batch.select(slice(a, a + int(chunk_size)))
        return
    for start, stop, uniforms in _uniform_chunks(rng, int(n), n_steps, int(chunk_size)):
        m = stop - start
        batch = RolloutBatch(
            np.empty((m, n_steps, len(OBSERVATION_NAMES))),
            np.empty((m, n_steps), dtype=bool),
            np.empty((m, n_steps)),
            np.empty((m, n_steps)),
            OBSERVATION_NAMES,
        )
        _run_chunk(p, sampler, target, uniforms, batch.observations, batch.detected, batch.log_p, batch.log_q)
        yield batch


def simulate_batched(
    params: BrakingParams | None,
    n: int,
    sampler: Detector,
    target: Detector,
    rng: np.random.Generator,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> RolloutBatch:
    """Run ``n`` braking rollouts together, detections drawn from ``sampler``, scored under ``target``.

    The batched twin of ``simulate(lambda: BrakingScenario(params), n, sampler, target, rng, T)``: the
    same seed gives the same batch (module docstring). The result holds ``n * T * 41`` bytes (4.1 GB for
    10^6 x 100); use :func:`summarise_batched` or :func:`iter_batched` for very large ``n``.

    Args:
        params: scenario constants (None: :class:`BrakingParams` defaults); T = ``params.n_steps``.
        n: number of rollouts (>= 1).
        sampler: the detector that draws the actions (proposal q, the PEM, a constant ...).
        target: the PEM whose probabilities weight the rollouts (may be ``sampler`` itself).
        rng: numpy Generator, consumed as :func:`pemviz.scenarios.simulate` consumes it.
        chunk_size: rollouts simulated together (bounds the working memory; not the result's).
    Returns:
        :class:`RolloutBatch` with observations [n, T, 3] and detected / log_p / log_q [n, T].
    Raises:
        ValueError: for ``n`` or ``chunk_size`` not an integer >= 1.
    """
    _check_args("simulate_batched", n, chunk_size)
    p = params or BrakingParams()
    n, n_steps = int(n), p.n_steps
    obs = np.empty((n, n_steps, len(OBSERVATION_NAMES)))
    detected = np.empty((n, n_steps), dtype=bool)
    log_p = np.empty((n, n_steps))
    log_q = np.empty((n, n_steps))
    chunk_size = RQMC_BLOCK if _coupled(sampler) else int(chunk_size)
    for start, stop, uniforms in _uniform_chunks(rng, n, n_steps, chunk_size):
        s = slice(start, stop)
        _run_chunk(p, sampler, target, uniforms, obs[s], detected[s], log_p[s], log_q[s])
    return RolloutBatch(obs, detected, log_p, log_q, OBSERVATION_NAMES)


def branch_batched(
    params: BrakingParams | None,
    parents: RolloutBatch,
    parent: np.ndarray,
    at: np.ndarray,
    target: Detector,
    rng: np.random.Generator,
) -> RolloutBatch:
    """:func:`pemviz.scenarios.branch` on the batched twin, vectorised: new rollout i replays parent ``parent[i]``'s
    actions before step ``at[i]`` (the state at a step is a function of the actions before it: the same state,
    bit for bit, as :meth:`BatchedBraking.restore` of a snapshot there) and draws the rest from ``target``.

    Returns:
        :class:`RolloutBatch` [K, T]; ``rng`` gives one ``random(K)`` per step.
    Raises:
        ValueError: ``parent`` / ``at`` out of range (:func:`pemviz.scenarios.check_branch_args`).
    """
    from pemviz.scenarios import check_branch_args

    p = params or BrakingParams()
    parent, at = np.asarray(parent, dtype=np.int64), np.asarray(at, dtype=np.int64)
    check_branch_args(parents, parent, at)
    k, n_steps = parent.size, p.n_steps
    out = RolloutBatch(np.empty((k, n_steps, len(OBSERVATION_NAMES))), np.empty((k, n_steps), dtype=bool),
                       np.empty((k, n_steps)), np.empty((k, n_steps)), OBSERVATION_NAMES)  # fmt: skip
    uniforms = (rng.random(k) for _ in range(n_steps))
    _run_chunk(p, target, target, uniforms, out.observations, out.detected, out.log_p, out.log_q,
               forced=(parents.detected[parent], at))  # fmt: skip
    return out


@dataclass(frozen=True)
class RolloutSummary:
    """What an estimate needs of N rollouts, without their trajectories (16 + 8 + 1 + 8 bytes a rollout): give
    ``log_weight``, ``failed`` and ``log_p_total`` to :func:`pemviz.estimate.estimate`.

    Attributes:
        log_weight: float64 [N] importance log-weights ``sum_t log p - log q`` over T - 1 steps (nats).
        log_p_total: float64 [N] ``sum_t log p_target(a_t | s_t)`` over T - 1 steps (nats), for the NLL.
        failed: bool [N] failure indicator.
        min_gap_m: float64 [N] the smallest gap of each rollout (metres).
    """

    log_weight: np.ndarray
    log_p_total: np.ndarray
    failed: np.ndarray
    min_gap_m: np.ndarray

    @property
    def n(self) -> int:
        return int(self.failed.size)


def summarise_batched(
    params: BrakingParams | None,
    n: int,
    sampler: Detector,
    target: Detector,
    rng: np.random.Generator,
    *,
    failed: Callable[[RolloutBatch], np.ndarray],
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> RolloutSummary:
    """Simulate ``n`` rollouts in chunks and keep per rollout only what an estimate needs.

    Peak memory is one chunk (:func:`iter_batched`) plus 33 bytes a rollout: 10^6 rollouts x 100 steps
    stay far below 1 GB. The rollouts (and so the summary) are those of :func:`simulate_batched` with
    the same ``rng``.

    Args:
        failed: the problem's failure event on a chunk, bool [m]: :meth:`pemviz.problems.Problem.failed` (classic
            robustness of the safety formula < 0; for the braking problem the gap drops below the crash gap).
        other arguments: as :func:`simulate_batched`.
    Returns:
        :class:`RolloutSummary` of the n rollouts, in order.
    Raises:
        ValueError: for ``n`` or ``chunk_size`` not an integer >= 1, or a ``failed`` of the wrong shape.
    """
    _check_args("summarise_batched", n, chunk_size)
    p = params or BrakingParams()
    n = int(n)
    log_weight, log_p_total, fail, min_gap = np.empty(n), np.empty(n), np.empty(n, dtype=bool), np.empty(n)
    start = 0
    for batch in iter_batched(p, n, sampler, target, rng, chunk_size=chunk_size):
        s = slice(start, start + batch.n)
        start += batch.n
        k = batch.n_steps - 1
        log_weight[s] = batch.log_weight(k)
        log_p_total[s] = batch.log_p[:, :k].sum(axis=1)
        min_gap[s] = batch.gap_m.min(axis=1)
        f = np.asarray(failed(batch), dtype=bool)
        if f.shape != (batch.n,):
            raise ValueError(f"summarise_batched: failed(batch) must be bool [{batch.n}], got shape {f.shape}")
        fail[s] = f
    return RolloutSummary(log_weight, log_p_total, fail, min_gap)

