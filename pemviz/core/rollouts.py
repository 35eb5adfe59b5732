"""The black-box simulator protocols (:class:`Simulator`, :class:`BatchedSimulator` for n rollouts at once, the
optional :class:`Snapshotting`) and the rollouts they give (:class:`RolloutBatch`), scene-neutral;
:mod:`pemviz.core.lockstep` simulates them."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol, TypeGuard

import numpy as np

from pemviz.core.detector_noise import noise_names_of
from pemviz.core.detectors import Detector


class Simulator(Protocol):
    """A black-box scenario stepped by the detector's output; its only randomness is the perception.

    Required: ``observation_names``, ``reset()``, ``observation() -> float64 [F]``, ``step(...)``. A scene of several
    objects also has ``n_objects`` (M), ``object_names`` (G names) and ``objects() -> float64 [M, G]``, and its
    ``step(detected: bool [M], noise: float64 [M, D] | None)`` takes every object's event; without them the
    simulator has one object whose row is its observation and ``step(detected: bool)``."""

    @property
    def observation_names(self) -> Sequence[str]: ...

    def reset(self) -> None: ...

    def observation(self) -> np.ndarray: ...

    def step(self, detected: bool) -> None: ...


class Snapshotting(Simulator, Protocol):
    """A :class:`Simulator` whose state can be saved and put back (the optional snapshot/restore capability).

    ``restore(snapshot())`` on any simulator of the same scenario, then the same detections, gives exactly
    the observations the snapshotted simulator would have reported (bit for bit)."""

    def snapshot(self) -> object: ...

    def restore(self, state: object) -> None: ...


class BatchedSimulator(Protocol):
    """n rollouts of a scenario stepped together: ``observation() -> float64 [n, F]``, ``step(detected: bool [n, M],
    noise: float64 [n, M, D] | None)``; with several objects also ``n_objects``, ``object_names`` and ``objects() ->
    float64 [n, M, G]`` (else one object per rollout whose row is its observation)."""

    @property
    def observation_names(self) -> Sequence[str]: ...

    def observation(self) -> np.ndarray: ...

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None: ...


class ObjectsSimulator(Protocol):
    """A :class:`Simulator` of a scene of several objects: ``objects() -> float64 [M, G]`` (``object_names``) and
    ``step(detected: bool [M], noise: float64 [M, D] | None)``."""

    @property
    def observation_names(self) -> Sequence[str]: ...

    @property
    def object_names(self) -> Sequence[str]: ...

    def reset(self) -> None: ...

    def observation(self) -> np.ndarray: ...

    def objects(self) -> np.ndarray: ...

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None: ...


class BatchedObjectsSimulator(BatchedSimulator, Protocol):
    """A :class:`BatchedSimulator` of several objects a rollout: ``objects() -> float64 [n, M, G]`` (``object_names``,
    not None)."""

    @property
    def object_names(self) -> Sequence[str]: ...

    def objects(self) -> np.ndarray: ...


def reports_objects(sim: BatchedSimulator) -> TypeGuard[BatchedObjectsSimulator]:
    """Whether a batched simulator reports object rows (``object_names`` not None; else one object per rollout whose
    row is its observation)."""
    return getattr(sim, "object_names", None) is not None


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
        log_p: float64 [N, T] log p_target(events_t | s_t) (nats), the M objects' events together.
        log_q: float64 [N, T] the same under the detector that sampled (nats).
        observation_names: names of the F columns.
        log_q_parts: None, or float64 [N, K, T] log q_k(events_t | s_t) (nats) under K other detectors.
        objects: float64 [N, T, M, G] each object's row (``object_names``), or None: its row is the observation.
        object_names: the G names of the object rows (None: ``observation_names``).
        noise: float64 [N, T, M, D] the detected objects' measurement errors (0 where missed), or None.
        noise_names: the D names of the errors (e.g. ``("range_err_m", "lateral_err_m")``).
        log_q_params: None, or float64 [N] log q(theta) - log p_ODD(theta) (nats) of ODD parameters drawn from a
            proposal (:mod:`pemviz.core.odd_proposal`).
        replay: None, or ``(detected, noise) -> objects`` rebuilding the object rows of a batch simulated without
            them when ``objects`` is first read (:func:`replay_rows`; :meth:`select` first)."""

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
    log_q_params: np.ndarray | None = None
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

    def with_changes(self, **changes: Any) -> RolloutBatch:
        """``dataclasses.replace(self, **changes)``, except that object rows not kept stay so (``replace`` reads every
        field, and reading ``objects`` rebuilds them: :attr:`rows_elided`)."""
        if self.rows_elided and "objects" not in changes:
            changes = {"objects": None, "replay": self.replay, **changes}
        return replace(self, **changes)

    def with_rows(self) -> RolloutBatch:
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
            raise ValueError(
                f"RolloutBatch: detected must be bool [N, T, M] (or [N, T]: one object), got shape "
                f"{self.detected.shape}"
            )

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

    def log_weight(self, n_factors: int | None = None) -> np.ndarray:
        """Importance log-weights ``sum_t log p - log q`` over the first ``n_factors`` steps (less
        :attr:`log_q_params`), float64 [N]; default T - 1 factors, as the last action affects nothing (Innes &
        Ramamoorthy (2022), Algorithm 1)."""
        k = self.n_steps - 1 if n_factors is None else n_factors
        log_w = (self.log_p[:, :k] - self.log_q[:, :k]).sum(axis=1)
        return log_w if self.log_q_params is None else log_w - self.log_q_params

    def log_likelihood(self, n_factors: int | None = None) -> np.ndarray:
        """``sum_t log p_target(a_t | s_t)`` over the first ``n_factors`` steps (default T - 1, as
        :meth:`log_weight`), float64 [N] (nats): how likely each rollout's detections are under the PEM."""
        k = self.n_steps - 1 if n_factors is None else n_factors
        return self.log_p[:, :k].sum(axis=1)

    def select(self, rows: np.ndarray | slice) -> RolloutBatch:
        """The rollouts ``rows`` (bool [N] mask, int indices or a slice), copied: a batch of its own, in their
        order."""

        def take(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[rows]

        objects = object.__getattribute__(self, "objects")  # rows not kept stay so: the selection replays its own
        return replace(
            self,
            observations=self.observations[rows],
            detected=self.detected[rows],
            log_p=self.log_p[rows],
            log_q=self.log_q[rows],
            log_q_parts=take(self.log_q_parts),
            objects=take(objects),
            noise=take(self.noise),
            log_q_params=take(self.log_q_params),
            replay=self.replay if objects is None else None,
        )

    @staticmethod
    def concatenate(batches: Sequence[RolloutBatch]) -> RolloutBatch:
        """Stack batches of equal T along N (``log_q_parts`` too where every batch has them)."""

        def cat(field: str) -> np.ndarray:
            return np.concatenate([getattr(b, field) for b in batches])

        def cat_optional(field: str) -> np.ndarray | None:
            parts = [getattr(b, field) for b in batches]
            return None if any(x is None for x in parts) else np.concatenate(parts)

        params = [b.log_q_params for b in batches]  # a component drawing from the ODD itself: 0
        lazy = all(b.rows_elided for b in batches)  # else every batch's rows, rebuilt where not kept
        return replace(
            batches[0],
            observations=cat("observations"),
            detected=cat("detected"),
            log_p=cat("log_p"),
            log_q=cat("log_q"),
            log_q_parts=cat_optional("log_q_parts"),
            objects=None if lazy else cat_optional("objects"),
            noise=cat_optional("noise"),
            log_q_params=None
            if all(x is None for x in params)
            else np.concatenate([np.zeros(b.n) if x is None else x for b, x in zip(batches, params, strict=True)]),
            replay=batches[0].replay if lazy else None,
        )
