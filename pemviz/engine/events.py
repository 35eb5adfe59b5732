"""The events the experiment engine (:class:`pemviz.engine.experiment.Experiment`) emits, in order:
:class:`RunStarted` (with the :class:`~pemviz.core.plan.RunPlan` and
:class:`~pemviz.core.problem_view.ProblemView`); per stage (0 = pretraining, 1..K = cross-entropy stages, K+1 =
final batch) :class:`StageStarted`, a :class:`RolloutChunk` per chunk, one :class:`RolloutsSampled` and
:class:`StageFinished`; then :class:`FinalEstimate` and :class:`RunFinished` (or :class:`RunCancelled`). Sinks read
these and nothing else of the engine; this module imports neither torch nor the engine."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pemviz.core.plan import RunPlan

if TYPE_CHECKING:  # annotations only: the modules behind them import torch
    from pemviz.config import ExperimentConfig
    from pemviz.core.detectors import Detector
    from pemviz.core.estimate import Estimate, Reference
    from pemviz.core.odd import OddMap
    from pemviz.core.population import FailureShares
    from pemviz.core.problem_view import ProblemView
    from pemviz.core.requirement import Decision
    from pemviz.core.reweight import PemSpread
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.core.severity import SeverityCurve


@dataclass(frozen=True)
class RunStarted:
    """The run begins: its config, the PEM's detection curve, the problem and the stages the estimator plans.

    ``config`` is the run's :class:`~pemviz.config.ExperimentConfig`; ``formula`` the requirement's STL formula as
    text; ``curve_grid_m`` the distances (metres, float64 [G]) the detection curves are drawn on."""

    config: ExperimentConfig
    formula: str
    curve_grid_m: np.ndarray
    pem_curve: np.ndarray
    """p_PEM(detect | d) on ``curve_grid_m``, float64 [G]."""
    problem: ProblemView
    """What the run estimates: the problem's name and description, its signals with their units, its thresholds and
    its scene (:attr:`pemviz.core.problems.Problem.view`)."""
    plan: RunPlan
    """The stages the estimator will run (number, kind, label, rollouts) and its simulations, as it states them
    (:meth:`pemviz.estimators.base.Estimator.plan`)."""
    exact_log_p: float | None = None
    """Natural log of the problem's exact failure probability when one is known (closed form, enumeration),
    else None: sinks show it beside every estimate with the relative error."""
    reference: Reference | None = None
    """Where no exact answer is known, the problem's plain Monte Carlo reference (:attr:`Problem.reference`), else
    None: sinks show it beside every estimate the same way."""
    verdict_cap: tuple[str, str] | None = None
    """The best verdict any run of the method's stages may have on this scene and why
    (:attr:`pemviz.core.problems.Problem.verdict_cap`), or None: the time estimates leave out a retry it refuses."""


@dataclass(frozen=True)
class StageStarted:
    """A stage begins; ``n_rollouts`` the rollouts it will simulate."""

    stage: int
    """0 = pretraining, 1..K = CE stages, K+1 = the final batch (the only stage of mc / naive50)."""
    kind: str
    """``pretrain`` | ``ce`` | ``final`` | ``ams``."""
    n_rollouts: int


@dataclass(frozen=True)
class RolloutsSampled:
    """A stage's rollouts are simulated and weighed: ``batch`` (the whole stage, or a sample of a streamed one) with
    its robustness, failures and importance log-weights; ``stage`` and ``kind`` as in :class:`StageStarted`."""

    stage: int
    kind: str
    batch: RolloutBatch
    robustness: np.ndarray
    """[N] under the configured metric."""
    robustness_by_metric: Mapping[str, np.ndarray]
    """metric name -> [N] robustness under each semantics of :data:`pemviz.settings.METRICS` (computed when read)."""
    failed: np.ndarray
    """bool [N]: the problem's failure (:meth:`pemviz.core.problems.Problem.failed`: classic robustness < 0)."""
    log_weight: np.ndarray
    """[N] importance log-weights (nats), T - 1 factors."""
    sampler: Detector | None = None
    """The detector that drew the batch (the proposal is trained in place afterwards: copy it to keep it)."""
    n_total: int | None = None
    """The stage's rollouts when ``batch`` is only a sample of them (a stage streamed in chunks: its
    :data:`pemviz.engine.experiment.SAMPLE_LEAST_ROBUST` least-robust rollouts, its first
    :data:`pemviz.engine.experiment.SAMPLE_FAILURES` failures and :data:`pemviz.engine.experiment.SAMPLE_UNIFORM` evenly
    spaced ones); None: ``batch`` is the whole stage."""
    index: np.ndarray | None = None
    """int [n]: the sampled rollouts' numbers in the stage (0 .. n_total - 1), with ``n_total``."""
    stage_robustness: np.ndarray | None = None
    """[n_total] every rollout's robustness under the configured metric, with ``n_total`` (e.g. for histograms)."""
    stage_log_weight: np.ndarray | None = None
    """[n_total] every rollout's importance log-weight, with ``n_total``."""
    target: Detector | None = None
    """The detector that weighs the batch (p, the PEM); with ``sampler``, what each object's p(detect) and q(detect)
    were (:func:`pemviz.core.proposal_view.object_detect_probabilities`) while the sampler is still the one that
    drew."""

    @property
    def rollout_numbers(self) -> np.ndarray:
        """int [n]: each row's number in the stage (``index``, or 0 .. n - 1 for a whole stage)."""
        return np.arange(self.batch.n) if self.index is None else self.index

    @property
    def n_rollouts(self) -> int:
        """The stage's rollouts: ``n_total`` for a streamed stage (of which ``batch`` is a sample), else the batch's."""
        return self.batch.n if self.n_total is None else self.n_total


@dataclass(frozen=True)
class RolloutChunk:
    """Rollouts ``start .. start + batch.n - 1`` of a stage as they are simulated (all of a stage that is not
    streamed), before :class:`RolloutsSampled`; ``log_weight`` [n] as the estimator computed them (nats)."""

    stage: int
    kind: str
    start: int
    batch: RolloutBatch
    log_weight: np.ndarray
    sampler: Detector | None = None
    parts: tuple = ()
    """The stage's samplers in the order drawn, ``(rollouts, detector)`` each
    (:attr:`pemviz.estimators.base.StagePlan.parts`): several for a mixture over whole rollouts, whose rollouts are
    weighed by the mixture (:func:`pemviz.core.weights.stage_log_q`)."""
    target: Detector | None = None
    """The problem's target detector (p)."""


@dataclass(frozen=True)
class StageResult:
    """What a stage found: its threshold, elites and estimate, the proposal's detection curve after its update and
    its wall time (``wall_s``, seconds); ``stage`` and ``kind`` as in :class:`StageStarted`."""

    stage: int
    kind: str
    gamma: float
    """Stage threshold gamma_kappa (nan for pretraining and final batches)."""
    n_elites: int
    estimate: Estimate
    proposal_curve: np.ndarray
    """q(detect | d) on the problem's ``curve_grid`` after this stage's update, float64 [G]."""
    elite_detect_rate: np.ndarray
    """Elite rollouts' empirical detection rate per bin of the ``curve_grid`` (nan where empty)."""
    wall_s: float


@dataclass(frozen=True)
class StageFinished:
    """A stage is done; ``result`` what it found."""

    result: StageResult


@dataclass(frozen=True)
class FinalEstimate:
    """The run's answer and what stands beside it; ``n_simulations`` the rollouts simulated in all, ``wall_s`` the
    run's wall time (seconds)."""

    estimate: Estimate
    """The run's answer: the final batch's estimate, or pooled over stages (``final_estimate="pooled"``)."""
    n_simulations: int
    wall_s: float
    stages_used: tuple[int, ...] = ()
    """The stages whose rollouts the estimate uses (e.g. CE stages 4..10 and the final batch 11 when pooled)."""
    log_p_seen: float | None = None
    """log of the probability of the distinct failures the run drew in any stage (nats), a lower bound of p
    (:class:`pemviz.estimators.base.SeenFailures`; None: none, or the scene has measurement errors): a mu_hat below
    it is called unreliable (:meth:`pemviz.core.estimate.Estimate.below_seen`)."""
    pooling: tuple[str, tuple[float, ...]] | None = None
    """How the estimate pools :attr:`stages_used` when the estimator says so itself (final batches added for a
    precision target): (the rule, ``rollouts`` for every rollout alike; lambda_k of each stage, summing to 1), as the
    rollout file's sidecar states it (:func:`pemviz.estimators.pooling.pool`); None: one stage, or the config's rule."""
    stop: str | None = None
    """With a target relative error or a requirement (``ExperimentConfig.rel_error``, ``require``): why the run
    stopped adding rollouts, one line (the target reached, the requirement decided, or which cap); None without one."""
    verdict_cap: tuple[str, str] | None = None
    """The best verdict the sampler lets its estimate claim, whatever the weights show (verdict, reason), or None
    (:attr:`pemviz.estimators.cross_entropy.CrossEntropy.verdict_cap`): the rollout file keeps it for ``pemviz
    estimate``."""
    decision: Decision | None = None
    """With a requirement (``ExperimentConfig.require``): the last look's decision, its outcome ``met``,
    ``violated`` or ``undecided`` (:mod:`pemviz.core.requirement`); None without one."""
    severity: SeverityCurve | None = None
    """The exceedance curve P(failure and min s < x) over the problem's severity levels, from the same rollouts
    (:func:`pemviz.estimators.pooling.severity_curve`); None where the problem has no severity scale or the estimator
    keeps no per-stage rollouts."""
    pem_spread: PemSpread | None = None
    """p under the PEM ensemble's members and the shifted PEMs, re-weighted from the same rollouts
    (:func:`pemviz.estimators.pooling.pem_spread`); None without ``pem_uncertainty`` or ``pem_shift``."""
    failures: FailureShares | None = None
    """The estimate's failing rollouts (stage, rollout number) with the share of mu_hat each carries, largest first
    (:func:`pemviz.estimators.pooling.failure_population`); None where the estimator keeps no per-stage rollouts."""
    look_ahead: bool = False
    """The estimate weighs each rollout up to a state and multiplies by the exact failure probability from it (the
    problem's :attr:`~pemviz.core.problems.Problem.look_ahead`): the rollout file says so, for ``pemviz estimate``."""
    prepared: str | None = None
    """How the estimator's proposal was prepared, one line (the tilt's: solved by this run, or reused from an earlier
    run of the same scene, PEMs and options); None: nothing to say."""
    plain_rollout_s: float | None = None
    """Seconds a plain rollout of the problem (its PEMs alone) takes on this machine, measured after the run by a probe
    of :data:`pemviz.engine.experiment.PLAIN_PROBE` rollouts where the advice sizes plain Monte Carlo (a verdict that
    is not ``reliable``, from another method); None: not probed (the advice then derives it from the run's own speed,
    :func:`pemviz.sinks.console.plain_rollout_seconds`)."""
    odd_map: OddMap | None = None
    """Over an operating design domain: where p_ODD comes from, p(failure | bin) of each drawn parameter's bins from the
    final stage's rollouts (:class:`pemviz.core.odd.OddMap`); None: no ODD."""


@dataclass(frozen=True)
class RunFinished:
    """The run is done: its final estimate and every stage's result, in order."""

    final: FinalEstimate
    stages: tuple[StageResult, ...]


@dataclass(frozen=True)
class RunCancelled:
    """The run stopped before its final estimate (``reason``, one line), with the stages it finished."""

    stages: tuple[StageResult, ...]
    reason: str


Event = (
    RunStarted
    | StageStarted
    | RolloutChunk
    | RolloutsSampled
    | StageFinished
    | FinalEstimate
    | RunFinished
    | RunCancelled
)
Listener = Callable[[Event], None]
