"""The state the stack acts on, per step, as named numeric features: what a state-dependent proposal may read.

A batched simulator may report the state its controller acts on (:class:`FeatureSimulator`, optional):
``state_features()`` returns float64 ``[n, F]`` for the ego (``feature_names``) and ``[n, M, G]`` per object
(``object_feature_names``) before the step's perception; a scene on the library's tracker gets them from
:func:`pemviz.stack.tracker.features`. They are not kept in a :class:`pemviz.core.rollouts.RolloutBatch`:
:func:`replay_features` rebuilds them from the events (:attr:`pemviz.core.problems.Problem.features`), and
:func:`check_features` checks them (shapes, finite, the same replayed twice and at any chunk size)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol, TypeGuard

import numpy as np

from pemviz.core.rollouts import BatchedSimulator, RolloutBatch, n_objects_of


class FeatureSimulator(BatchedSimulator, Protocol):
    """A :class:`pemviz.core.rollouts.BatchedSimulator` that reports the state its controller acts on:
    ``state_features() -> (ego float64 [n, F], objects float64 [n, M, G])`` at the current step, named
    ``feature_names`` (F) and ``object_feature_names`` (G); a function of the events before the step only, and of each
    rollout's own."""

    @property
    def feature_names(self) -> Sequence[str]: ...

    @property
    def object_feature_names(self) -> Sequence[str]: ...

    def state_features(self) -> tuple[np.ndarray, np.ndarray]: ...


def reports_features(sim: object) -> TypeGuard[FeatureSimulator]:
    """Whether ``sim`` reports state features (:class:`FeatureSimulator`)."""
    return callable(getattr(sim, "state_features", None))


@dataclass(frozen=True)
class StateFeatures:
    """The state features of N rollouts of T steps (:func:`replay_features`).

    Attributes:
        ego: float64 [N, T, F] (``feature_names``).
        objects: float64 [N, T, M, G] (``object_feature_names``).
        feature_names, object_feature_names: the F and G names."""

    ego: np.ndarray
    objects: np.ndarray
    feature_names: tuple[str, ...]
    object_feature_names: tuple[str, ...]

    def feature(self, name: str) -> np.ndarray:
        """The ego feature ``name``, float64 [N, T]; raises KeyError naming the known ones."""
        if name not in self.feature_names:
            raise KeyError(f"unknown feature {name!r}; these features are {self.feature_names}")
        return self.ego[:, :, self.feature_names.index(name)]

    def object_feature(self, name: str) -> np.ndarray:
        """The object feature ``name``, float64 [N, T, M]; raises KeyError naming the known ones."""
        if name not in self.object_feature_names:
            raise KeyError(f"unknown object feature {name!r}; these features are {self.object_feature_names}")
        return self.objects[:, :, :, self.object_feature_names.index(name)]


FeaturesFn = Callable[[RolloutBatch, "int | None"], "StateFeatures | None"]
"""``features(batch, chunk_size)``: the state features of ``batch``'s rollouts (:func:`replay_features`), replayed in
chunks of at most ``chunk_size`` rollouts (None: all at once); None where the simulator reports none."""


def replay_features(
    make: Callable[[int], BatchedSimulator],
    detected: np.ndarray,
    noise: np.ndarray | None,
    chunk_size: int | None = None,
) -> StateFeatures | None:
    """The state features of K rollouts of the batched simulator ``make(k)`` that took the events ``detected`` bool
    [K, T, M] and ``noise`` float64 [K, T, M, D] (or None): the simulator stepped with those events, in chunks of at
    most ``chunk_size`` rollouts (None: one chunk), ``state_features()`` read at each step before it is stepped.

    Returns:
        :class:`StateFeatures` [K, T], or None: the simulator reports none (:func:`reports_features`).
    Raises:
        ValueError: features of another shape than their names say (one line naming the simulator), or
            ``chunk_size`` < 1."""
    k, n_steps = detected.shape[:2]
    if chunk_size is not None and chunk_size < 1:
        raise ValueError(f"replay_features: chunk_size must be >= 1, got {chunk_size}")
    size = max(k, 1) if chunk_size is None else chunk_size
    ego = objects = None
    names: tuple[tuple[str, ...], tuple[str, ...]] = ((), ())
    for start in range(0, max(k, 1), size):
        stop = min(start + size, k)
        sim = make(max(stop - start, 1))
        if not reports_features(sim):
            return None
        names = (tuple(sim.feature_names), tuple(sim.object_feature_names))
        m = n_objects_of(sim)
        if ego is None or objects is None:
            ego, objects = np.empty((k, n_steps, len(names[0]))), np.empty((k, n_steps, m, len(names[1])))
        for t in range(n_steps if k else 0):
            e, o = (np.asarray(a, dtype=np.float64) for a in sim.state_features())
            want = ((stop - start, len(names[0])), (stop - start, m, len(names[1])))
            if (e.shape, o.shape) != want:
                raise ValueError(
                    f"{type(sim).__name__}.state_features() at step {t}: shapes {e.shape} and {o.shape}, not "
                    f"{want[0]} and {want[1]} (rollouts, [objects,] feature_names / object_feature_names)"
                )
            ego[start:stop, t], objects[start:stop, t] = e, o
            sim.step(detected[start:stop, t], None if noise is None else noise[start:stop, t])
    assert ego is not None and objects is not None  # the loop ran at least once
    return StateFeatures(ego, objects, *names)


def feature_replay(make: Callable[[int], BatchedSimulator]) -> FeaturesFn:
    """A problem's :attr:`pemviz.core.problems.Problem.features` for the batched simulator ``make(n)``: the features
    of a batch's rollouts replayed from its events (:func:`replay_features`)."""

    def features(batch: RolloutBatch, chunk_size: int | None = None) -> StateFeatures | None:
        return replay_features(make, batch.detected, batch.noise, chunk_size)

    return features


def check_features(features: FeaturesFn, batch: RolloutBatch, chunk_size: int) -> str | None:
    """What is wrong with the state features of ``batch`` (None: nothing): each name once, every value finite, the
    same replayed twice, and the same replayed in chunks of ``chunk_size`` rollouts as all at once (the first
    difference: feature, rollout, step, object).

    Raises:
        ValueError: the simulator reports no features (nothing to check)."""
    first = features(batch, None)
    if first is None:
        raise ValueError("check_features: the simulator reports no state features")
    for kind, names in (("feature_names", first.feature_names), ("object_feature_names", first.object_feature_names)):
        if len(set(names)) != len(names):
            return f"{kind} {names} name a feature twice"
    for kind, values, names in (
        ("ego feature", first.ego, first.feature_names),
        ("object feature", first.objects, first.object_feature_names),
    ):
        bad = np.argwhere(~np.isfinite(values))
        if bad.size:
            i = tuple(map(int, bad[0]))
            return (
                f"{kind} {names[i[-1]]!r} is {values[i].item()!r} at rollout {i[0]}, step {i[1]}"
                f"{f', object {i[2]}' if len(i) == 4 else ''} (every feature must be finite)"
            )
    for how, chunk in (("replayed again", None), (f"replayed in chunks of {chunk_size} rollouts", chunk_size)):
        other = features(batch, chunk)
        assert other is not None  # the same simulator
        for kind, a, b, names in (
            ("ego feature", first.ego, other.ego, first.feature_names),
            ("object feature", first.objects, other.objects, first.object_feature_names),
        ):
            differ = np.argwhere(a != b)
            if differ.size:
                i = tuple(map(int, differ[np.lexsort((differ[:, 0], differ[:, 1]))[0]]))
                return (
                    f"{kind} {names[i[-1]]!r} at rollout {i[0]}, step {i[1]}"
                    f"{f', object {i[2]}' if len(i) == 4 else ''}: {a[i].item()!r} replayed at once, "
                    f"{b[i].item()!r} {how} (features must be a function of each rollout's own events)"
                )
    return None


def with_state(batch: RolloutBatch, features: StateFeatures) -> RolloutBatch:
    """``batch`` whose object rows [N, T, M, G] carry the rollouts' state features after their own columns: [N, T, M,
    G + G_o + F], each object's features (``object_feature_names``) then its ego's (``feature_names``), the order
    :func:`pemviz.core.lockstep.run_batched` hands them to a detector that reads them."""
    rows = batch.object_rows
    n, n_steps, m = batch.detected.shape
    ego = np.broadcast_to(features.ego[:, :, None, :], (n, n_steps, m, features.ego.shape[-1]))
    names = (
        *batch.row_names,
        *(f"object {x}" for x in features.object_feature_names),
        *(f"ego {x}" for x in features.feature_names),
    )
    objects = np.concatenate([rows, features.objects, ego], axis=-1)
    return dataclasses.replace(batch, objects=objects, object_names=names, replay=None)
