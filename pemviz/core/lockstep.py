"""The one rollout runner: every simulator's rollouts drawn, scored and stepped through :func:`run_batched`, the same
bits for any chunk size (:func:`uniform_chunks`)."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import replace
from typing import cast

import numpy as np

from pemviz.core.detector_noise import noise_names_of
from pemviz.core.detectors import Detector, StepDraw, draw_step, reads_state
from pemviz.core.exact import row_sum
from pemviz.core.features import FeaturesFn, FeatureSimulator, feature_replay, reports_features
from pemviz.core.rng import JUMPABLE, RQMC_BLOCK, advance, bit_generator_at
from pemviz.core.rollouts import (
    BatchedObjectsSimulator,
    BatchedSimulator,
    ObjectsSimulator,
    RolloutBatch,
    Simulator,
    draws_per_rollout,
    n_objects_of,
    reports_objects,
)


class Lockstep:
    """N black-box :class:`Simulator` objects stepped together as one :class:`BatchedSimulator`."""

    def __init__(self, sims: Sequence[Simulator]) -> None:
        self.sims = list(sims)
        first = self.sims[0]
        self.observation_names = tuple(first.observation_names)
        self.multi = hasattr(first, "objects")
        self.n_objects = n_objects_of(first)
        self.object_names = tuple(self._scenes[0].object_names) if self.multi else None

    @property
    def _scenes(self) -> list[ObjectsSimulator]:
        """:attr:`sims` as scenes of several objects (read only when ``multi``)."""
        return cast("list[ObjectsSimulator]", self.sims)

    def observation(self) -> np.ndarray:
        return np.stack([s.observation() for s in self.sims])

    def objects(self) -> np.ndarray:
        return np.stack([s.objects() for s in self._scenes])

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None:
        if not self.multi:
            for s, a in zip(self.sims, detected[:, 0], strict=False):
                s.step(bool(a))
            return
        for i, scene in enumerate(self._scenes):
            scene.step(detected[i], None if noise is None else noise[i])


class FeaturedLockstep(Lockstep):
    """A :class:`Lockstep` of simulators that report the state their controller acts on: each one's
    ``state_features() -> (ego float64 [F], objects float64 [M, G])``, named ``feature_names`` and
    ``object_feature_names`` (default none), stacked as a :class:`pemviz.core.features.FeatureSimulator`'s."""

    def __init__(self, sims: Sequence[Simulator]) -> None:
        super().__init__(sims)
        self.feature_names = tuple(getattr(self.sims[0], "feature_names", ()))
        self.object_feature_names = tuple(getattr(self.sims[0], "object_feature_names", ()))

    def state_features(self) -> tuple[np.ndarray, np.ndarray]:
        n, m, f, g = len(self.sims), self.n_objects, len(self.feature_names), len(self.object_feature_names)
        ego, objects = np.empty((n, f)), np.empty((n, m, g))
        for i, s in enumerate(self.sims):
            ego[i], objects[i] = cast(FeatureSimulator, s).state_features()  # one rollout's [F], [M, G]
        return ego, objects


def lockstep(make_simulator: Callable[[], Simulator], n: int) -> Lockstep:
    """``n`` fresh simulators of ``make_simulator`` stepped together: a :class:`FeaturedLockstep` where they report
    state features (:func:`pemviz.core.features.reports_features`), else a :class:`Lockstep`."""
    sims = [make_simulator() for _ in range(n)]
    return FeaturedLockstep(sims) if reports_features(sims[0]) else Lockstep(sims)


def run_batched(
    sim: BatchedSimulator,
    n: int,
    n_steps: int,
    sampler: Detector,
    target: Detector,
    uniforms: Iterable[np.ndarray],
    forced: tuple[np.ndarray, np.ndarray | None, np.ndarray] | None = None,
    keep_rows: bool = True,
    replayed_densities: bool = True,
) -> RolloutBatch:
    """Simulate the ``n`` rollouts of ``sim`` for ``n_steps`` steps, each object's events drawn from ``sampler`` and
    scored under ``target`` (:func:`pemviz.core.detectors.draw_step`): the rollout runner of every simulator. A
    detector that reads state features (:func:`pemviz.core.detectors.reads_state`) is asked about each row with the
    step's features appended.

    Args:
        sim: n rollouts at their start, a :class:`BatchedSimulator`.
        n: the rollouts.
        n_steps: T, the steps simulated.
        sampler: the detector the events are drawn from (q).
        target: the detector they are scored under (p, the PEM).
        uniforms: per step, float64 [n K] in [0, 1), rollout by rollout, K = :func:`draws_per_rollout`.
        forced: optional (detected bool [n, T, M], noise [n, T, M, D] or None, until int [n]): rollout i takes these
            events before ``until[i]`` (a replayed prefix).
        keep_rows: False: the object rows are not kept (``objects`` None; the caller attaches a
            :attr:`RolloutBatch.replay`).
        replayed_densities: False: the detectors are not asked about the replayed rows (their events are
            ``forced``'s), whose ``log_p`` and ``log_q`` are nan: the states and the drawn events are the same bits.
    Returns:
        :class:`RolloutBatch` [n, T]."""
    names = tuple(sim.observation_names)
    scene = sim if reports_objects(sim) else None  # None: one object per rollout, its observation
    m = n_objects_of(sim)
    noise_names = noise_names_of(target)
    d = len(noise_names)
    # Rollout-major arrays written a step (a column) at a time: ~2x as fast as step-major buffers transposed at the end
    obs = np.empty((n, n_steps, len(names)))
    det = np.empty((n, n_steps, m), dtype=bool)
    log_p, log_q = np.empty((n, n_steps)), np.empty((n, n_steps))
    objects = np.empty((n, n_steps, m, len(scene.object_names))) if scene is not None and keep_rows else None
    noise = np.empty((n, n_steps, m, d)) if d else None
    featured = sim if (reads_state(sampler) or reads_state(target)) and reports_features(sim) else None
    for t, u in zip(range(n_steps), uniforms, strict=False):
        o = np.asarray(sim.observation(), dtype=np.float64)
        obs[:, t] = o
        if scene is not None:
            rows = np.asarray(scene.objects(), dtype=np.float64)
            if objects is not None:
                objects[:, t] = rows
            rows = rows.reshape(n * m, -1)  # a view where the simulator's layout allows (e.g. cut-in: column-major)
        else:
            rows = o
        f = None
        if forced is not None:
            given = np.repeat(t < forced[2], m)
            f = (forced[0][:, t].reshape(-1), None if forced[1] is None else forced[1][:, t].reshape(-1, d), given)
        state = None
        if featured is not None:  # the step's state features, each object's then its rollout's ego's
            ego, per_object = (np.asarray(a, dtype=np.float64) for a in featured.state_features())
            state = np.concatenate([per_object.reshape(n * m, -1), np.repeat(ego, m, axis=0)], axis=1)
        u = np.asarray(u, dtype=np.float64).reshape(n * m, 1 + d)
        if f is None or replayed_densities:
            step = draw_step(sampler, target, rows, u, RQMC_BLOCK * m, f, m, state)
        else:
            step = _draw_unreplayed(sampler, target, rows, u, m, f, state)
        detected = step.detected.reshape(n, m)
        det[:, t] = detected
        if m == 1:
            log_q[:, t], log_p[:, t] = step.log_q, step.log_p
        else:  # the step's objects together
            log_q[:, t], log_p[:, t] = row_sum(step.log_q.reshape(n, m)), row_sum(step.log_p.reshape(n, m))
        errors = None
        if noise is not None and step.noise is not None:  # d > 0: the target's errors, drawn
            errors = step.noise.reshape(n, m, d)
            noise[:, t] = errors
        sim.step(detected, errors)
    return RolloutBatch(
        obs,
        det,
        log_p,
        log_q,
        names,
        objects=objects,
        object_names=tuple(scene.object_names) if scene is not None else None,
        noise=noise,
        noise_names=noise_names,
    )


def _draw_unreplayed(
    sampler: Detector,
    target: Detector,
    rows: np.ndarray,
    u: np.ndarray,
    m: int,
    forced: tuple[np.ndarray, np.ndarray | None, np.ndarray],
    state: np.ndarray | None,
) -> StepDraw:
    """:func:`draw_step` of the rows [R, G] that ``forced`` does not give (row by row, the same bits as among all
    rows); the given rows take ``forced``'s events and nan log-probabilities, no detector asked."""
    given = forced[2]
    detected = forced[0].copy()
    d = u.shape[1] - 1
    noise = None if not d else np.zeros((rows.shape[0], d)) if forced[1] is None else forced[1].copy()
    log_q, log_p = np.full(rows.shape[0], np.nan), np.full(rows.shape[0], np.nan)
    free = np.flatnonzero(~given)
    if free.size:
        own = None if state is None else state[free]
        step = draw_step(sampler, target, rows[free], u[free], RQMC_BLOCK * m, None, m, own)
        detected[free] = step.detected
        if noise is not None and step.noise is not None:
            noise[free] = step.noise
        log_q[free], log_p[free] = step.log_q, step.log_p
    return StepDraw(detected, noise, log_q, log_p)


def replay_rows(make: Callable[[int], BatchedSimulator], detected: np.ndarray, noise: np.ndarray | None) -> np.ndarray:
    """The object rows float64 [K, T, M, G] of K rollouts of the batched simulator ``make(K)`` that took the events
    ``detected`` bool [K, T, M] and ``noise`` float64 [K, T, M, D] (or None): the simulator stepped with those events,
    no detector asked. Bit for bit the rows :func:`run_batched` saw (a state is a function of the events before it,
    and a batched simulator's arithmetic is row by row)."""
    k, n_steps = detected.shape[:2]
    # no rollout: the rows' shape only; a simulator of object rows (rows are replayed only for batches that have them)
    sim = cast(BatchedObjectsSimulator, make(max(k, 1)))
    out = np.empty((k, n_steps, n_objects_of(sim), len(sim.object_names)))
    for t in range(n_steps if k else 0):
        out[:, t] = sim.objects()
        sim.step(detected[:, t], None if noise is None else noise[:, t])
    return out


DEFAULT_CHUNK_SIZE = RQMC_BLOCK
"""Rollouts a batched simulator steps together, one Array-RQMC block: one chunk's working set stays in cache."""


def check_counts(who: str, **counts: object) -> None:
    """Raise ValueError unless every ``name=value`` is an integer >= 1 (a rollout count, a chunk size)."""
    for name, value in counts.items():
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{who}: {name} must be an integer >= 1, got {value!r}")


def uniform_chunks(
    rng: np.random.Generator, n: int, n_steps: int, chunk_size: int, per_rollout: int = 1
) -> Iterator[tuple[int, int, Iterator[np.ndarray]]]:
    """``(start, stop, per-step uniforms [(stop - start) K])`` for each chunk of rollouts, K = ``per_rollout``: the
    numbers one ``rng.random(n K)`` per step gives rollouts ``start .. stop - 1``, whatever the chunks (a PCG64 /
    PCG64DXSM generator jumps to each chunk's slice with ``bit_generator.advance`` and ends where the serial run
    leaves it; another draws chunk after chunk)."""
    bounds = [(a, min(a + chunk_size, n)) for a in range(0, n, chunk_size)]
    k = int(per_rollout)
    bit_gen = rng.bit_generator
    if len(bounds) == 1 or not isinstance(bit_gen, JUMPABLE):
        for start, stop in bounds:
            yield start, stop, (rng.random((stop - start) * k) for _ in range(n_steps))
        return
    base = bit_gen.state

    def draws(start: int, stop: int) -> Iterator[np.ndarray]:
        bg = bit_generator_at(base, start * k)
        gen = np.random.Generator(bg)
        for t in range(n_steps):
            if t:
                bg.advance((n - (stop - start)) * k)
            yield gen.random((stop - start) * k)

    for start, stop in bounds:
        yield start, stop, draws(start, stop)
    advance(rng, n * k * n_steps)


def _coupled(sampler: Detector) -> bool:
    """Whether ``sampler`` draws by Array-RQMC: its rollouts are then simulated one fixed block of
    :data:`pemviz.core.rng.RQMC_BLOCK` at a time, whatever the chunk size (the block's rollouts are coupled)."""
    return bool(getattr(sampler, "array_rqmc", False))


def iter_rollouts(
    make: Callable[[int], BatchedSimulator],
    n: int,
    n_steps: int,
    sampler: Detector,
    target: Detector,
    rng: np.random.Generator,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    keep_rows: bool = True,
) -> Iterator[RolloutBatch]:
    """Stream ``n`` rollouts of a batched simulator as :class:`RolloutBatch` chunks of at most ``chunk_size``
    rollouts (:func:`run_batched` on ``make(m)``), the same rollouts bit for bit for any chunk size
    (:func:`uniform_chunks`); an Array-RQMC sampler's are simulated one block of :data:`pemviz.core.rng.RQMC_BLOCK`
    at a time. With ``keep_rows=False`` object rows are rebuilt by replay when asked for
    (:attr:`RolloutBatch.replay`, :func:`replay_rows`).

    Raises:
        ValueError: ``n`` or ``chunk_size`` not an integer >= 1."""
    check_counts("iter_rollouts", n=n, chunk_size=chunk_size)
    n, chunk_size = int(n), int(chunk_size)
    if _coupled(sampler) and chunk_size != RQMC_BLOCK:  # simulated block by block, handed out chunk by chunk
        for batch in iter_rollouts(make, n, n_steps, sampler, target, rng, chunk_size=RQMC_BLOCK, keep_rows=keep_rows):
            for a in range(0, batch.n, chunk_size):
                yield batch if batch.n <= chunk_size else batch.select(slice(a, a + chunk_size))
        return
    k = draws_per_rollout(make(1), target)
    replay = None if keep_rows else functools.partial(replay_rows, make)
    for start, stop, uniforms in uniform_chunks(rng, n, n_steps, chunk_size, k):
        batch = run_batched(make(stop - start), stop - start, n_steps, sampler, target, uniforms, keep_rows=keep_rows)
        elided = replay is not None and batch.object_names is not None  # a multi-object batch without its rows
        yield replace(batch, replay=replay) if elided else batch


def simulate_rollouts(
    make: Callable[[int], BatchedSimulator],
    n: int,
    n_steps: int,
    sampler: Detector,
    target: Detector,
    rng: np.random.Generator,
    *,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> RolloutBatch:
    """The ``n`` rollouts of :func:`iter_rollouts` as one :class:`RolloutBatch` [n, T] (it holds them all: stream them
    for very large ``n``).

    Raises:
        ValueError: ``n`` or ``chunk_size`` not an integer >= 1."""
    check_counts("simulate_rollouts", n=n, chunk_size=chunk_size)
    size = RQMC_BLOCK if _coupled(sampler) else int(chunk_size)
    chunks = list(iter_rollouts(make, n, n_steps, sampler, target, rng, chunk_size=size))
    return chunks[0] if len(chunks) == 1 else RolloutBatch.concatenate(chunks)


def branch_rollouts(
    make: Callable[[int], BatchedSimulator],
    parents: RolloutBatch,
    parent: np.ndarray,
    at: np.ndarray,
    target: Detector,
    rng: np.random.Generator,
    events_only: bool = False,
) -> RolloutBatch:
    """:func:`branch` on a batched simulator (``make(K)``): new rollout i replays parent ``parent[i]``'s events
    before step ``at[i]`` (the state at a step is a function of the events before it) and draws the rest from
    ``target``; one ``rng.random(K k)`` per step. With ``events_only`` the observations and events only, the same
    bits for less: no object rows kept, the detectors not asked about the replayed steps (their ``log_p`` and
    ``log_q`` nan).

    Returns:
        :class:`RolloutBatch` [K, T].
    Raises:
        ValueError: ``parent`` / ``at`` out of range (:func:`check_branch_args`)."""
    parent, at = np.asarray(parent, dtype=np.int64), np.asarray(at, dtype=np.int64)
    check_branch_args(parents, parent, at)
    sim = make(parent.size)
    k = draws_per_rollout(sim, target) * parent.size
    noise = None if parents.noise is None else parents.noise[parent]
    return run_batched(
        sim,
        parent.size,
        parents.n_steps,
        target,
        target,
        (rng.random(k) for _ in range(parents.n_steps)),
        forced=(parents.detected[parent], noise, at),
        keep_rows=not events_only,
        replayed_densities=not events_only,
    )


def simulate(
    make_simulator: Callable[[], Simulator],
    n: int,
    sampler: Detector,
    target: Detector,
    rng: np.random.Generator | None,
    n_steps: int,
    uniforms: np.ndarray | None = None,
) -> RolloutBatch:
    """Run ``n`` rollouts in lockstep (:class:`Lockstep`, :func:`run_batched`), each object's events drawn from
    ``sampler``, scored under ``target``: a detection iff ``u <= q(detect | s)``, ``u`` from one ``rng.random(n K)``
    per step (K = :func:`draws_per_rollout`), as in the authors' code. Detectors are asked one block of
    :data:`pemviz.core.rng.RQMC_BLOCK` rollouts at a time, so chunks of whole blocks simulated elsewhere give the
    same bits.

    Args:
        make_simulator: builds a fresh simulator at its start state.
        n: number of rollouts (>= 1).
        sampler: the detector that draws the events.
        target: the PEM whose probabilities weight the rollouts (may be ``sampler`` itself).
        rng: numpy Generator (unused, may be None, with ``uniforms``).
        n_steps: T, steps per rollout.
        uniforms: optional float64 [T, n K] pre-drawn u's, row t used at step t; a column slice ``[:, a K:b K]`` of
            ``rng.random((T, n K))`` reproduces rollouts a..b-1.
    Returns:
        :class:`RolloutBatch` with arrays [n, T].
    Raises:
        ValueError: ``n < 1``, ``uniforms`` not of shape [T, n K] with values in [0, 1), or neither ``rng`` nor
            ``uniforms``."""
    if n < 1:
        raise ValueError(f"simulate: n must be >= 1, got {n}")
    sim = lockstep(make_simulator, n)
    k = draws_per_rollout(sim, target)
    if uniforms is not None:
        uniforms = np.asarray(uniforms, dtype=np.float64)
        if uniforms.shape != (n_steps, n * k) or not np.all((uniforms >= 0.0) & (uniforms < 1.0)):
            raise ValueError(
                f"simulate: uniforms must be float64 [T, n K] = [{n_steps}, {n * k}] in [0, 1), "
                f"got shape {uniforms.shape}"
            )
    draws: Iterable[np.ndarray]
    if uniforms is not None:
        draws = uniforms
    elif rng is None:
        raise ValueError("simulate: rng is None and no uniforms are given")
    else:
        draws = (rng.random(n * k) for _ in range(n_steps))
    return run_batched(sim, n, n_steps, sampler, target, draws)


def branch(
    make_simulator: Callable[[], Simulator],
    parents: RolloutBatch,
    parent: np.ndarray,
    at: np.ndarray,
    target: Detector,
    rng: np.random.Generator,
) -> RolloutBatch:
    """Continue rollouts from given steps of earlier ones, events drawn from ``target``: K new rollouts. New rollout i
    replays rollout ``parent[i]``'s events at its steps ``0..at[i] - 1`` and draws from ``target`` from ``at[i]`` on
    (``log_q = log_p``), one ``rng.random(K)`` per step as :func:`branch_rollouts` draws.

    Args:
        make_simulator: builds a fresh simulator at its start state.
        parents: the rollouts to branch from, [M, T].
        parent: int [K] row of ``parents`` for each new rollout.
        at: int [K] branching steps, in [0, T - 1].
        target: the detector (p) the new events are drawn from and scored under.
        rng: the draws.
    Returns:
        :class:`RolloutBatch` [K, T].
    Raises:
        ValueError: ``parent`` / ``at`` out of range."""
    return branch_rollouts(functools.partial(lockstep, make_simulator), parents, parent, at, target, rng)


def state_replay(make_simulator: Callable[[], Simulator]) -> FeaturesFn:
    """The :attr:`pemviz.core.problems.Problem.features` of a scene run by :func:`simulate`: the state features of a
    batch's rollouts, ``make_simulator()``'s ``state_features()`` (ego float64 [F], objects float64 [M, G]) read at
    each step of the rollouts' events replayed (:func:`pemviz.core.features.replay_features`); None where the
    simulator reports none."""
    return feature_replay(functools.partial(lockstep, make_simulator))


def check_branch_args(parents: RolloutBatch, parent: np.ndarray, at: np.ndarray) -> None:
    """Raise ValueError unless ``parent`` and ``at`` are int [K >= 1] rows of ``parents`` and steps in [0, T - 1]."""
    if parent.ndim != 1 or parent.size < 1 or at.shape != parent.shape:
        raise ValueError(f"branch: parent and at must be int [K >= 1] of one shape, got {parent.shape}, {at.shape}")
    if parent.min() < 0 or parent.max() >= parents.n or at.min() < 0 or at.max() >= parents.n_steps:
        raise ValueError(f"branch: parent must be in [0, {parents.n - 1}] and at in [0, {parents.n_steps - 1}]")
