"""Problems: what the sampler needs to know about a scenario, independent of which scenario it is.

A :class:`Problem` bundles a black-box simulation (``simulate(n, sampler, target, rng)``), the target detector whose
probabilities weight the rollouts (the PEM), the safety requirement as an STL formula over named signals, and the
proposal's input scale. The failure event is always classic robustness below 0; the chosen metric only ranks
rollouts and sets the adaptive thresholds (Innes & Ramamoorthy (2022), Sec. IV). Here: :class:`Problem` and its
function types and a problem's functions for any batched simulator (:func:`rollout_functions`); the built-in
scenarios' problems are in :mod:`pemviz.scenarios.problems`."""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from scipy.special import expit

from pemviz import stl
from pemviz.core.detectors import Detector
from pemviz.core.estimate import Reference
from pemviz.core.features import FeaturesFn, feature_replay
from pemviz.core.lockstep import branch_rollouts, iter_rollouts, simulate_rollouts
from pemviz.core.problem_view import ProblemView, SignalView, Thresholds
from pemviz.core.reweight import AlternativeTarget
from pemviz.core.rollouts import BatchedSimulator, RolloutBatch
from pemviz.core.severity import SeverityScale

SimulateFn = Callable[[int, Detector, Detector, np.random.Generator], RolloutBatch]
"""``simulate(n, sampler, target, rng) -> RolloutBatch``: n rollouts drawn from ``sampler``."""

LookAheadFn = Callable[[RolloutBatch], tuple[np.ndarray, np.ndarray]]
"""``look_ahead(batch) -> (start int [N], log V float64 [N])``: for each rollout a step ``start`` (a stopping time: it
depends on the steps up to it; T: none) and log P(failure | the rollout's state at that step) in nats, computed exactly
(e.g. by enumerating the detections after it; -inf: no failure possible): the estimate then weighs each rollout by its
importance weight over the steps before ``start`` times V (conditional Monte Carlo)."""

BranchFn = Callable[[RolloutBatch, np.ndarray, np.ndarray, Detector, np.random.Generator], RolloutBatch]
"""``branch(parents, parent, at, target, rng)``: K rollouts continuing rollout ``parent[i]`` of ``parents`` from step
``at[i]`` on with ``target``'s detections (:func:`pemviz.core.lockstep.branch`; needs snapshot/restore)."""

StreamFn = Callable[..., Iterator[RolloutBatch]]
"""``stream(n, sampler, target, rng, chunk_size=DEFAULT_CHUNK_SIZE)``: the rollouts of ``simulate`` with the same
arguments, in chunks of at most ``chunk_size`` rollouts (the rollouts do not depend on it)."""


class TiltSampler(Protocol):
    """A scenario's own importance sampler (``method = "tilt"``, :class:`pemviz.estimators.tilt.CommittorTilt`):
    ``solve()`` prepares it once a run and returns the rollout-steps it simulated (None: reused), ``draw(n, rng)``
    returns ``n`` rollouts (``log_q`` the proposal's) and the rollout-steps its look-aheads simulated."""

    def solve(self) -> int | None: ...

    def draw(self, n: int, rng: np.random.Generator) -> tuple[RolloutBatch, int]: ...


@dataclass(frozen=True)
class Problem:
    """A rare-failure estimation problem: simulator, target detector, safety formula.

    Attributes:
        name: short label.
        simulate: draws rollouts (see :data:`SimulateFn`).
        target: the detector the failure probability is defined under (the PEM).
        formula: the safety requirement; failure = classic robustness < 0.
        signals: STL signal name -> observation column, for every signal of the formula (a missing column makes
            :meth:`robustness` raise ValueError).
        signal_ranges: per-signal (lo, hi) for AGM's predicate normalisation (default none).
        h_scale: the proposal's input is ``obs[:, 0] / h_scale``.
        curve_grid: values of ``obs[:, 0]`` where proposal and target curves are reported [G].
        window: where the detector can change the outcome, ``obs[:, 0] < window``: the proposal replaces the target
            only there (default infinity: everywhere).
        decided_below: where the outcome is already decided, ``obs[:, 0] < decided_below``; with ``skip_decided``
            the proposal gives way to the target there (default minus infinity: nowhere).
        stream: optional, the same rollouts as ``simulate`` as chunks of bounded memory (None: cannot).
        branch: optional, continues rollouts from one of their steps (:data:`BranchFn`), for ``method = "ams"``.
        exact_log_p: natural log of the exact failure probability when known, else None; shown beside every
            estimate.
        reference: else a plain Monte Carlo reference under the same PEMs (:class:`pemviz.core.estimate.Reference`),
            or None.
        dt_s: seconds per step (None: not known, e.g. the toys).
        description: one line saying what is simulated (for sinks and tables).
        units: STL signal name -> unit, for sinks (default none).
        thresholds: the failure threshold and sampler window that sinks draw (None: none).
        objects_xy, noise_xy: where sinks find each object's position and its measurement error
            (:class:`ProblemView`); None: not drawn.
        n_objects: M, the objects the detector sees each step, known before any rollout.
        curve_rows: ``curve_rows(grid [G]) -> [G, cols]``, the object rows at which the target's curve is drawn
            (None: :meth:`target_curve`'s default).
        severity: the signal and levels of the run's exceedance curve (:class:`pemviz.core.severity.SeverityScale`;
            None: no curve).
        severity_exact: level -> the exact log P(failure and min s < level) (nats), where known.
        alternatives: other targets the rollouts are re-weighted under
            (:class:`pemviz.core.reweight.AlternativeTarget`); alternatives_source: where they come from.
        n_steps: T, the steps of a rollout (None: not known, e.g. a rollout file's problem).
        drawing: the scenario's drawing object (:class:`ProblemView`), or None: only the signals are drawn.
        verdict_cap: (verdict, reason): the best verdict the adaptive sampler may claim where its proposal is known
            to miss part of the failures (:meth:`pemviz.core.estimate.Estimate.at_most`); None: no cap.
        look_ahead: the exact failure probability from a state on (:data:`LookAheadFn`), multiplied into each
            rollout's weight up to that state: conditional Monte Carlo (Asmussen & Glynn, Stochastic Simulation,
            Springer 2007, V.4); None: the failure indicator.
        look_ahead_s: the seconds per rollout the look-ahead takes, about (0: none).
        tilt: the scenario's own importance sampler (``tilt() ->`` :class:`TiltSampler`) for ``method = "tilt"``;
            None: none.
        object_labels: what each of the M objects is called (:meth:`ProblemView.object_label`); empty: ``object 0``,
            ...
        odd: the operating design domain its rollouts draw their parameters from (:class:`pemviz.core.odd.ODD`), or
            None.
        features: the state features of a batch's rollouts (:data:`pemviz.core.features.FeaturesFn`); None: taken
            from ``simulate`` where :func:`rollout_functions` made it, else none.
        array_rqmc: the importance-sampling batches of a run with ``uniforms = "array-rqmc"`` may couple its
            rollouts (:func:`pemviz.core.detectors.step_uniforms`; L'Ecuyer, Lecot & Tuffin, Operations Research
            56(4), 2008): True only where the ranking by the sampler's logit and the object row sees what the
            controller acts on, measured (e.g. the braking scene); False (the default): i.i.d. uniforms, as a controller
            with a memory the rows do not show (a brake that counts detections) needs for its intervals to hold.

    Raises:
        ValueError: ``window`` or ``decided_below`` not a number (NaN included), ``h_scale`` not a finite number
            > 0, or ``array_rqmc`` not a bool."""

    name: str
    simulate: SimulateFn
    target: Detector
    formula: stl.Formula
    signals: Mapping[str, str]
    signal_ranges: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    h_scale: float = 12.0
    curve_grid: np.ndarray = field(default_factory=lambda: np.linspace(0.0, 13.0, 131))
    window: float = math.inf
    decided_below: float = -math.inf
    stream: StreamFn | None = None
    branch: BranchFn | None = None
    exact_log_p: float | None = None
    reference: Reference | None = None
    dt_s: float | None = None
    description: str = ""
    units: Mapping[str, str] = field(default_factory=dict)
    thresholds: Thresholds | None = None
    curve_rows: Callable[[np.ndarray], np.ndarray] | None = None
    n_objects: int = 1
    objects_xy: tuple[str, str] | None = None
    noise_xy: tuple[int, int] | None = None
    severity: SeverityScale | None = None
    severity_exact: Mapping[float, float] = field(default_factory=dict)
    alternatives: tuple[AlternativeTarget, ...] = ()
    alternatives_source: str = ""
    n_steps: int | None = None
    drawing: object | None = None
    verdict_cap: tuple[str, str] | None = None
    look_ahead: LookAheadFn | None = None
    look_ahead_s: float = 0.0
    tilt: Callable[[], TiltSampler] | None = None
    object_labels: tuple[str, ...] = ()
    odd: Any = None
    features: FeaturesFn | None = None
    array_rqmc: bool = False

    def __post_init__(self) -> None:
        for name, value, allowed in (
            ("window", self.window, "a number in the first observation column's unit (math.inf, the default: all)"),
            ("decided_below", self.decided_below, "a number (-math.inf, the default: nowhere)"),
            ("h_scale", self.h_scale, "a finite number > 0, about the first observation column's largest value"),
        ):
            number = isinstance(value, numbers.Real) and not math.isnan(value)
            if not number or (name == "h_scale" and not (math.isfinite(value) and value > 0.0)):
                raise ValueError(f"Problem {self.name!r}: {name} must be {allowed}; got {value!r}")
        if not isinstance(self.array_rqmc, bool):  # a truthy text or 1 would couple a scene that never said so
            raise ValueError(f"Problem {self.name!r}: array_rqmc must be True or False; got {self.array_rqmc!r}")
        if self.features is None:  # a problem on rollout_functions: its simulator's replay
            object.__setattr__(self, "features", getattr(self.simulate, "state_features", None))

    @property
    def view(self) -> ProblemView:
        """The problem as sinks show it: name, description, signals with units, thresholds, scene."""
        signals = tuple(SignalView(n, c, self.units.get(n, "")) for n, c in self.signals.items())
        return ProblemView(
            self.name,
            self.description or self.name,
            signals,
            self.thresholds,
            self.objects_xy,
            self.noise_xy,
            self.n_steps,
            self.drawing,
            self.look_ahead_s,
            tuple(self.object_labels),
            tuple(self.odd.names) if self.odd is not None else (),
            self.tilt is not None,
            self.n_objects,
        )

    def signal_arrays(self, batch: RolloutBatch) -> dict[str, np.ndarray]:
        """The batch's signals under their STL names, float64 [N, T] each."""
        return {name: batch.signal(col) for name, col in self.signals.items() if col in batch.observation_names}

    def robustness(self, batch: RolloutBatch, metric: str) -> np.ndarray:
        """Robustness at time 0 of the formula for every rollout, float64 [N], under ``metric``."""
        r = stl.robustness(self.formula, self.signal_arrays(batch), semantics=metric, signal_ranges=self.signal_ranges)
        return np.asarray(r, dtype=np.float64)

    def failed(self, batch: RolloutBatch, classic: np.ndarray | None = None) -> np.ndarray:
        """The failure event, bool [N]: classic robustness of the safety formula < 0 (Innes & Ramamoorthy (2022),
        Sec. IV), whatever metric ranks the rollouts.

        Args:
            batch: the rollouts [N, T].
            classic: the batch's classic robustness [N] when it is already computed (None: computed here)."""
        return (self.robustness(batch, "classic") if classic is None else np.asarray(classic)) < 0.0

    def target_curve(self) -> np.ndarray:
        """p_target(detect | h) on :attr:`curve_grid`, float64 [G], at the rows of :attr:`curve_rows`, or else the
        first object's row at step 0 of one rollout drawn by the target (seed 0) with its first column set to each
        grid value.

        Raises:
            ValueError: the target cannot read those rows (one line naming ``curve_rows``, which gives rows it can)."""
        grid = np.asarray(self.curve_grid, dtype=np.float64)
        try:
            if self.curve_rows is not None:
                rows = np.asarray(self.curve_rows(grid), dtype=np.float64)
            else:
                batch = self.simulate(1, self.target, self.target, np.random.default_rng(0))
                first = batch.observations[0, 0] if batch.objects is None else batch.objects[0, 0, 0]
                rows = np.tile(np.asarray(first, dtype=np.float64), (grid.size, 1))
                rows[:, 0] = grid
            return np.asarray(expit(self.target.detect_logit(rows)), dtype=np.float64)
        except (IndexError, KeyError, TypeError, ValueError) as exc:
            raise ValueError(
                f"{self.name}: the target's detection curve over the first column cannot be drawn "
                f"({type(exc).__name__}: {exc}); give the Problem curve_rows=lambda grid: rows [G, "
                "columns] the target reads, with grid in the first column"
            ) from None


def rollout_functions(make: Callable[[int], BatchedSimulator], n_steps: int) -> tuple[SimulateFn, StreamFn, BranchFn]:
    """A :class:`Problem`'s ``simulate``, ``stream`` and ``branch`` for a batched simulator ``make(n)`` of
    ``n_steps`` steps, through the one runner (:mod:`pemviz.core.lockstep`), ``simulate`` carrying the replay of the
    state features (:func:`pemviz.core.features.feature_replay`). Simulated on one BLAS thread (``threadpoolctl``):
    a PEM of one's own in float64 products would otherwise round by the thread count."""
    from threadpoolctl import threadpool_limits

    def run(n: int, sampler: Detector, target: Detector, rng: np.random.Generator) -> RolloutBatch:
        with threadpool_limits(1, user_api="blas"):
            return simulate_rollouts(make, n, n_steps, sampler, target, rng)

    def stream(n: int, *args: Any, **kwargs: Any) -> Iterator[RolloutBatch]:
        """:func:`pemviz.core.lockstep.iter_rollouts` of ``make`` (``sampler, target, rng, chunk_size=...,
        keep_rows=...``)."""
        chunks = iter_rollouts(make, n, n_steps, *args, **kwargs)
        while True:  # one thread while a chunk is simulated, whatever the consumer does between chunks
            with threadpool_limits(1, user_api="blas"):
                batch = next(chunks, None)
            if batch is None:
                return
            yield batch

    def resume(*args: Any, **kwargs: Any) -> RolloutBatch:
        """:func:`pemviz.core.lockstep.branch_rollouts` of ``make`` (``parents, parent, at, target, rng,
        events_only=False``)."""
        with threadpool_limits(1, user_api="blas"):
            return branch_rollouts(make, *args, **kwargs)

    stream.elides_rows = True  # type: ignore[attr-defined]  # it takes keep_rows=False (Experiment)
    resume.events_only = True  # type: ignore[attr-defined]  # it takes events_only=True (the look-ahead score)
    run.state_features = feature_replay(make)  # type: ignore[attr-defined]  # the Problem's features (post_init)
    return run, stream, resume


def no_branch_message(problem: Problem) -> str:
    """The one-line error for a problem whose simulator cannot be continued from a step."""
    return f"method ams needs a simulator with snapshot/restore; {problem.name} has none"


def step_robustness(problem: Problem, batch: RolloutBatch) -> np.ndarray:
    """The classic robustness of the operand of the problem's ``G[a,b](operand)`` formula at every step, float64
    [N, T], +inf outside [a, b].

    Raises:
        ValueError: a formula that is not ``G[a,b](state predicate)`` (cf. :func:`pemviz.stl.first_violation`)."""
    f = problem.formula
    if not isinstance(f, stl.Always) or f.operand.horizon() != 0:
        raise ValueError(f"method ams needs a safety formula G[a,b](state predicate), got {f}")
    rho = np.array(stl.robustness_signal(f.operand, problem.signal_arrays(batch), "classic"), dtype=np.float64)
    rho = np.atleast_2d(rho)
    end = rho.shape[1] - 1 if f.end is None else min(f.end, rho.shape[1] - 1)
    rho[:, : f.start] = np.inf
    rho[:, end + 1 :] = np.inf
    return rho


class StateScore:
    """A graded AMS score read off each step's state (:class:`pemviz.estimators.ams.GradedScore`): the rollouts are
    the problem's own (``simulate`` / ``branch`` under its target, the PEM), scored at every step by :meth:`graded`,
    no look-ahead. A scenario's score subclasses it and gives :meth:`graded` (e.g. -log of a committor V).

    Attributes:
        problem: the problem whose rollouts are scored (a ``branch`` of its own).
        steps: rollout-steps simulated besides the rollouts (a solve this run made; 0 by default)."""

    problem: Problem
    steps: int = 0

    def graded(self, batch: RolloutBatch) -> np.ndarray:
        """The score of every rollout's state at every step, float64 [N, T] (nats, lower = closer to failure)."""
        raise NotImplementedError

    def simulate(self, n: int, rng: np.random.Generator) -> tuple[RolloutBatch, np.ndarray]:
        """``n`` rollouts of the problem's target and their scores, float64 [n, T] (nats)."""
        batch = self.problem.simulate(n, self.problem.target, self.problem.target, rng)
        return batch, self.graded(batch)

    def branch(
        self, parents: RolloutBatch, parent: np.ndarray, at: np.ndarray, rng: np.random.Generator
    ) -> tuple[RolloutBatch, np.ndarray]:
        """``parents``' rollouts ``parent`` continued from the steps ``at`` (the problem's ``branch``) and their scores
        [K, T]."""
        assert self.problem.branch is not None, no_branch_message(self.problem)
        batch = self.problem.branch(parents, parent, at, self.problem.target, rng)
        return batch, self.graded(batch)
