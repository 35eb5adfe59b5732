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
import torch

from pemviz import stl
from pemviz.config import METRICS, ExperimentConfig
from pemviz.detectors import ConstantDetector, Detector, WindowDetector
from pemviz.executors import get_executor
from pemviz.problems import Problem, braking_problem
from pemviz.sampling import (
    Estimate,
    Proposal,
    StateProposal,
    ce_update,
    estimate,
    pretrain_proposal,
    quantile_threshold,
)
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


def _elite_counts(batch: RolloutBatch, elite: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Elite steps per bin of ``grid`` and the detections among them, float64 [G] each."""
    edges = np.concatenate([[-np.inf], (grid[1:] + grid[:-1]) / 2, [np.inf]])
    d = batch.observations[elite][:, :, 0].ravel()
    a = batch.detected[elite].ravel()
    idx = np.digitize(d, edges) - 1
    counts = np.bincount(idx, minlength=grid.size).astype(float)
    hits = np.bincount(idx, weights=a.astype(float), minlength=grid.size)
    return counts, hits


def _rate(counts: np.ndarray, hits: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, hits / np.maximum(counts, 1), np.nan)


def _elite_rate(batch: RolloutBatch, elite: np.ndarray, grid: np.ndarray) -> np.ndarray:
    return _rate(*_elite_counts(batch, elite, grid))


class Experiment:
    """Runs one :class:`ExperimentConfig` on a :class:`Problem` and tells listeners what happens.

    ``problem`` defaults to the braking scenario with the PEM named by ``config.pem`` (the shipped one
    when None).
    """

    def __init__(
        self,
        config: ExperimentConfig,
        listeners: Iterable[Listener] = (),
        cancel: threading.Event | None = None,
        problem: Problem | None = None,
    ) -> None:
        if problem is None:
            from pemviz.pem import load_pem

            problem = braking_problem(load_pem(config.pem), sim=config.sim)
        self.config = config
        self.listeners = list(listeners)
        self.cancel = cancel or threading.Event()
        self.problem = problem
        self.stages: list[StageResult] = []
        self.n_simulations = 0
        self._per_rollout: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        """stage -> (log-weights, failed, log p before the failure), [N] each, for the pooled estimate."""

    # -- plumbing ---------------------------------------------------------------------------------
    def emit(self, event: Event) -> None:
        for listener in self.listeners:
            listener(event)

    def _check_cancel(self) -> None:
        if self.cancel.is_set():
            raise Cancelled("cancelled by the user")

    def _sample(self, stage: int, kind: str, n: int, sampler: Detector, rng: np.random.Generator):
        self._check_cancel()
        self.emit(StageStarted(stage, kind, n))
        executor = get_executor(self.config.executor, self.config.ray_address)  # serial or Ray tasks
        batch = executor.simulate(self.problem, n, sampler, self.problem.target, rng)
        self.n_simulations += n
        by_metric = {m: self.problem.robustness(batch, m) for m in METRICS}
        r = by_metric[self.config.metric]
        failed = by_metric["classic"] < 0.0
        log_w = self._log_weight(batch)
        self.emit(RolloutsSampled(stage, kind, batch, r, by_metric, failed, log_w, sampler))
        return batch, r, failed, log_w

    def _finish_stage(self, stage, kind, gamma, elite, batch, failed, log_w, proposal, t0) -> StageResult:
        log_p_total = self._log_p_total(batch)
        self._per_rollout[stage] = (log_w, failed, log_p_total)
        est = estimate(log_w, failed, log_p_total)
        grid = self.problem.curve_grid
        curve = proposal.curve(grid) if proposal is not None else np.full(grid.size, np.nan)
        res = StageResult(
            stage, kind, gamma, int(elite.sum()), est, curve, _elite_rate(batch, elite, grid), time.perf_counter() - t0
        )
        self.stages.append(res)
        self.emit(StageFinished(res))
        return res

    # -- sampler improvements over the paper (on by default) ------------------------------------------
    def _step_mask(self, batch: RolloutBatch, level: float = 0.0) -> np.ndarray | None:
        """bool [N, T]: the steps whose actions enter the weights and the CE fit, or None for all of them.

        ``weights_until_failure``: the steps before the rollout reaches the stage's level (failure: the first
        step where the operand of the ``G`` safety formula is violated; with the classic metric and a level
        gamma_kappa > 0, the first step where its robustness is <= gamma_kappa: whether a rollout is an
        elite is settled there, later actions are not what made it one); ``proposal_window``: the steps
        inside the problem's window.
        """
        cfg = self.config
        if not (cfg.weights_until_failure or cfg.proposal_window):
            return None
        mask = np.ones(batch.detected.shape, bool)
        if cfg.weights_until_failure:
            level = level if cfg.metric == "classic" else 0.0
            mask &= np.arange(batch.n_steps)[None, :] < failure_steps(self.problem, batch, level)[:, None]
        if cfg.proposal_window:
            mask &= batch.gap_m < self.problem.window
        return mask

    def _log_weight(self, batch: RolloutBatch) -> np.ndarray:
        """Importance log-weights [N] (nats): T - 1 factors, or up to the failure step (``weights_until_failure``;
        the NLL of :meth:`_log_p_total` then covers the same steps)."""
        if not self.config.weights_until_failure:
            return batch.log_weight()
        k = np.minimum(failure_steps(self.problem, batch), batch.n_steps - 1)
        upto = np.arange(batch.n_steps)[None, :] < k[:, None]
        return ((batch.log_p - batch.log_q) * upto).sum(axis=1)

    def _log_p_total(self, batch: RolloutBatch) -> np.ndarray:
        """sum_{t < t_fail} log p_PEM(a_t | s_t) [N] (nats), for the NLL of the failures: the actions before the
        failure step, whatever the sampler, so that NLLs of every preset compare (T - 1 steps for a rollout that
        does not fail, or when the safety formula is not ``G[a,b](state predicate)``)."""
        try:
            k = np.minimum(failure_steps(self.problem, batch), batch.n_steps - 1)
        except ValueError:
            k = np.full(batch.n, batch.n_steps - 1)
        return (batch.log_p * (np.arange(batch.n_steps)[None, :] < k[:, None])).sum(axis=1)

    def _new_proposal(self, pretrain: RolloutBatch) -> Proposal:
        """The paper's gap-only proposal, or a :class:`StateProposal` over every observation column
        (``proposal_inputs = "state"``): the gap scaled by the problem's ``h_scale``, the other columns by their
        largest magnitude in the pretraining rollouts; its curve holds them at the start state."""
        if self.config.proposal_inputs == "gap":
            return Proposal(self.problem.h_scale)
        obs = pretrain.observations
        scales = [self.problem.h_scale] + [float(np.max(np.abs(obs[:, :, j]))) or 1.0 for j in range(1, obs.shape[2])]
        return StateProposal(tuple(range(obs.shape[2])), tuple(scales), tuple(obs[0, 0]))

    # -- the pipeline -----------------------------------------------------------------------------
    def run(self) -> RunFinished | RunCancelled:
        """Run the whole experiment; returns the last event emitted.

        Torch runs on one thread meanwhile: the proposal is tiny, and on 2 cores a second thread only
        adds synchronisation (measured 7.7 ms vs 74 ms per epoch under load).
        """
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return self._run()
        finally:
            torch.set_num_threads(threads)

    def _run(self) -> RunFinished | RunCancelled:
        cfg = self.config
        t_start = time.perf_counter()
        rng = np.random.default_rng(cfg.seed)  # the rollouts' detections; other purposes have their own streams
        pb = self.problem
        self.emit(RunStarted(cfg, str(pb.formula), pb.curve_grid, pb.target_curve(), pb.exact_log_p))
        try:
            if cfg.method == "adaptive":
                final_stage, used = self._adaptive(rng)
            else:
                sampler = {
                    "mc": pb.target,
                    "naive50": ConstantDetector(0.5),
                    "mixed50": WindowDetector(ConstantDetector(0.5), pb.target, pb.window),
                }[cfg.method]
                final_stage, used = self._final(1, sampler, rng, None), (1,)
        except Cancelled as exc:
            event = RunCancelled(tuple(self.stages), str(exc))
            self.emit(event)
            return event
        est = final_stage.estimate
        if len(used) > 1:  # every stage's weights come from the proposal that drew it: the pooled mean is unbiased
            log_w, failed, log_p_total = (np.concatenate(a) for a in zip(*(self._per_rollout[k] for k in used)))
            est = estimate(log_w, failed, log_p_total)
        final = FinalEstimate(est, self.n_simulations, time.perf_counter() - t_start, used)
        self.emit(final)
        done = RunFinished(final, tuple(self.stages))
        self.emit(done)
        return done

    def _final(self, stage: int, sampler: Detector, rng, proposal: Proposal | None) -> StageResult:
        t0 = time.perf_counter()
        n = self.config.n_final if self.config.method == "adaptive" else self.config.n_per_stage
        if n > STREAM_ABOVE and self.problem.stream is not None and self.config.executor == "serial":
            return self._final_streamed(stage, n, sampler, rng, proposal, t0)
        batch, r, failed, log_w = self._sample(stage, "final", n, sampler, rng)
        return self._finish_stage(stage, "final", float("nan"), failed, batch, failed, log_w, proposal, t0)

    def _final_streamed(self, stage, n, sampler, rng, proposal, t0) -> StageResult:
        """The final batch in chunks (``Problem.stream``): memory one chunk plus ~70 bytes a rollout.

        The same rollouts, failures, weights and estimate as :meth:`_sample`; listeners get one
        :class:`RolloutsSampled` for the first chunk only (a sample of the batch, not all n rollouts).
        """
        pb, grid = self.problem, self.problem.curve_grid
        self._check_cancel()
        self.emit(StageStarted(stage, "final", n))
        failed, log_w, log_p_total = [], [], []
        counts, hits = np.zeros(grid.size), np.zeros(grid.size)
        for i, chunk in enumerate(pb.stream(n, sampler, pb.target, rng)):
            self._check_cancel()
            if i == 0:
                by_metric = {m: pb.robustness(chunk, m) for m in METRICS}
                f = by_metric["classic"] < 0.0
                self.emit(RolloutsSampled(stage, "final", chunk, by_metric[self.config.metric], by_metric, f,
                                          self._log_weight(chunk), sampler))  # fmt: skip
            else:
                f = pb.failed(chunk)
            failed.append(f)
            log_w.append(self._log_weight(chunk))
            log_p_total.append(self._log_p_total(chunk))
            c, h = _elite_counts(chunk, f, grid)
            counts, hits = counts + c, hits + h
        self.n_simulations += n
        failed_all = np.concatenate(failed)
        est = estimate(np.concatenate(log_w), failed_all, np.concatenate(log_p_total))
        curve = proposal.curve(grid) if proposal is not None else np.full(grid.size, np.nan)
        self._per_rollout[stage] = (np.concatenate(log_w), failed_all, np.concatenate(log_p_total))
        res = StageResult(stage, "final", float("nan"), int(failed_all.sum()), est, curve, _rate(counts, hits),
                          time.perf_counter() - t0)  # fmt: skip
        self.stages.append(res)
        self.emit(StageFinished(res))
        return res

    def _adaptive(self, rng: np.random.Generator) -> tuple[StageResult, tuple[int, ...]]:
        """Pretraining, K cross-entropy stages and the final batch; returns the last stage and the stages the
        run's estimate uses: with ``final_estimate="pooled"``, every CE stage after the first one that reached
        gamma = 0, and the final batch. The pool's size is fixed by then, before any pooled stage is sampled, and
        each pooled stage is weighted by the proposal that drew it, so the pooled mean of 1[fail] w is unbiased
        (a sum of martingale differences; cf. Cornuet, Marin, Mira, Robert, "Adaptive multiple importance
        sampling", Scand. J. Stat. 2012, for recycling the stages of an adaptive sampler)."""
        cfg = self.config
        pooled: list[int] = []
        reached_failures = False
        t0 = time.perf_counter()
        pre_sampler = self.problem.target
        if cfg.pretrain_cap is not None:  # the first proposal misses at least 1 - cap of the time inside the window
            capped = _CappedDetector(self.problem.target, float(np.log(cfg.pretrain_cap) - np.log1p(-cfg.pretrain_cap)))
            pre_sampler = WindowDetector(capped, self.problem.target, self.problem.window)
        batch, r, failed, log_w = self._sample(0, "pretrain", cfg.pretrain_rollouts, pre_sampler, rng)
        fit_rng = np.random.default_rng((cfg.seed, 1))  # the fits' subsamples; the rollouts' stream stays as it was
        tie_rng = np.random.default_rng((cfg.seed, 2))  # tie-breaking: turning it on leaves the rollouts' stream alone
        with torch.random.fork_rng(devices=[]):  # the proposal's initial weights, without reseeding the process
            torch.manual_seed(cfg.seed)
            proposal = self._new_proposal(batch)
        pretrain_proposal(
            proposal, proposal.features(batch.observations), batch.detected,
            epochs=cfg.pretrain_epochs if cfg.fit == "adam" else cfg.fit_max_steps, lr=cfg.learning_rate,
            check=self._check_cancel, step_mask=self._step_mask(batch) if cfg.proposal_window else None,
            fit=cfg.fit, max_rows=cfg.fit_rows, rng=fit_rng, tolerance=cfg.fit_tolerance,
        )  # fmt: skip
        self._finish_stage(0, "pretrain", float("nan"), np.zeros(batch.n, bool), batch, failed, log_w, proposal, t0)
        sampler: Detector = proposal
        if cfg.defensive > 0.0:  # every outcome keeps at least probability defensive / 2
            sampler = _DefensiveDetector(proposal, float(cfg.defensive))
        if cfg.proposal_window:  # q = p_PEM where the detector cannot matter
            sampler = WindowDetector(sampler, self.problem.target, self.problem.window)
        last = None
        for stage in range(1, cfg.n_stages + 1):
            t0 = time.perf_counter()
            if reached_failures:
                pooled.append(stage)
            batch, r, failed, log_w = self._sample(stage, "ce", cfg.n_per_stage, sampler, rng)
            gamma = quantile_threshold(r, cfg.quantile_level, floor=0.0)
            reached_failures = reached_failures or gamma <= 0.0  # latched: N of the pool is fixed once it starts
            elite = r <= gamma
            if cfg.elite_ties == "random":
                elite = _break_ties(r, gamma, cfg.quantile_level, tie_rng)
            smoothing = cfg.smoothing
            if cfg.smoothing_at_failure is not None and gamma <= 0.0:
                smoothing = cfg.smoothing_at_failure
            self._check_cancel()
            ce_update(
                proposal, proposal.features(batch.observations), batch.detected, batch.log_p, batch.log_q, elite,
                smoothing=smoothing, epochs=cfg.ce_epochs if cfg.fit == "adam" else cfg.fit_max_steps,
                lr=cfg.learning_rate, weights=cfg.weights, check=self._check_cancel,
                step_mask=self._step_mask(batch, gamma), fit=cfg.fit, max_rows=cfg.fit_rows, rng=fit_rng,
                tolerance=cfg.fit_tolerance,
            )  # fmt: skip
            last = self._finish_stage(stage, "ce", gamma, elite, batch, failed, log_w, proposal, t0)
        if cfg.final_estimate == "last-stage":
            return last, (last.stage,)
        final = self._final(cfg.n_stages + 1, sampler, rng, proposal)
        if cfg.final_estimate == "pooled" and reached_failures:
            return final, (*pooled, final.stage)
        return final, (final.stage,)


@dataclass(frozen=True)
class _CappedDetector:
    """``logit min(p_detector, cap)``: the detector, never more sure to detect than the cap (``pretrain_cap``)."""

    detector: Detector
    cap_logit: float

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        return np.minimum(self.detector.detect_logit(obs), self.cap_logit)


@dataclass(frozen=True)
class _DefensiveDetector:
    """The mixture (1 - eps) q + eps * 50 %: detects with (1 - eps) q(detect) + eps / 2 (``defensive``)."""

    detector: Detector
    eps: float

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        logit = np.asarray(self.detector.detect_logit(obs), dtype=np.float64)
        a, half = np.log1p(-self.eps), np.log(self.eps / 2.0)
        log_hit = np.logaddexp(a - np.logaddexp(0.0, -logit), half)
        log_miss = np.logaddexp(a - np.logaddexp(0.0, logit), half)
        return log_hit - log_miss


def _break_ties(robustness: np.ndarray, gamma: float, quantile_level: float, rng: np.random.Generator) -> np.ndarray:
    """bool [N]: every rollout below gamma plus randomly chosen ties at gamma up to ceil((1 - sigma) N) elites.

    At gamma = 0 (the failure threshold) this keeps all failures (r < 0) and admits a non-failing rollout
    with r = 0 only to reach ceil((1 - sigma) N) elites.
    """
    k = max(1, int(np.ceil((1.0 - quantile_level) * robustness.size - 1e-9)))
    below = robustness < gamma
    ties = np.flatnonzero(robustness == gamma)
    elite = below.copy()
    elite[rng.permutation(ties)[: max(0, k - int(below.sum()))]] = True
    return elite


def failure_steps(problem: Problem, batch: RolloutBatch, level: float = 0.0) -> np.ndarray:
    """The step at which each rollout fails, int [N] (T when it does not): :func:`pemviz.stl.first_violation` of
    the problem's safety formula on the batch's signals.

    Raises:
        ValueError: if the formula is not ``G[a,b](operand)`` with a time-free operand (horizon 0).
    """
    return stl.first_violation(problem.formula, problem.signal_arrays(batch), level)


def run_experiment(
    config: ExperimentConfig,
    listeners: Iterable[Listener] = (),
    cancel: threading.Event | None = None,
    problem: Problem | None = None,
) -> RunFinished | RunCancelled:
    """Build an :class:`Experiment` and run it (see the module docstring for the events)."""
    return Experiment(config, listeners, cancel, problem).run()
