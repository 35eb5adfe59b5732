"""The toy 1-D braking model of the authors' code (``adaptiveImportanceSampler.py``), as a scenario with an exact answer.

A car starts ``total`` units from an obstacle and moves 1 unit per step. Each step a detector fires
with probability ``p(distance)``; a detection at distance <= ``braking`` stops the car for good. The
car fails if it ever reaches a distance < ``safe``. The only randomness is the detector, and failure
happens iff the detector misses at every distance ``braking, braking - 1, ..., safe``, so

    p_fail = prod_{d = safe}^{braking} (1 - p(d))      (= (1 - p)^(braking - safe + 1) for constant p)

(:func:`pemviz.truth.toy_log_failure_probability`). Source: ``SimParams``/``step_state``/``car_rollout``
in craigiedon/CarlaStuff ``adaptiveImportanceSampler.py`` and ``approxDP.py``. The authors end a rollout
at its failure; here every rollout has the fixed length ``total - safe + 2`` (a
:class:`~pemviz.scenarios.RolloutBatch` has one T), which is exactly long enough for a failure to be
observed at the last step, so a failing rollout also ends at its failure. A car that has stopped stays
stopped (and reports ``stopped = 1``); its later detector outputs change nothing.

Units: abstract distance units (the ``gap_m`` column, so that every detector and the proposal read
the distance like the braking scenario's gap), one step per unit of travel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Union

import numpy as np

from pemviz.detectors import Detector, action_log_prob, step_uniforms
from pemviz.rng import by_blocks

if TYPE_CHECKING:  # imported lazily at run time: pemviz.problems imports the scenarios package
    from pemviz.problems import Problem
    from pemviz.scenarios import RolloutBatch

OBSERVATION_NAMES: tuple[str, ...] = ("gap_m", "stopped")
"""Columns of the toy's observation: distance to the obstacle (units) and 1.0 once stopped or crashed."""

DetectionProbability = Union[float, Callable[[np.ndarray], np.ndarray]]
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
        ValueError: for parameters outside these ranges.
    """

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
            ValueError: if a callable ``p_detect`` returns values outside (0, 1) or of the wrong shape.
        """
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
    """The toy's detector as a :class:`~pemviz.detectors.Detector`: logit p(detect | distance)."""

    params: ToyParams

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        return self.params.detect_logit(np.asarray(obs)[:, 0])


class ToyBraking:
    """One rollout of the toy model as a :class:`~pemviz.scenarios.Simulator` (the authors' ``step_state``)."""

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
        """The whole state, (distance, stopped) (the snapshot/restore capability of :class:`~pemviz.scenarios.Snapshotting`)."""
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


def simulate_toy(
    params: ToyParams, n: int, sampler: Detector, target: Detector, rng: np.random.Generator,
    forced: tuple[np.ndarray, np.ndarray] | None = None,
) -> "RolloutBatch":
    """``n`` toy rollouts, vectorised; the same draws and batch as :func:`pemviz.scenarios.simulate` with
    :class:`ToyBraking` (one ``rng.random(n)`` per step, detect iff ``log u <= log q(detect)``).

    ``forced``: optional (detected bool [n, T], until int [n]): rollout i takes the given actions at steps
    before ``until[i]`` instead of drawing them (a replayed prefix, for :func:`branch_toy`).

    Returns:
        :class:`~pemviz.scenarios.RolloutBatch` with observations [n, T, 2] (distance, stopped).
    Raises:
        ValueError: if ``n < 1``.
    """
    from pemviz.scenarios import RolloutBatch

    if n < 1:
        raise ValueError(f"simulate_toy: n must be >= 1, got {n}")
    T = params.steps
    distance = np.full(n, float(params.total))
    stopped = np.zeros(n, dtype=bool)
    obs = np.empty((n, T, 2))
    detected = np.empty((n, T), dtype=bool)
    log_p = np.empty((n, T))
    log_q = np.empty((n, T))
    for t in range(T):
        o = np.stack([distance, stopped.astype(np.float64)], axis=1)
        q_logit = by_blocks(sampler.detect_logit, o)  # one fixed block at a time, as on every executor
        p_logit = q_logit if target is sampler else by_blocks(target.detect_logit, o)
        u = step_uniforms(rng.random(n), sampler, q_logit, o)
        a = np.log(u) <= action_log_prob(q_logit, np.ones(n, dtype=bool))
        if forced is not None:
            a = np.where(t < forced[1], forced[0][:, t], a)
        obs[:, t] = o
        detected[:, t] = a
        log_q[:, t] = action_log_prob(q_logit, a)
        log_p[:, t] = action_log_prob(p_logit, a)
        crashed = distance < params.safe
        stopped = stopped | crashed | (a & (distance <= params.braking))
        distance = np.where(stopped, distance, distance - 1.0)
    return RolloutBatch(obs, detected, log_p, log_q, OBSERVATION_NAMES)


def branch_toy(
    params: ToyParams, parents: "RolloutBatch", parent: np.ndarray, at: np.ndarray, target: Detector,
    rng: np.random.Generator,
) -> "RolloutBatch":
    """:func:`pemviz.scenarios.branch` for the toy, vectorised: the parents' prefixes are replayed (the state at a
    step is a function of the actions before it) and the rest drawn from ``target``; [K, T]."""
    from pemviz.scenarios import check_branch_args

    parent, at = np.asarray(parent, dtype=np.int64), np.asarray(at, dtype=np.int64)
    check_branch_args(parents, parent, at)
    return simulate_toy(params, parent.size, target, target, rng, forced=(parents.detected[parent], at))


def toy_problem(params: ToyParams | None = None, name: str | None = None) -> "Problem":
    """The toy as a :class:`~pemviz.problems.Problem`: failure = classic robustness of
    ``G[0,T-1](d >= safe)`` below 0; the proposal sees h(s) = distance / total (as the authors'
    ``FFPolicy`` norm); curves are reported at the integer distances ``safe - 1 .. total``.
    """
    from pemviz import stl
    from pemviz.problems import Problem, Thresholds
    from pemviz.truth import toy_log_failure_probability  # truth imports this module

    p = params or ToyParams()
    formula = stl.parse(f"G[0,{p.steps - 1}](d >= {p.safe})")

    def run(n: int, sampler: Detector, target: Detector, rng: np.random.Generator):
        return simulate_toy(p, n, sampler, target, rng)

    def branch(parents, parent, at, target: Detector, rng: np.random.Generator):
        return branch_toy(p, parents, parent, at, target, rng)

    p_label = f"{p.p_detect:g}" if not callable(p.p_detect) else "p(d)"
    return Problem(
        name or f"toy({p.total},{p.braking},{p.safe},{p_label})",
        run,
        ToyDetector(p),
        formula,
        signals={"d": "gap_m"},
        units={"d": "units"},
        thresholds=Thresholds(float(p.safe), float(p.braking), "units", "failure below", "braking within"),
        signal_ranges={"d": (0.0, float(p.total))},
        h_scale=float(p.total),
        curve_grid=np.arange(max(p.safe - 1, 0), p.total + 1, dtype=np.float64),
        window=float(p.braking) + 0.5,
        exact_log_p=toy_log_failure_probability(p),
        branch=branch,
        description=(f"toy braking: {p.total} steps from the obstacle, braking possible within {p.braking}, failure "
                     f"closer than {p.safe}; detection probability {p_label}"),
    )
