"""Scenarios: black-box simulators stepped by a detector's perception of their objects, and the rollout runner.

A :class:`Simulator` reports, at each step, its scene's signals (``observation()``, float64 [F]) and the rows of its M
objects (``objects()``, float64 [M, G]: each object's salient variables and relative state, the window's column
first), and is stepped with each object's detection and, for a detector that mislocates, its measurement error
(``step(detected [M], noise [M, D])``). A single-object simulator needs neither ``objects`` nor the error: its one
object row is its observation and ``step(detected: bool)`` takes the detection (the braking scenario, the toys).
A :class:`BatchedSimulator` is the same for n rollouts at once (a leading [n]). :func:`run_batched` is the one rollout
runner: each step it asks the sampling detector and the target (PEM) about every object row of the batch, draws the
events (:func:`pemviz.core.detectors.draw_step`) and steps the simulator; :func:`simulate` runs N black-box simulators
in lockstep through it (:class:`Lockstep`), and the batched twins (:mod:`pemviz.scenarios.batched`, the toys) run
through it too, so every simulator draws the same events from the same uniforms.

Optional capability (:class:`Snapshotting`): ``snapshot()`` returns the simulator's whole state at the
current step and ``restore(state)`` puts it back (checked by :func:`pemviz.core.checks.check_simulator`).

The scenarios by name (:mod:`pemviz.scenarios.registry`): :func:`registered` lists them, :func:`get_scenario` returns
one's record and :func:`register` adds one of one's own (imported when first named: ``from pemviz.scenarios import
registered``); :func:`pemviz.testing.check_scenario` checks any of them.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Iterable, Iterator, Protocol, Sequence

import numpy as np

from pemviz.core.detectors import Detector, draw_step, noise_names_of
from pemviz.core.exact import row_sum
from pemviz.core.rng import JUMPABLE, RQMC_BLOCK, advance, bit_generator_at


class Simulator(Protocol):
    """A black-box scenario stepped by the detector's output; its only randomness is the perception.

    Required: ``observation_names``, ``reset()``, ``observation() -> float64 [F]``, ``step(...)``. A scene of several
    objects also has ``n_objects`` (M), ``object_names`` (G names) and ``objects() -> float64 [M, G]``, and its
    ``step(detected: bool [M], noise: float64 [M, D] | None)`` takes every object's event; without them the
    simulator has one object whose row is its observation and ``step(detected: bool)``.
    """

    observation_names: Sequence[str]

    def reset(self) -> None: ...

    def observation(self) -> np.ndarray: ...

    def step(self, detected: bool) -> None: ...


class Snapshotting(Simulator, Protocol):
    """A :class:`Simulator` whose state can be saved and put back (the optional snapshot/restore capability).

    ``restore(snapshot())`` on any simulator of the same scenario, then the same detections, gives exactly
    the observations the snapshotted simulator would have reported (bit for bit).
    """

    def snapshot(self) -> object: ...

    def restore(self, state: object) -> None: ...


class BatchedSimulator(Protocol):
    """n rollouts of a scenario stepped together: ``observation() -> float64 [n, F]``, ``step(detected: bool [n, M],
    noise: float64 [n, M, D] | None)``; with several objects also ``n_objects``, ``object_names`` and ``objects() ->
    float64 [n, M, G]`` (else one object per rollout whose row is its observation)."""

    observation_names: Sequence[str]

    def observation(self) -> np.ndarray: ...

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None: ...


def can_snapshot(sim: object) -> bool:
    """Whether ``sim`` has the snapshot/restore capability (:class:`Snapshotting`)."""
    return callable(getattr(sim, "snapshot", None)) and callable(getattr(sim, "restore", None))


def n_objects_of(sim: object) -> int:
    """M, the objects a (batched) simulator reports each step (1 without ``n_objects``)."""
    return int(getattr(sim, "n_objects", 1))


def draws_per_rollout(sim: object, target: Detector) -> int:
    """Uniforms a rollout of ``sim`` draws per step under ``target``: M (1 + D), one per object to detect it and D for
    its measurement error (1 for a single-object simulator whose detectors only detect)."""
    return n_objects_of(sim) * (1 + len(noise_names_of(target)))


@dataclass(frozen=True)
class RolloutBatch:
    """N rollouts of T steps of M objects, with the log-probabilities of every step's perception under both detectors.

    Attributes:
        observations: float64 [N, T, F] the scene's signals at each step (``observation_names``).
        detected: bool [N, T, M] each object's detection taken (given as [N, T]: one object per step).
        log_p: float64 [N, T] log p_target(events_t | s_t) (nats): the step's M objects' detections (and measurement
            errors) together, target = the PEM.
        log_q: float64 [N, T] the same under the detector that sampled (nats).
        observation_names: names of the F columns.
        log_q_parts: None, or float64 [N, K, T] log q_k(events_t | s_t) (nats) under each of K other detectors, e.g.
            the components of a mixture over rollouts, as an estimator asked them while the rollouts were drawn.
        objects: float64 [N, T, M, G] each object's row (``object_names``), or None: one object (M = 1) whose row is
            the observation.
        object_names: the G names of the object rows (None: ``observation_names``).
        noise: float64 [N, T, M, D] the measurement errors of the detected objects (0 where missed), or None (D = 0).
        noise_names: the D names of the errors (e.g. ``("range_err_m", "lateral_err_m")``).
        replay: None, or a function ``(detected [K, T, M], noise [K, T, M, D] | None) -> objects [K, T, M, G]``
            that rebuilds the object rows of rollouts by replaying their events (:func:`replay_rows`). A batch
            simulated without its object rows (``objects`` None, ``replay`` given: :func:`run_batched` with
            ``keep_rows=False``) rebuilds them when ``objects`` is first read, for the rollouts it holds then: select
            the few rollouts whose rows are wanted first (:meth:`select`, :meth:`object_rows_of`). The rows are bit for
            bit those of the simulation (a state is a function of the events before it).
    """

    observations: np.ndarray
    detected: np.ndarray
    log_p: np.ndarray
    log_q: np.ndarray
    observation_names: tuple[str, ...]
    log_q_parts: np.ndarray | None = None
    objects: np.ndarray | None = None
    object_names: tuple[str, ...] | None = None
    noise: np.ndarray | None = None
    noise_names: tuple[str, ...] = ()
    replay: Callable[[np.ndarray, np.ndarray | None], np.ndarray] | None = field(default=None, compare=False)

    def __getattribute__(self, name: str) -> Any:
        if name != "objects":
            return object.__getattribute__(self, name)
        rows = object.__getattribute__(self, "objects")
        if rows is None:
            replay = object.__getattribute__(self, "replay")
            if replay is not None:  # rebuilt once, from this batch's events
                rows = replay(self.detected, self.noise)
                object.__setattr__(self, "objects", rows)
                object.__setattr__(self, "replay", None)
        return rows

    @property
    def rows_elided(self) -> bool:
        """Whether the object rows were not kept and would be rebuilt by replay when read (:attr:`replay`)."""
        return object.__getattribute__(self, "objects") is None and self.replay is not None

    def with_changes(self, **changes: Any) -> "RolloutBatch":
        """``dataclasses.replace(self, **changes)``, except that object rows not kept stay so (``replace`` reads every
        field, and reading ``objects`` rebuilds them: :attr:`rows_elided`)."""
        if self.rows_elided and "objects" not in changes:
            changes = {"objects": None, "replay": self.replay, **changes}
        return replace(self, **changes)

    def with_rows(self) -> "RolloutBatch":
        """This batch with its object rows held (rebuilt by replay where they were not kept: :attr:`rows_elided`)."""
        return replace(self, objects=self.objects, replay=None) if self.rows_elided else self

    def object_rows_of(self, rows: np.ndarray) -> np.ndarray:
        """``object_rows[rows]`` (bool [N] mask or int indices), float64 [K, T, M, G]; a batch without its rows
        (:attr:`rows_elided`) rebuilds those K rollouts' rows only."""
        if self.rows_elided:
            return self.select(rows).object_rows
        return self.object_rows[rows]

    def __post_init__(self) -> None:
        if self.detected.ndim == 2:  # one object per step
            object.__setattr__(self, "detected", self.detected[:, :, None])
        if self.detected.ndim != 3:
            raise ValueError(f"RolloutBatch: detected must be bool [N, T, M] (or [N, T]: one object), got shape "
                             f"{self.detected.shape}")

    @property
    def n(self) -> int:
        return int(self.detected.shape[0])

    @property
    def n_steps(self) -> int:
        return int(self.detected.shape[1])

    @property
    def n_objects(self) -> int:
        """M, the objects perceived at each step."""
        return int(self.detected.shape[2])

    @property
    def object_rows(self) -> np.ndarray:
        """float64 [N, T, M, G]: each object's row (the observation itself for a single-object scenario; a view)."""
        return self.observations[:, :, None, :] if self.objects is None else self.objects

    def events(self) -> tuple[np.ndarray, np.ndarray]:
        """(object rows float64 [N, T M, G], detections bool [N, T M]): each rollout's object events in order, step by
        step and the objects of a step together (for a single-object batch, views of the observations and detections
        [N, T])."""
        rows = self.object_rows
        return rows.reshape(self.n, -1, rows.shape[-1]), self.detected.reshape(self.n, -1)

    @property
    def row_names(self) -> tuple[str, ...]:
        """The G names of :attr:`object_rows`."""
        return self.observation_names if self.object_names is None else self.object_names

    def signal(self, name: str) -> np.ndarray:
        """One observed signal, float64 [N, T]; raises KeyError naming the known signals."""
        try:
            return self.observations[:, :, self.observation_names.index(name)]
        except ValueError:
            raise KeyError(f"unknown signal {name!r}; this batch has {self.observation_names}") from None

    @property
    def gap_m(self) -> np.ndarray:
        return self.signal("gap_m")

    def log_weight(self, n_factors: int | None = None) -> np.ndarray:
        """Importance log-weights ``sum_t log p - log q`` over the first ``n_factors`` steps, float64 [N].

        The last action of a rollout affects nothing (Innes & Ramamoorthy (2022), Algorithm 1), so the default is T - 1 factors.
        """
        k = self.n_steps - 1 if n_factors is None else n_factors
        return (self.log_p[:, :k] - self.log_q[:, :k]).sum(axis=1)

    def log_likelihood(self, n_factors: int | None = None) -> np.ndarray:
        """``sum_t log p_target(a_t | s_t)`` over the first ``n_factors`` steps (default T - 1, as
        :meth:`log_weight`), float64 [N] (nats): how likely each rollout's detections are under the PEM."""
        k = self.n_steps - 1 if n_factors is None else n_factors
        return self.log_p[:, :k].sum(axis=1)

    def select(self, rows: np.ndarray) -> "RolloutBatch":
        """The rollouts ``rows`` (bool [N] mask or int indices), copied: a batch of its own, in their order."""

        def take(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[rows]

        objects = object.__getattribute__(self, "objects")  # rows not kept stay so: the selection replays its own
        return replace(self, observations=self.observations[rows], detected=self.detected[rows],
                       log_p=self.log_p[rows], log_q=self.log_q[rows], log_q_parts=take(self.log_q_parts),
                       objects=take(objects), noise=take(self.noise),
                       replay=self.replay if objects is None else None)  # fmt: skip

    @staticmethod
    def concatenate(batches: Sequence["RolloutBatch"]) -> "RolloutBatch":
        """Stack batches of equal T along N (``log_q_parts`` too where every batch has them)."""

        def cat(field: str) -> np.ndarray | None:
            parts = [getattr(b, field) for b in batches]
            return None if any(x is None for x in parts) else np.concatenate(parts)

        lazy = all(b.rows_elided for b in batches)  # else every batch's rows, rebuilt where not kept
        return replace(batches[0], observations=cat("observations"), detected=cat("detected"), log_p=cat("log_p"),
                       log_q=cat("log_q"), log_q_parts=cat("log_q_parts"), objects=None if lazy else cat("objects"),
                       noise=cat("noise"), replay=batches[0].replay if lazy else None)  # fmt: skip


class Lockstep:
    """N black-box :class:`Simulator` objects stepped together as one :class:`BatchedSimulator`."""

    def __init__(self, sims: Sequence[Simulator]) -> None:
        self.sims = list(sims)
        first = self.sims[0]
        self.observation_names = tuple(first.observation_names)
        self.multi = hasattr(first, "objects")
        self.n_objects = n_objects_of(first)
        self.object_names = tuple(first.object_names) if self.multi else None

    def observation(self) -> np.ndarray:
        return np.stack([s.observation() for s in self.sims])

    def objects(self) -> np.ndarray:
        return np.stack([s.objects() for s in self.sims])

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None:
        if not self.multi:
            for s, a in zip(self.sims, detected[:, 0]):
                s.step(bool(a))
            return
        for i, s in enumerate(self.sims):
            s.step(detected[i], None if noise is None else noise[i])


def run_batched(
    sim: BatchedSimulator,
    n: int,
    n_steps: int,
    sampler: Detector,
    target: Detector,
    uniforms: Iterable[np.ndarray],
    forced: tuple[np.ndarray, np.ndarray | None, np.ndarray] | None = None,
    keep_rows: bool = True,
) -> RolloutBatch:
    """Simulate the ``n`` rollouts of ``sim`` for ``n_steps`` steps, each object's events drawn from ``sampler`` and
    scored under ``target`` (:func:`pemviz.core.detectors.draw_step`): the rollout runner of every simulator.

    Args:
        sim: n rollouts at their start, a :class:`BatchedSimulator`.
        uniforms: per step, float64 [n K] in [0, 1), rollout by rollout, K = :func:`draws_per_rollout` (object by
            object: its detection's uniform, then its D errors'); e.g. ``rng.random(n K)`` per step.
        forced: optional (detected bool [n, T, M], noise [n, T, M, D] or None, until int [n]): rollout i takes these
            events at its steps before ``until[i]`` (a replayed prefix).
        keep_rows: False: a simulator with object rows does not keep them (``objects`` None; the caller attaches a
            :attr:`RolloutBatch.replay`): float64 [n, T, M, G] is most of a multi-object batch's memory.
    Returns:
        :class:`RolloutBatch` [n, T] (``objects`` when the simulator reports object rows and ``keep_rows``, ``noise``
        when the target mislocates).
    """
    names = tuple(sim.observation_names)
    multi = getattr(sim, "object_names", None) is not None  # else one object per rollout: its observation
    m = n_objects_of(sim)
    noise_names = noise_names_of(target)
    d = len(noise_names)
    # Rollout-major arrays written a step (a column) at a time: ~2x as fast as step-major buffers transposed at the end
    obs = np.empty((n, n_steps, len(names)))
    det = np.empty((n, n_steps, m), dtype=bool)
    log_p, log_q = np.empty((n, n_steps)), np.empty((n, n_steps))
    objects = np.empty((n, n_steps, m, len(sim.object_names))) if multi and keep_rows else None
    noise = np.empty((n, n_steps, m, d)) if d else None
    for t, u in zip(range(n_steps), uniforms):
        o = np.asarray(sim.observation(), dtype=np.float64)
        obs[:, t] = o
        if multi:
            rows = np.asarray(sim.objects(), dtype=np.float64)
            if objects is not None:
                objects[:, t] = rows
            rows = rows.reshape(n * m, -1)  # a view where the simulator's layout allows (the cut-in's: column-major)
        else:
            rows = o
        f = None
        if forced is not None:
            given = np.repeat(t < forced[2], m)
            f = (forced[0][:, t].reshape(-1), None if forced[1] is None else forced[1][:, t].reshape(-1, d), given)
        step = draw_step(sampler, target, rows, np.asarray(u, dtype=np.float64).reshape(n * m, 1 + d),
                         RQMC_BLOCK * m, f, m)  # fmt: skip
        detected = step.detected.reshape(n, m)
        det[:, t] = detected
        if m == 1:
            log_q[:, t], log_p[:, t] = step.log_q, step.log_p
        else:  # the step's objects together
            log_q[:, t], log_p[:, t] = row_sum(step.log_q.reshape(n, m)), row_sum(step.log_p.reshape(n, m))
        errors = None
        if d:
            errors = step.noise.reshape(n, m, d)
            noise[:, t] = errors
        sim.step(detected, errors)
    return RolloutBatch(obs, det, log_p, log_q, names, objects=objects,
                        object_names=tuple(sim.object_names) if multi else None, noise=noise,
                        noise_names=noise_names)  # fmt: skip


def replay_rows(make: Callable[[int], BatchedSimulator], detected: np.ndarray,
                noise: np.ndarray | None) -> np.ndarray:  # fmt: skip
    """The object rows float64 [K, T, M, G] of K rollouts of the batched simulator ``make(K)`` that took the events
    ``detected`` bool [K, T, M] and ``noise`` float64 [K, T, M, D] (or None): the simulator stepped with those events,
    no detector asked. Bit for bit the rows :func:`run_batched` saw (a state is a function of the events before it,
    and a batched simulator's arithmetic is row by row)."""
    k, n_steps = detected.shape[:2]
    sim = make(max(k, 1))  # no rollout: the rows' shape only
    out = np.empty((k, n_steps, n_objects_of(sim), len(sim.object_names)))
    for t in range(n_steps if k else 0):
        out[:, t] = sim.objects()
        sim.step(detected[:, t], None if noise is None else noise[:, t])
    return out


DEFAULT_CHUNK_SIZE = RQMC_BLOCK
"""Rollouts a batched simulator steps together: one chunk's working set stays in cache-sized arrays (measured fastest
of 2048..65536 for the braking twin on the 2-core CI machine), one Array-RQMC block."""


def check_counts(who: str, **counts: object) -> None:
    """Raise ValueError unless every ``name=value`` is an integer >= 1 (a rollout count, a chunk size)."""
    for name, value in counts.items():
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
            raise ValueError(f"{who}: {name} must be an integer >= 1, got {value!r}")


def uniform_chunks(rng: np.random.Generator, n: int, n_steps: int, chunk_size: int,
                   per_rollout: int = 1) -> Iterator[tuple[int, int, Iterator[np.ndarray]]]:  # fmt: skip
    """``(start, stop, per-step uniforms [(stop - start) K])`` for each chunk of rollouts, K = ``per_rollout``: the
    numbers one ``rng.random(n K)`` per step gives rollouts ``start .. stop - 1``, whatever the chunks.

    With one chunk or a generator that cannot jump, the draws come from ``rng`` itself in order (the chunks then draw
    one after the other). With a PCG64 / PCG64DXSM generator each chunk reads its slice ``[t n K + start K, t n K +
    stop K)`` of the serial stream from a copy of ``rng``'s state (``bit_generator.advance``), and ``rng`` is finally
    advanced past all ``n K T`` draws, where the serial run leaves it.
    """
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


def iter_rollouts(make: Callable[[int], BatchedSimulator], n: int, n_steps: int, sampler: Detector, target: Detector,
                  rng: np.random.Generator, *, chunk_size: int = DEFAULT_CHUNK_SIZE,
                  keep_rows: bool = True) -> Iterator[RolloutBatch]:  # fmt: skip
    """Stream ``n`` rollouts of a batched simulator as :class:`RolloutBatch` chunks of at most ``chunk_size`` rollouts
    (:func:`run_batched` on ``make(m)``, m rollouts at their start), the rollouts of ``rng.random(n K)`` per step
    (:func:`uniform_chunks`): the same rollouts, bit for bit, for any chunk size. An Array-RQMC sampler's rollouts are
    simulated one fixed block of :data:`pemviz.core.rng.RQMC_BLOCK` at a time (its rollouts are coupled) and handed out
    in chunks of ``chunk_size``. With ``keep_rows=False`` a simulator's object rows are not kept: a chunk rebuilds
    the rows it is asked for by replay (:attr:`RolloutBatch.replay`, :func:`replay_rows`).

    Raises:
        ValueError: ``n`` or ``chunk_size`` not an integer >= 1.
    """
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


def simulate_rollouts(make: Callable[[int], BatchedSimulator], n: int, n_steps: int, sampler: Detector,
                      target: Detector, rng: np.random.Generator, *,
                      chunk_size: int = DEFAULT_CHUNK_SIZE) -> RolloutBatch:  # fmt: skip
    """The ``n`` rollouts of :func:`iter_rollouts` as one :class:`RolloutBatch` [n, T] (it holds them all: stream them
    for very large ``n``).

    Raises:
        ValueError: ``n`` or ``chunk_size`` not an integer >= 1.
    """
    check_counts("simulate_rollouts", n=n, chunk_size=chunk_size)
    size = RQMC_BLOCK if _coupled(sampler) else int(chunk_size)
    chunks = list(iter_rollouts(make, n, n_steps, sampler, target, rng, chunk_size=size))
    return chunks[0] if len(chunks) == 1 else RolloutBatch.concatenate(chunks)


def branch_rollouts(make: Callable[[int], BatchedSimulator], parents: RolloutBatch, parent: np.ndarray,
                    at: np.ndarray, target: Detector, rng: np.random.Generator) -> RolloutBatch:  # fmt: skip
    """:func:`branch` on a batched simulator (``make(K)``): new rollout i replays parent ``parent[i]``'s events
    before step ``at[i]`` (the state at a step is a function of the events before it) and draws the rest from
    ``target``; one ``rng.random(K k)`` per step.

    Returns:
        :class:`RolloutBatch` [K, T].
    Raises:
        ValueError: ``parent`` / ``at`` out of range (:func:`check_branch_args`).
    """
    parent, at = np.asarray(parent, dtype=np.int64), np.asarray(at, dtype=np.int64)
    check_branch_args(parents, parent, at)
    sim = make(parent.size)
    k = draws_per_rollout(sim, target) * parent.size
    noise = None if parents.noise is None else parents.noise[parent]
    return run_batched(sim, parent.size, parents.n_steps, target, target,
                       (rng.random(k) for _ in range(parents.n_steps)),
                       forced=(parents.detected[parent], noise, at))  # fmt: skip


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
    ``sampler``, scored under ``target``.

    A detection happens iff ``u <= q(detect | s)`` with ``u ~ U(0, 1)`` from ``rng`` (one ``rng.random(n K)`` per
    step, K = :func:`draws_per_rollout`: one ``rng.random(n)`` for a single-object scenario), as in the authors' code.
    The detectors are asked about one fixed block of :data:`pemviz.core.rng.RQMC_BLOCK` rollouts at a time, and an
    Array-RQMC sampler couples the rollouts of each block (``uniforms`` must then start at a block boundary of the
    batch), so that chunks of whole blocks simulated elsewhere give the same bits.

    Args:
        make_simulator: builds a fresh simulator at its start state.
        n: number of rollouts (>= 1).
        sampler: the detector that draws the events (proposal q, the PEM, a constant ...).
        target: the PEM whose probabilities weight the rollouts (may be ``sampler`` itself).
        rng: numpy Generator; the same seed gives the same batch (unused, may be None, with ``uniforms``).
        n_steps: T, steps per rollout.
        uniforms: optional float64 [T, n K] pre-drawn u's, row t used at step t instead of ``rng.random(n K)``.
            ``rng.random((T, n K))`` holds exactly the numbers of T calls ``rng.random(n K)``, so a column slice
            ``[:, a K:b K]`` of it reproduces rollouts a..b-1 of the serial run elsewhere (pemviz.engine.executors).
    Returns:
        :class:`RolloutBatch` with arrays [n, T].
    Raises:
        ValueError: ``n < 1``, or ``uniforms`` not of shape [T, n K] with values in [0, 1).
    """
    if n < 1:
        raise ValueError(f"simulate: n must be >= 1, got {n}")
    sim = Lockstep([make_simulator() for _ in range(n)])
    k = draws_per_rollout(sim, target)
    if uniforms is not None:
        uniforms = np.asarray(uniforms, dtype=np.float64)
        if uniforms.shape != (n_steps, n * k) or not np.all((uniforms >= 0.0) & (uniforms < 1.0)):
            raise ValueError(f"simulate: uniforms must be float64 [T, n K] = [{n_steps}, {n * k}] in [0, 1), "
                             f"got shape {uniforms.shape}")
    draws = uniforms if uniforms is not None else (rng.random(n * k) for _ in range(n_steps))
    return run_batched(sim, n, n_steps, sampler, target, draws)


def branch(
    make_simulator: Callable[[], Simulator],
    parents: RolloutBatch,
    parent: np.ndarray,
    at: np.ndarray,
    target: Detector,
    rng: np.random.Generator,
) -> RolloutBatch:
    """Continue rollouts from given steps of earlier ones, events drawn from ``target``: K new rollouts.

    New rollout i takes rollout ``parent[i]`` of ``parents``'s events at its steps ``0..at[i] - 1`` (a replay: the
    scenario is deterministic given its perception, so it passes through the parent's states) and draws them from
    ``target`` from step ``at[i]`` on (``log_q = log_p``), in lockstep (:func:`run_batched`): one ``rng.random(K)``
    per step 0..T - 1 for single-object rollouts (replayed rows ignore theirs), as the vectorised twins
    (:func:`pemviz.scenarios.batched.branch_batched`, :func:`pemviz.scenarios.toy.branch_toy`) draw.

    Args:
        make_simulator: builds a fresh simulator at its start state.
        parents: the rollouts to branch from, [M, T].
        parent: int [K] row of ``parents`` for each new rollout.
        at: int [K] branching steps, in [0, T - 1].
    Returns:
        :class:`RolloutBatch` [K, T].
    Raises:
        ValueError: ``parent`` / ``at`` out of range.
    """
    return branch_rollouts(lambda k: Lockstep([make_simulator() for _ in range(k)]), parents, parent, at, target, rng)


def check_branch_args(parents: RolloutBatch, parent: np.ndarray, at: np.ndarray) -> None:
    """Raise ValueError unless ``parent`` and ``at`` are int [K >= 1] rows of ``parents`` and steps in [0, T - 1]."""
    if parent.ndim != 1 or parent.size < 1 or at.shape != parent.shape:
        raise ValueError(f"branch: parent and at must be int [K >= 1] of one shape, got {parent.shape}, {at.shape}")
    if parent.min() < 0 or parent.max() >= parents.n or at.min() < 0 or at.max() >= parents.n_steps:
        raise ValueError(f"branch: parent must be in [0, {parents.n - 1}] and at in [0, {parents.n_steps - 1}]")


_REGISTRY_NAMES = {"registered": "registered", "register": "register", "get_scenario": "get", "Scenario": "Scenario"}
"""The names this package lends from :mod:`pemviz.scenarios.registry` (the name here -> the name there)."""


def __getattr__(name: str) -> Any:
    """:func:`registered`, :func:`register`, :func:`get_scenario` (the registry's ``get``) and :class:`Scenario` of
    :mod:`pemviz.scenarios.registry`, imported when first named (importing this package loads no registry)."""
    if name in _REGISTRY_NAMES:
        from pemviz.scenarios import registry

        return getattr(registry, _REGISTRY_NAMES[name])
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
