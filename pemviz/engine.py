"""The experiment engine: runs the PEM + adaptive-importance-sampling pipeline and emits events.

No printing, no rerun, no viser here: sinks (console table, rerun recording, the viser panel) subscribe
as listeners ``listener(event) -> None`` and never call back into the engine, except through the
``cancel`` token (a :class:`threading.Event`).

Events, in order: :class:`RunStarted`; for each stage (0 = pretraining, 1..K = cross-entropy stages,
K+1 = final batch) :class:`StageStarted`, :class:`RolloutsSampled`, :class:`StageFinished`; then
:class:`FinalEstimate` and :class:`RunFinished` (or :class:`RunCancelled`).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Callable, Iterable, Union

import numpy as np

from pemviz.config import METRICS, ExperimentConfig
from pemviz.detectors import Detector
from pemviz.estimators import Estimator, StagePlan, build_estimator
from pemviz.executors import get_executor
from pemviz.problems import Problem, ProblemInfo
from pemviz.sampling import Estimate
from pemviz.scenarios import RolloutBatch


@dataclass(frozen=True)
class RunStarted:
    config: ExperimentConfig
    formula: str
    curve_grid_m: np.ndarray
    pem_curve: np.ndarray
    """p_PEM(detect | d) on ``curve_grid_m``, float64 [G]."""
    exact_log_p: float | None = None
    """Natural log of the problem's exact failure probability when one is known (closed form, enumeration),
    else None: sinks show it beside every estimate with the relative error."""
    problem: ProblemInfo | None = None
    """What the run estimates: the problem's name, a one-line description and its signals."""


@dataclass(frozen=True)
class StageStarted:
    stage: int
    """0 = pretraining, 1..K = CE stages, K+1 = the final batch (the only stage of mc / naive50)."""
    kind: str
    """``pretrain`` | ``ce`` | ``final``."""
    n_rollouts: int


def stage_label(stage: int, kind: str, n_stages: int) -> str:
    """The one name of a stage in console, panel, recording and CSVs.

    ``pretraining`` (stage 0), ``CE stage k/K`` (stages 1..K, ``n_stages`` = K), ``final batch`` (stage K+1,
    or the only batch of mc / naive50 / mixed50); the number is the engine's ``stage`` everywhere.
    """
    if kind == "pretrain":
        return "pretraining"
    if kind == "ce":
        return f"CE stage {stage}/{n_stages}"
    return "final batch"


@dataclass(frozen=True)
class RolloutsSampled:
    stage: int
    kind: str
    batch: RolloutBatch
    robustness: np.ndarray
    """[N] under the configured metric."""
    robustness_by_metric: dict
    """metric name -> [N] robustness under each semantics of :data:`pemviz.config.METRICS`."""
    failed: np.ndarray
    """bool [N]: crash (classic robustness < 0)."""
    log_weight: np.ndarray
    """[N] importance log-weights (nats), T - 1 factors."""
    sampler: Detector | None = None
    """The detector that drew the batch (the proposal is trained in place afterwards: copy it to keep it)."""


@dataclass(frozen=True)
class StageResult:
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
    result: StageResult


@dataclass(frozen=True)
class FinalEstimate:
    estimate: Estimate
    """The run's answer: the final batch's estimate, or pooled over stages (``final_estimate="pooled"``)."""
    n_simulations: int
    wall_s: float
    stages_used: tuple[int, ...] = ()
    """The stages whose rollouts the estimate uses (e.g. CE stages 4..10 and the final batch 11 when pooled)."""


@dataclass(frozen=True)
class RunFinished:
    final: FinalEstimate
    stages: tuple[StageResult, ...]


@dataclass(frozen=True)
class RunCancelled:
    stages: tuple[StageResult, ...]
    reason: str


Event = Union[RunStarted, StageStarted, RolloutsSampled, StageFinished, FinalEstimate, RunFinished, RunCancelled]
Listener = Callable[[Event], None]


class Cancelled(Exception):
    """Raised inside the engine when the cancel token is set; the run ends with :class:`RunCancelled`."""


STREAM_ABOVE = 100_000
"""Final / baseline batches of more rollouts than this are simulated chunk by chunk when the problem can
stream (``Problem.stream``) and kept only as per-rollout numbers: a [10^6, 100] batch holds 4.1 GB."""


class Experiment:
    """Runs one :class:`ExperimentConfig` on a :class:`Problem` and tells listeners what happens.

    The estimator of ``config.method`` (:func:`pemviz.estimators.build_estimator`) plans the batches and does the
    arithmetic; the experiment simulates them (on ``config.executor``), computes their robustness, emits the
    events and checks the cancel token. ``problem``: what to estimate (e.g. :func:`pemviz.problems.problem_for`
    ``(config)``: the braking scenario with ``config.pem``); the engine itself loads nothing.
    """

    def __init__(
        self,
        config: ExperimentConfig,
        listeners: Iterable[Listener] = (),
        cancel: threading.Event | None = None,
        *,
        problem: Problem,
    ) -> None:
        self.config = config
        self.listeners = list(listeners)
        self.cancel = cancel or threading.Event()
        self.problem = problem
        self.stages: list[StageResult] = []
        self.n_simulations = 0

    def emit(self, event: Event) -> None:
        for listener in self.listeners:
            listener(event)

    def _check_cancel(self) -> None:
        if self.cancel.is_set():
            raise Cancelled("cancelled by the user")

    def run(self) -> RunFinished | RunCancelled:
        """Run the whole experiment; returns the last event emitted (see the module docstring for the events)."""
        cfg, pb = self.config, self.problem
        t_start = time.perf_counter()
        self.emit(RunStarted(cfg, str(pb.formula), pb.curve_grid, pb.target_curve(), pb.exact_log_p, pb.info))
        estimator = build_estimator(cfg, pb, self._check_cancel)  # it seeds its streams, the rollouts' included
        try:
            while (plan := estimator.next_stage()) is not None:
                self._stage(estimator, plan)
        except Cancelled as exc:
            event = RunCancelled(tuple(self.stages), str(exc))
            self.emit(event)
            return event
        est, used = estimator.result()
        final = FinalEstimate(est, self.n_simulations, time.perf_counter() - t_start, used)
        self.emit(final)
        done = RunFinished(final, tuple(self.stages))
        self.emit(done)
        return done

    def _stage(self, estimator: Estimator, plan: StagePlan) -> StageResult:
        """Draw the planned batch, show it to the estimator and the listeners, close the stage."""
        t0 = time.perf_counter()
        self._check_cancel()
        self.emit(StageStarted(plan.stage, plan.kind, plan.n))
        pb, cfg = self.problem, self.config
        if plan.kind == "final" and plan.n > STREAM_ABOVE and pb.stream is not None and cfg.executor == "serial":
            chunks = pb.stream(plan.n, plan.sampler, pb.target, estimator.rng)
        else:  # one batch, on the configured executor (serial or Ray tasks)
            executor = get_executor(cfg.executor, cfg.ray_address)
            chunks = iter([executor.simulate(pb, plan.n, plan.sampler, pb.target, estimator.rng)])
        for i, batch in enumerate(chunks):
            self._check_cancel()
            if i == 0:  # listeners see the first chunk of a streamed batch only (a sample of it, not all n)
                by_metric = {m: pb.robustness(batch, m) for m in METRICS}
                failed = by_metric["classic"] < 0.0
                log_w = estimator.observe(batch, failed, by_metric[cfg.metric])
                self.emit(RolloutsSampled(plan.stage, plan.kind, batch, by_metric[cfg.metric], by_metric, failed,
                                          log_w, plan.sampler))  # fmt: skip
            else:
                estimator.observe(batch, pb.failed(batch), None)
        self.n_simulations += plan.n
        out = estimator.finish()
        res = StageResult(plan.stage, plan.kind, out.gamma, out.n_elites, out.estimate, out.proposal_curve,
                          out.elite_detect_rate, time.perf_counter() - t0)  # fmt: skip
        self.stages.append(res)
        self.emit(StageFinished(res))
        return res
