"""The toy 1-D braking model of the authors' code (``adaptiveImportanceSampler.py``), as a scenario with an exact
answer.

A car starts ``total`` units from an obstacle and moves 1 unit per step; each step a detector fires with probability
``p(distance)``, and a detection at distance <= ``braking`` stops the car for good. It fails iff the detector misses
at every distance ``braking .. safe``:

    p_fail = prod_{d = safe}^{braking} (1 - p(d))      (:func:`toy_log_failure_probability`).

Source: craigiedon/CarlaStuff ``adaptiveImportanceSampler.py`` and ``approxDP.py``. Every rollout has the fixed
length ``total - safe + 2``, just long enough to observe a failure. Units: abstract distance units (the ``gap_m``
column), one step per unit of travel."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.special import log_expit

from pemviz.core.detectors import Detector
from pemviz.core.lockstep import run_batched
from pemviz.core.rollouts import RolloutBatch

OBSERVATION_NAMES: tuple[str, ...] = ("gap_m", "stopped")
"""Columns of the toy's observation: distance to the obstacle (units) and 1.0 once stopped or crashed."""

DetectionProbability = float | Callable[[np.ndarray], np.ndarray]
"""A constant p(detect) in (0, 1), or a function ``p(distance float64 [N]) -> float64 [N]`` in (0, 1)."""


@dataclass(frozen=True)
class ToyParams:
    """The toy braking problem ``(total, braking, safe, p)`` of the authors' code.

    Attributes:
        total: start distance (units, integer >= 2).
        braking: a detection at distance <= ``braking`` stops the car.
        safe: failure = the distance drops below ``safe``; 1 <= safe <= braking < total.
        p_detect: p(detect), a constant or a function of the distance (:data:`DetectionProbability`).
        n_steps: steps per rollout; default ``total - safe + 2``, the first step at which a failure can
            be observed plus one (a failing rollout ends at its failure, as in the authors' ``car_rollout``);
            at least that.
    Raises:
        ValueError: for parameters outside these ranges."""

    total: int = 100
    braking: int = 50
    safe: int = 30
    p_detect: DetectionProbability = 0.9
    n_steps: int | None = None

    def __post_init__(self) -> None:
        for name in ("total", "braking", "safe"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool):
                raise ValueError(f"ToyParams: {name} = {v!r} must be an integer")
        if not 1 <= self.safe <= self.braking < self.total:
            raise ValueError(
                f"ToyParams: need 1 <= safe <= braking < total, got total={self.total}, "
                f"braking={self.braking}, safe={self.safe}"
            )
        if not callable(self.p_detect):
            p = self.p_detect
            if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0.0 < float(p) < 1.0:
                raise ValueError(f"ToyParams: p_detect = {p!r} must be in (0, 1) or a function of the distance")
        if self.steps < self.total - self.safe + 2:
            raise ValueError(
                f"ToyParams: n_steps = {self.n_steps} is too short to observe a failure; "
                f"need at least total - safe + 2 = {self.total - self.safe + 2}"
            )

    @property
    def steps(self) -> int:
        """T, steps per rollout."""
        return self.total - self.safe + 2 if self.n_steps is None else int(self.n_steps)

    def detect_probability(self, distance: np.ndarray) -> np.ndarray:
        """p(detect | distance), float64 of the shape of ``distance``.

        Raises:
            ValueError: if a callable ``p_detect`` returns values outside (0, 1) or of the wrong shape."""
        d = np.asarray(distance, dtype=np.float64)
        if not callable(self.p_detect):
            return np.full(d.shape, float(self.p_detect))
        p = np.asarray(self.p_detect(d), dtype=np.float64)
        if p.shape != d.shape or not np.all((p > 0.0) & (p < 1.0)):
            raise ValueError("ToyParams.p_detect(distance) must return values in (0, 1), one per distance")
        return p

    def detect_logit(self, distance: np.ndarray) -> np.ndarray:
        """logit p(detect | distance) = log p - log(1 - p), float64 (nats)."""
        p = self.detect_probability(distance)
        return np.log(p) - np.log1p(-p)


@dataclass(frozen=True)
class ToyDetector:
    """The toy's detector as a :class:`~pemviz.core.detectors.Detector`: logit p(detect | distance)."""

    params: ToyParams

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        return self.params.detect_logit(np.asarray(obs)[:, 0])


class ToyBraking:
    """One rollout of the toy model as a :class:`~pemviz.core.rollouts.Simulator` (the authors' ``step_state``)."""

    observation_names = OBSERVATION_NAMES

    def __init__(self, params: ToyParams | None = None) -> None:
        self.params = params or ToyParams()
        self.reset()

    def reset(self) -> None:
        self.distance = self.params.total
        self.stopped = False

    def observation(self) -> np.ndarray:
        """float64 [2]: (distance, stopped)."""
        return np.array([float(self.distance), float(self.stopped)])

    def snapshot(self) -> tuple[int, bool]:
        """The whole state, (distance, stopped) (the snapshot/restore capability of
        :class:`~pemviz.core.rollouts.Snapshotting`)."""
        return (self.distance, self.stopped)

    def restore(self, state: tuple[int, bool]) -> None:
        self.distance, self.stopped = state

    def step(self, detected: bool) -> None:
        p = self.params
        if self.distance < p.safe:  # crashed: absorbing
            self.stopped = True
        elif self.stopped or (detected and self.distance <= p.braking):
            self.stopped = True
        else:
            self.distance -= 1


FEATURE_NAMES: tuple[str, ...] = ("stopped",)
"""The toy's ego state feature (:meth:`BatchedToy.state_features`): 1.0 once stopped or crashed."""

OBJECT_FEATURE_NAMES: tuple[str, ...] = ("misses_in_a_row",)
"""The toy's object state feature: the detector's misses since its last detection (a count)."""


class BatchedToy:
    """n toy rollouts stepped together, a :class:`~pemviz.core.rollouts.BatchedSimulator`: the vectorised
    :class:`ToyBraking` (the same states for the same detections). It reports its state features
    (:class:`pemviz.core.features.FeatureSimulator`): whether the car stopped, and the misses in a row."""

    observation_names = OBSERVATION_NAMES
    feature_names = FEATURE_NAMES
    object_feature_names = OBJECT_FEATURE_NAMES

    def __init__(self, params: ToyParams, n: int) -> None:
        self.params = params
        self.distance = np.full(n, float(params.total))
        self.stopped = np.zeros(n, dtype=bool)
        self.misses = np.zeros(n)

    def state_features(self) -> tuple[np.ndarray, np.ndarray]:
        """float64 [n, 1] (:data:`FEATURE_NAMES`) and [n, 1, 1] (:data:`OBJECT_FEATURE_NAMES`)."""
        return self.stopped.astype(np.float64)[:, None], self.misses[:, None, None].copy()

    def observation(self) -> np.ndarray:
        """float64 [n, 2]: (distance, stopped)."""
        return np.stack([self.distance, self.stopped.astype(np.float64)], axis=1)

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None:
        """``detected``: bool [n, 1] (or [n]), the detector's output at each rollout's one object."""
        p, a = self.params, np.asarray(detected, dtype=bool).reshape(self.distance.size)
        crashed = self.distance < p.safe
        self.misses = np.where(a, 0.0, self.misses + 1.0)
        self.stopped = self.stopped | crashed | (a & (self.distance <= p.braking))
        self.distance = np.where(self.stopped, self.distance, self.distance - 1.0)


def simulate_toy(
    params: ToyParams,
    n: int,
    sampler: Detector,
    target: Detector,
    rng: np.random.Generator,
) -> RolloutBatch:
    """``n`` toy rollouts, vectorised (:class:`BatchedToy`, :func:`pemviz.core.lockstep.run_batched`): the same
    draws and batch as :func:`pemviz.scenarios.simulate` with :class:`ToyBraking`; branches by
    :func:`pemviz.core.lockstep.branch_rollouts`.

    Returns:
        :class:`~pemviz.core.rollouts.RolloutBatch` with observations [n, T, 2] (distance, stopped).
    Raises:
        ValueError: if ``n < 1``."""
    if n < 1:
        raise ValueError(f"simulate_toy: n must be >= 1, got {n}")
    uniforms = (rng.random(n) for _ in range(params.steps))
    return run_batched(BatchedToy(params, n), n, params.steps, sampler, target, uniforms)


# -- the exact answer ----------------------------------------------------------------------------------


def toy_log_failure_probability(params: ToyParams) -> float:
    """log p_fail of the toy model, exact: ``sum_{d=safe}^{braking} log(1 - p(d))`` (nats); for constant p
    ``(braking - safe + 1) log(1 - p)``, e.g. (100, 50, 30, 0.9) gives log(1e-21). Source: the authors'
    ``adaptiveImportanceSampler.py``."""
    d = np.arange(params.safe, params.braking + 1, dtype=np.float64)
    logit = params.detect_logit(d)
    return float(np.sum(log_expit(-logit)))
