"""Cross-entropy adaptive importance sampling of detector outputs (Innes & Ramamoorthy 2022, Algorithm 1), with
pemviz's improvements over the paper (each switched by a field of :class:`~pemviz.config.ExperimentConfig`).

Stage 0 pretrains the proposal on rollouts of the target detector (the PEM); each CE stage draws N rollouts from
the proposal, takes the elites (robustness <= gamma_kappa, the (1 - sigma) quantile, floored at the failure level
0) and refits the proposal to them with importance weights raised to the power alpha (:func:`pemviz.sampling.
ce_update`); a final batch of N_e rollouts from the last proposal gives the estimate, alone or pooled with the CE
stages drawn from proposals fitted to failures.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.special import log_expit

from pemviz.config import ExperimentConfig
from pemviz.detectors import Detector, WindowDetector, logit
from pemviz.estimators.base import (
    Check,
    StageOutcome,
    StagePlan,
    StageRollouts,
    detect_rate,
    elite_counts,
    failure_steps,
    pooled_estimate,
)
from pemviz.problems import Problem
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
class CappedDetector:
    """``logit min(p_detector, cap)``: the detector, never more sure to detect than the cap (``pretrain_cap``)."""

    detector: Detector
    cap_logit: float

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        return np.minimum(self.detector.detect_logit(obs), self.cap_logit)


@dataclass(frozen=True)
class DefensiveDetector:
    """The defensive mixture (1 - eps) q + eps * 50 % (Hesterberg, "Weighted average importance sampling and
    defensive mixture distributions", Technometrics 1995): detects with (1 - eps) q(detect) + eps / 2, so both
    outcomes keep probability >= eps / 2 at every step (``defensive``)."""

    detector: Detector
    eps: float

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """log p_mix(detect) - log p_mix(miss), float64 [N], in log space throughout."""
        q_logit = np.asarray(self.detector.detect_logit(obs), dtype=np.float64)
        a, half = np.log1p(-self.eps), np.log(self.eps / 2.0)
        return np.logaddexp(a + log_expit(q_logit), half) - np.logaddexp(a + log_expit(-q_logit), half)


def break_ties(robustness: np.ndarray, gamma: float, quantile_level: float, rng: np.random.Generator) -> np.ndarray:
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


class CrossEntropy:
    """Algorithm 1 of Innes & Ramamoorthy (2022) as configured by ``config`` (``method = "adaptive"``).

    Stages: 0 pretraining (``pretrain_rollouts``), 1..K cross-entropy (``n_per_stage`` each), K+1 the final batch
    (``n_final``; none with ``final_estimate = "last-stage"``).

    Random streams, one per purpose, all from ``config.seed``: the engine's rollouts; the fits' subsamples
    (``(seed, 1)``); tie-breaking (``(seed, 2)``); the proposal's initial weights (torch, seeded in a fork of the
    process's generator), so turning one option on leaves the other streams as they were.

    Args:
        config: the sampler's settings.
        problem: what to estimate.
        check: called between and inside fits; may raise to abandon the run.
    """

    def __init__(self, config: ExperimentConfig, problem: Problem, check: Check | None = None) -> None:
        self.config, self.problem = config, problem
        self.check: Check = check or (lambda: None)
        self.fit_rng = np.random.default_rng((config.seed, 1))
        self.tie_rng = np.random.default_rng((config.seed, 2))
        self.proposal: Proposal | None = None
        self.sampler: Detector | None = None
        self.stages: dict[int, StageRollouts] = {}
        self.pooled: list[int] = []
        """CE stages drawn after one reached gamma = 0 (their proposals were fitted to failures)."""
        self.reached_failures = False
        self._plan: StagePlan | None = None
        self._batch: tuple[RolloutBatch, np.ndarray] | None = None
        self._last: tuple[int, Estimate] | None = None

    # -- the interface --------------------------------------------------------------------------------------------
    def next_stage(self) -> StagePlan | None:
        cfg, k = self.config, (-1 if self._plan is None else self._plan.stage) + 1
        if k == 0:
            plan = StagePlan(0, "pretrain", cfg.pretrain_rollouts, self._pretrain_sampler())
        elif k <= cfg.n_stages:
            if self.reached_failures:
                self.pooled.append(k)
            plan = StagePlan(k, "ce", cfg.n_per_stage, self.sampler)
        elif k == cfg.n_stages + 1 and cfg.final_estimate != "last-stage":
            plan = StagePlan(k, "final", cfg.n_final, self.sampler)
        else:
            return None
        self._plan = plan
        self.stages[k] = StageRollouts(self.problem.curve_grid)
        return plan

    def observe(self, batch: RolloutBatch, failed: np.ndarray, robustness: np.ndarray | None) -> np.ndarray:
        plan = self._plan
        if plan.kind != "final":
            self._batch = (batch, robustness)
        return self.stages[plan.stage].add(self.problem, batch, failed, self.config.weights_until_failure,
                                           count_failures=plan.kind == "final")  # fmt: skip

    def finish(self) -> StageOutcome:
        plan, grid = self._plan, self.problem.curve_grid
        if plan.kind == "final":
            outcome = self.stages[plan.stage].failures_outcome(self.proposal.curve(grid))
        else:
            batch, r = self._batch
            self._batch = None
            if plan.kind == "pretrain":
                gamma, elite = float("nan"), np.zeros(batch.n, bool)
                self._pretrain(batch)
            else:
                gamma, elite = self._ce_stage(batch, r)
            log_w, failed, log_p = self.stages[plan.stage].arrays()
            outcome = StageOutcome(gamma, int(elite.sum()), estimate(log_w, failed, log_p), self.proposal.curve(grid),
                                   detect_rate(*elite_counts(batch, elite, grid)))  # fmt: skip
        self._last = (plan.stage, outcome.estimate)
        return outcome

    def result(self) -> tuple[Estimate, tuple[int, ...]]:
        """The last stage's estimate, or with ``final_estimate = "pooled"`` (once a CE stage reached gamma = 0) the
        estimate over every CE stage after it and the final batch.

        The pool's size is fixed by then, before any pooled stage is sampled, and each pooled stage is weighted by
        the proposal that drew it, so the pooled mean of 1[fail] w is unbiased (a sum of martingale differences;
        cf. Cornuet, Marin, Mira, Robert, "Adaptive multiple importance sampling", Scand. J. Stat. 2012, for
        recycling the stages of an adaptive sampler).
        """
        stage, est = self._last
        if self.config.final_estimate == "pooled" and self.reached_failures and self.pooled:
            used = (*self.pooled, stage)
            return pooled_estimate([self.stages[k] for k in used]), used
        return est, (stage,)

    # -- the algorithm --------------------------------------------------------------------------------------------
    def _pretrain_sampler(self) -> Detector:
        """The target, or with ``pretrain_cap`` c the target capped at c inside the problem's window, so that the
        first proposal misses at least 1 - c of the time there."""
        pb, cap = self.problem, self.config.pretrain_cap
        if cap is None:
            return pb.target
        return WindowDetector(CappedDetector(pb.target, logit(cap)), pb.target, pb.window)

    def _pretrain(self, batch: RolloutBatch) -> None:
        """A new proposal fitted to the pretraining rollouts' actions; the CE stages' sampler around it."""
        cfg, pb = self.config, self.problem
        with torch.random.fork_rng(devices=[]):  # the proposal's initial weights, without reseeding the process
            torch.manual_seed(cfg.seed)
            self.proposal = proposal = self._new_proposal(batch)
        pretrain_proposal(
            proposal, proposal.features(batch.observations), batch.detected,
            epochs=cfg.pretrain_epochs if cfg.fit == "adam" else cfg.fit_max_steps, lr=cfg.learning_rate,
            check=self.check, step_mask=self.step_mask(batch) if cfg.proposal_window else None,
            fit=cfg.fit, max_rows=cfg.fit_rows, rng=self.fit_rng, tolerance=cfg.fit_tolerance,
        )  # fmt: skip
        sampler: Detector = proposal
        if cfg.defensive > 0.0:  # every outcome keeps at least probability defensive / 2
            sampler = DefensiveDetector(proposal, float(cfg.defensive))
        if cfg.proposal_window:  # q = p_target where the detector cannot matter
            sampler = WindowDetector(sampler, pb.target, pb.window)
        self.sampler = sampler

    def _ce_stage(self, batch: RolloutBatch, robustness: np.ndarray) -> tuple[float, np.ndarray]:
        """gamma_kappa, the elites, and the proposal refitted to them (in place); returns (gamma, elite [N])."""
        cfg, proposal = self.config, self.proposal
        gamma = quantile_threshold(robustness, cfg.quantile_level, floor=0.0)
        self.reached_failures = self.reached_failures or gamma <= 0.0  # latched: the pool's N is fixed once it starts
        elite = robustness <= gamma
        if cfg.elite_ties == "random":
            elite = break_ties(robustness, gamma, cfg.quantile_level, self.tie_rng)
        smoothing = cfg.smoothing
        if cfg.smoothing_at_failure is not None and gamma <= 0.0:
            smoothing = cfg.smoothing_at_failure
        self.check()
        ce_update(
            proposal, proposal.features(batch.observations), batch.detected, batch.log_p, batch.log_q, elite,
            smoothing=smoothing, epochs=cfg.ce_epochs if cfg.fit == "adam" else cfg.fit_max_steps,
            lr=cfg.learning_rate, weights=cfg.weights, check=self.check, step_mask=self.step_mask(batch, gamma),
            fit=cfg.fit, max_rows=cfg.fit_rows, rng=self.fit_rng, tolerance=cfg.fit_tolerance,
        )  # fmt: skip
        return gamma, elite

    def step_mask(self, batch: RolloutBatch, level: float = 0.0) -> np.ndarray | None:
        """bool [N, T]: the steps whose actions enter the CE fit, or None for all of them.

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

    def _new_proposal(self, pretrain: RolloutBatch) -> Proposal:
        """The paper's gap-only proposal, or a :class:`StateProposal` over every observation column
        (``proposal_inputs = "state"``): the gap scaled by the problem's ``h_scale``, the other columns by their
        largest magnitude in the pretraining rollouts; its curve holds them at the start state."""
        if self.config.proposal_inputs == "gap":
            return Proposal(self.problem.h_scale)
        obs = pretrain.observations
        scales = [self.problem.h_scale] + [float(np.max(np.abs(obs[:, :, j]))) or 1.0 for j in range(1, obs.shape[2])]
        return StateProposal(tuple(range(obs.shape[2])), tuple(scales), tuple(obs[0, 0]))
