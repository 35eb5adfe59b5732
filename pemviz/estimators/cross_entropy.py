"""Cross-entropy adaptive importance sampling of detector outputs (Innes & Ramamoorthy 2022, Algorithm 1), with
pemviz's improvements over the paper (each switched by a field of :class:`~pemviz.config.ExperimentConfig`).

Stage 0 pretrains the proposal on rollouts of the target detector (the PEM); each CE stage draws N rollouts from
the proposal, takes the elites (robustness <= gamma_kappa, the (1 - sigma) quantile, floored at the failure level
0) and refits the proposal to them with importance weights raised to the power alpha (:func:`ce_update`); a
final batch of N_e rollouts from the last proposal gives the estimate, alone or pooled with the CE stages drawn
from proposals fitted to failures. The whole stage lives here: elites, weights (a mixture's in
:mod:`pemviz.estimators.ce_mixture`), step masks, the fit's data and loss (:mod:`pemviz.estimators.ce_fit`; the
optimiser and the proposal networks are in :mod:`pemviz.core.sampling`)."""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass
from typing import cast

import numpy as np

from pemviz.config import ExperimentConfig
from pemviz.core.detector_noise import noise_names_of
from pemviz.core.detectors import (
    Detector,
    NoisyDetector,
    StageSamplers,
    WindowDetector,
    defensive_logit,
    logit,
)
from pemviz.core.estimate import Estimate, estimate
from pemviz.core.fit_settings import EXACT, FitOptions
from pemviz.core.plan import RunPlan
from pemviz.core.problems import Problem
from pemviz.core.rollouts import RolloutBatch
from pemviz.core.sampling import Proposal
from pemviz.core.scored_target import ScoredTarget
from pemviz.estimators.base import (
    Check,
    EliteCandidates,
    OwnsSettings,
    StageOutcome,
    StagePlan,
    StageRollouts,
    detect_rate,
    elite_counts,
    failure_steps,
    masked_log_weight,
    pooled_estimate,
    weighted_steps_mask,
)
from pemviz.estimators.ce_fit import EliteSteps, WeightMode, break_ties, ce_update, new_proposal, pretrain_proposal
from pemviz.estimators.ce_mixture import MixtureWeights
from pemviz.estimators.ce_odd import ParameterFit
from pemviz.estimators.ce_plan import adaptive_run_plan
from pemviz.estimators.pooling import pool_stage_weights
from pemviz.methods import CROSS_ENTROPY_METHOD
from pemviz.settings import settings_of


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
        """log p_mix(detect) - log p_mix(miss), float64 [N], in log space throughout (:func:`defensive_logit`)."""
        return defensive_logit(self.detector.detect_logit(obs), self.eps)


class CrossEntropy(OwnsSettings, MixtureWeights):
    """Algorithm 1 of Innes & Ramamoorthy (2022) as configured by ``config`` (``method = "adaptive"``).

    Stages: 0 pretraining (``pretrain_rollouts``), 1..K cross-entropy (``n_per_stage`` each), K+1 the final batch
    (``n_final``; none with ``final_estimate = "last-stage"``).

    Random streams, one per purpose, all from ``config.seed``: the rollouts' detections (:attr:`rng`, which the
    engine draws from); the fits' subsamples
    (``(seed, 1)``); tie-breaking (``(seed, 2)``); the proposal's initial weights (numpy's generator seeded
    with ``seed``, :meth:`pemviz.core.sampling.Proposal.initialise`), so turning one option on leaves the other
    streams as they were.

    Args:
        config: the sampler's settings.
        problem: what to estimate.
        check: called between and inside fits; may raise to abandon the run."""

    SETTINGS = settings_of(CROSS_ENTROPY_METHOD)
    fits_errors = True
    """Whether the proposal draws a noisy target's measurement errors from a model of its own (else the target's)."""

    def __init__(self, config: ExperimentConfig, problem: Problem, check: Check | None = None) -> None:
        self.config, self.problem = config, problem
        self.ce = config.adaptive
        """The sampler's own settings (:class:`pemviz.methods.adaptive.CrossEntropySettings`)."""
        self.check: Check = check or (lambda: None)
        self.rng = np.random.default_rng(config.seed)
        self.fit_rng = np.random.default_rng((config.seed, 1))
        self.tie_rng = np.random.default_rng((config.seed, 2))
        self.proposal: Proposal | None = None
        self.sampler: Detector | None = None
        """The CE stages' sampler: the proposal, with the per-step defensive mixture (``defensive``) and the window."""
        self.plain_sampler: Detector | None = None
        """The proposal with the window only (a share ``plain_share`` of a stage's rollouts once the failure level is
        reached)."""
        self.stages: dict[int, StageRollouts] = {}
        self.pooled: list[int] = []
        """CE stages drawn after one reached gamma = 0 (their proposals were fitted to failures)."""
        self.reached_failures = False
        self._plan: StagePlan | None = None
        self._chunks: list[RolloutBatch] = []
        """The pretraining batch's chunks."""
        self._elites: EliteCandidates | None = None
        """A CE stage's rollouts that can still be elites."""
        self._failure_steps: EliteSteps | None = None
        """With ``fit_all_failures``: the fitted steps of every failure of the CE stages since the failure level."""
        self._index_offset = 0
        """Rollouts of the CE stages already in :attr:`_failure_steps` (the order of their steps)."""
        self._pool_start: int | None = None
        """The stage whose threshold first reached the failure level (its failures start :attr:`_failure_steps`)."""
        self._stage_samplers: dict[int, tuple[tuple[int, Detector], ...]] = {}
        """With ``fit_weights = "mixture"``: each CE stage's samplers as (rollouts, detector) with a frozen copy of
        the proposal that drew them."""
        self._pool_log_q: dict[object, np.ndarray] = {}
        """With ``fit_weights = "mixture"``: log p and each stage sampler's log q of every rollout in the failure pool
        (over the steps that count; nan: not computed yet), by rollout."""
        self._steps: EliteSteps | None = None
        """A CE stage's settled elites as fitted steps (frozen weights with a step mask; else the elites are fitted
        from their rollouts by :func:`ce_update`)."""
        self._last: tuple[int, Estimate] | None = None
        self._added: list[int] = []
        """Final batches added after the first (:meth:`extend`), by stage."""
        self._pooling: tuple[str, tuple[float, ...]] | None = None
        self._noise_data: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        """The stage's elites' detected objects: (rows [S, G], errors [S, D], alpha log w [S]) for the error head's
        fit."""
        self._samplers: StageSamplers | None = None
        """The proposal's samplers and the target, evaluated together once per step (:class:`StageSamplers`)."""
        self._seen = 0
        """Rollouts of the planned stage observed so far."""
        self._scored: ScoredTarget | None = None
        """The planned mixture stage's target, keeping its proposal components' logits while the rollouts are drawn."""
        self.tolerance = self.ce.fit_tolerance if self.ce.fit == "adam" else None
        """Early stopping of the CE stages' Adam fits (L-BFGS stops at its own tolerance)."""
        self.fit_dtype = self.ce.fit_precision if self.ce.fit_precision in ("float32", "float64") else EXACT
        """The arithmetic of the Adam fits (``fit_precision``)."""
        self.whole_rollouts = self.ce.fits_whole_rollouts(config.weights_until_failure)
        """The first CE stage fits whole elite rollouts, one object a step (the ``paper`` preset)."""
        self._parameters = ParameterFit(problem)
        """Over an ODD: the proposal the CE stages draw the parameters from, fitted to the elites (:mod:`.ce_odd`)."""
        if problem.n_objects != 1 and self.whole_rollouts:  # refused before any rollout, not after pretraining
            raise ValueError(self.ce.whole_rollouts_refusal(problem.n_objects))

    # -- the interface --------------------------------------------------------------------------------------------
    @staticmethod
    def run_plan(config: ExperimentConfig) -> RunPlan:
        """Stage 0 pretraining, 1..K cross-entropy stages, K+1 the final batch (none with ``last-stage``):
        :func:`pemviz.estimators.ce_plan.adaptive_run_plan`."""
        return adaptive_run_plan(config)

    def plan(self) -> RunPlan:
        return self.run_plan(self.config)

    def next_stage(self) -> StagePlan | None:
        cfg, k = self.config, (-1 if self._plan is None else self._plan.stage) + 1
        if k == 0:
            plan = StagePlan(0, "pretrain", self.ce.pretrain_rollouts, self._pretrain_sampler())
        elif k <= self.ce.n_stages:
            assert self.sampler is not None, "the CE stages' sampler comes with the pretraining fit"
            if self.reached_failures:
                self.pooled.append(k)
            plan = StagePlan(k, "ce", cfg.n_per_stage, self.sampler, mixture=self._mixture(cfg.n_per_stage))
            if self.ce.fit_weights == "mixture":
                self._stage_samplers[k] = self._frozen_samplers(plan)
            self._elites = EliteCandidates(plan.n, self.ce.quantile_level, floor=0.0)
            if self._failure_steps is not None:  # every failure since the failure level was reached
                self._steps = self._failure_steps
            elif not self.whole_rollouts:
                self._steps = EliteSteps(
                    self.problem.curve_grid,
                    self.ce.fit_rows,
                    self.fit_rng,
                    keep_observations=self.ce.fit_weights == "mixture",
                )
        elif k == self.ce.n_stages + 1 and self.ce.has_final_batch:
            assert self.sampler is not None, "the final batch's sampler comes with the pretraining fit"
            plan = StagePlan(k, "final", self.ce.n_final, self.sampler, mixture=self._mixture(self.ce.n_final))
        else:
            return None
        return self._open(plan)

    def extend(self, n: int) -> StagePlan:
        """``n`` more rollouts from the final batch's sampler and mixture (the proposal is not refitted), as the next
        stage; :meth:`result` pools them with the final batch, every final rollout alike.

        Raises:
            RuntimeError: before the final batch, or with ``final_estimate = "last-stage"`` (no final batch)."""
        final = self.ce.n_stages + 1
        if self._plan is None or self._plan.stage < final or final not in self.stages:
            raise RuntimeError("CrossEntropy.extend: the final batch has not been drawn")
        assert self.sampler is not None  # fitted before the final batch
        self._added.append(self._plan.stage + 1)
        return self._open(StagePlan(self._plan.stage + 1, "final", int(n), self.sampler, mixture=self._mixture(int(n))))

    def final_rollouts(self) -> int:
        """The final batch's rollouts and the added ones (:meth:`extend`)."""
        return sum(self.stages[k].n for k in (self.ce.n_stages + 1, *self._added) if k in self.stages)

    def simulations_counted(self) -> int | None:
        """None: the rollouts planned are the simulations (:class:`pemviz.estimators.precision.Extensible`)."""
        return None

    def _open(self, plan: StagePlan) -> StagePlan:
        """Make ``plan`` the stage being drawn: its mixture's scoring target, its per-rollout numbers."""
        k = plan.stage
        if self._samplers is not None:
            self._samplers.forget()  # the proposal was fitted since it last answered
        self._scored, self._seen = None, 0
        if plan.mixture:
            assert self._samplers is not None, "a mixture stage comes after the pretraining fit"
            extras = tuple(dict.fromkeys(d for _, d in plan.mixture if d is not self.problem.target))
            self._scored = ScoredTarget(self._samplers.target, extras)
            plan = dataclasses.replace(plan, target=self._scored)
        self._plan = plan
        self.stages[k] = StageRollouts(self.problem.curve_grid)
        return plan

    def _mixture(self, n: int) -> tuple[tuple[int, Detector], ...]:
        """The mixture over whole rollouts of a CE or final stage of ``n`` (:attr:`StagePlan.mixture`):
        round(``target_share`` n) rollouts from the target, round(``plain_share`` n) from the proposal without the
        per-step defensive mixture, the rest from :attr:`sampler`; none with both shares 0."""
        if self.ce.target_share + self.ce.plain_share == 0.0:
            return ()
        assert self.plain_sampler is not None and self.sampler is not None, "set by the pretraining fit"
        # before the failure level the target's rollouts would not reach the stage's level: none are drawn
        n_p = int(round(self.ce.target_share * n)) if self.reached_failures else 0
        n_q = int(round(self.ce.plain_share * n))
        n_q = min(n_q, n - n_p)
        return ((n_p, self.problem.target), (n_q, self.plain_sampler), (n - n_p - n_q, self.sampler))

    def observe(self, batch: RolloutBatch, failed: np.ndarray, robustness: np.ndarray | None) -> np.ndarray:
        plan = self._plan
        assert plan is not None, "observe() before a stage was planned"
        if plan.mixture:
            batch = self._with_parts(batch)
        if plan.kind == "pretrain":
            self._chunks.append(batch)
        elif plan.kind == "ce":
            assert self._elites is not None and robustness is not None, "a CE stage ranks its rollouts"
            self._elites.add(batch, robustness)
            if self._steps is not None:  # failures of a stage at the failure level: only their fitted steps are kept
                settled, index = self._elites.settle()
                if settled is not None:
                    self._add_steps(settled, index, self._elites.floor)
        until = self.config.weights_until_failure
        weigh = (lambda mask, rows=None: self._mixture_log_weight(batch, mask, rows)) if plan.mixture else None
        log_w = weigh(weighted_steps_mask(self.problem, batch, until)) if weigh is not None else None
        return self.stages[plan.stage].add(
            self.problem, batch, failed, until, count_failures=plan.kind == "final", log_w=log_w, weigh=weigh
        )

    def finish(self) -> StageOutcome:
        plan, grid = self._plan, self.problem.curve_grid
        assert plan is not None, "finish() before a stage was planned"
        if plan.kind == "final":
            assert self.proposal is not None  # fitted before the final batch
            outcome = self.stages[plan.stage].failures_outcome(self.proposal.curve(grid))
        else:
            if plan.kind == "pretrain":
                batch = RolloutBatch.concatenate(self._chunks) if len(self._chunks) > 1 else self._chunks[0]
                self._chunks = []
                gamma, n_elites, rate = (
                    float("nan"),
                    0,
                    detect_rate(*elite_counts(batch, np.zeros(batch.n, bool), grid)),
                )
                self._pretrain(batch)
            else:
                assert self._elites is not None  # opened with the CE stage (next_stage)
                kept, r, index = self._elites.candidates()
                gamma, n_elites, rate = self._ce_stage(kept, r, index, self._elites.gamma(), plan.n)
                if self.ce.fit_all_failures and gamma <= 0.0 and self._steps is not None:
                    self._failure_steps = self._steps
                    self._index_offset += plan.n
                    self._pool_start = plan.stage if self._pool_start is None else self._pool_start
                self._elites = self._steps = None
            log_w, failed, log_p = self.stages[plan.stage].arrays()
            assert self.proposal is not None  # fitted by the pretraining stage
            outcome = StageOutcome(gamma, n_elites, estimate(log_w, failed, log_p), self.proposal.curve(grid), rate)
        if self.problem.verdict_cap is not None:  # each stage's row too: its weights miss what the final one's do
            outcome = dataclasses.replace(outcome, estimate=outcome.estimate.at_most(self.problem.verdict_cap))
        self._last = (plan.stage, outcome.estimate)
        return outcome

    def result(self) -> tuple[Estimate, tuple[int, ...]]:
        """The last stage's estimate, or with ``final_estimate = "pooled"`` (once a CE stage reached gamma = 0) the
        estimate over every CE stage after it and the final batch.

        The pool's size is fixed by then, before any pooled stage is sampled, and each pooled stage is weighted by
        the proposal that drew it, so the pooled mean of 1[fail] w is unbiased (a sum of martingale differences;
        cf. Cornuet, Marin, Mira, Robert, "Adaptive multiple importance sampling", Scand. J. Stat. 2012, for
        recycling the stages of an adaptive sampler). With ``pool_weights = "linear"`` the j-th pooled stage
        (j = 1..K) counts lambda_j = j n_j / sum_i i n_i, with ``quadratic`` (the default) j^2 n_j / sum_i i^2 n_i:
        fixed as soon as the pool starts too, so still unbiased, and later proposals, fitted to more failures, count
        more (weighting the stages of adaptive importance sampling: Portier & Delyon, "Asymptotic optimality of
        adaptive importance sampling", NeurIPS 2018)."""
        est, used = self._result()
        return est.at_most(self.verdict_cap), used

    @property
    def verdict_cap(self) -> tuple[str, str] | None:
        """(verdict, reason): the best verdict this sampler's estimate can claim, whatever its weights show, or None.

        ``doubtful`` when no stage's threshold reached the failure level (a proposal never fitted to a failure), and
        when the first fit takes whole elite rollouts (:attr:`whole_rollouts`, the paper's own fit): such a proposal can
        settle on one failure mode and miss others, which no diagnostic of its weights can see (the user guide's
        Validation page: "reliable" with the exact answer far outside the interval in 1 of 200 seeds of the ``paper``
        preset and 1 of 10 of ``authors-code`` at N = 100); else the problem's own cap
        (:attr:`pemviz.core.problems.Problem.verdict_cap`)."""
        if not self.reached_failures:
            return "doubtful", (
                "no stage's threshold reached the failure level: the proposal was never fitted to a " "failure"
            )
        if self.whole_rollouts:
            return "doubtful", (
                "the paper's fit of whole elite rollouts can settle on one failure mode and miss "
                "others its weights cannot show (the Validation page); use the default sampler"
            )
        return self.problem.verdict_cap  # what the scenario knows its proposal misses (Problem.verdict_cap)

    def _result(self) -> tuple[Estimate, tuple[int, ...]]:
        assert self._last is not None, "result() before a stage was finished"
        stage, est = self._last
        finals = [k for k in (self.ce.n_stages + 1, *self._added) if k in self.stages]
        pooled = self.ce.final_estimate == "pooled" and self.reached_failures and self.pooled
        if not pooled and len(finals) <= 1:
            self._pooling = None
            return est, (stage,)
        front = list(self.pooled) if pooled else []
        sizes = [self.stages[k].n for k in front] + [sum(self.stages[k].n for k in finals)]
        rule = pool_stage_weights(self.ce.pool_weights, sizes) if pooled else None  # None: every rollout alike
        lam = np.asarray(sizes, dtype=np.float64) / sum(sizes) if rule is None else rule
        # the final batches share the final's lambda, every final rollout alike
        share = np.array([self.stages[k].n for k in finals], dtype=np.float64) / sizes[-1]
        weights = np.concatenate([lam[:-1], lam[-1] * share])
        used = (*front, *finals)
        self._pooling = (
            "rollouts" if rule is None else self.ce.pool_weights,
            tuple(float(x) for x in weights),
        )
        return pooled_estimate([self.stages[k] for k in used], None if rule is None else weights), used

    def pooling(self) -> tuple[str, tuple[float, ...]] | None:
        """How :meth:`result` pooled the stages it used: (the rule, ``rollouts`` for every rollout alike; lambda_k of
        each), or None: one stage alone."""
        return self._pooling

    # -- the algorithm --------------------------------------------------------------------------------------------
    def _pretrain_sampler(self) -> Detector:
        """The target, or with ``pretrain_cap`` c the target capped at c inside the problem's window, so that the
        first proposal misses at least 1 - c of the time there."""
        pb, cap = self.problem, self.ce.pretrain_cap
        if cap is None:
            return pb.target
        return WindowDetector(CappedDetector(pb.target, logit(cap)), pb.target, pb.window)

    def _pretrain(self, batch: RolloutBatch) -> None:
        """A new proposal fitted to the pretraining rollouts' actions; the CE stages' sampler around it."""
        cfg = self.config
        self.proposal = proposal = self._new_proposal(batch)
        proposal.initialise(np.random.default_rng(cfg.seed))  # the initial weights: the same on every CPU
        if noise_names_of(self.problem.target) and self.fits_errors:  # errors by a model of its own, p's until fitted
            proposal.add_noise_head(len(noise_names_of(self.problem.target)))
        features, detected, mask = self._fit_events(batch, self.step_mask(batch) if self.ce.proposal_window else None)
        pretrain_proposal(proposal, features, detected, self._fit_options(self.ce.pretrain_epochs), mask)
        self._samplers, self.plain_sampler, self.sampler = self._samplers_around(proposal)
        own = self._own_samplers()
        if own is not None:  # over an ODD the samplers (not the target) draw theta from q(theta)
            own.parameter_proposal = self._parameters.proposal

    def _new_proposal(self, batch: RolloutBatch) -> Proposal:
        """The first proposal, before its pretraining fit on ``batch``: :func:`new_proposal` of ``proposal_inputs``."""
        return new_proposal(self.ce.proposal_inputs, self.problem.h_scale, batch)

    def _fit_options(self, adam_epochs: int) -> FitOptions:
        """The proposal's fits' settings: ``adam_epochs`` Adam epochs, or ``fit_max_steps`` L-BFGS iterations."""
        ce = self.ce
        epochs = adam_epochs if ce.fit == "adam" else ce.fit_max_steps
        return FitOptions(
            epochs, ce.learning_rate, self.check, ce.fit, ce.fit_rows, self.fit_rng, self.tolerance, self.fit_dtype
        )

    def _own_samplers(self) -> StageSamplers | None:
        """The samplers that draw an ODD's parameters from q(theta): the window's (not the proposal itself)."""
        return self._samplers if self.ce.proposal_window else None

    def _samplers_around(self, proposal: Proposal) -> tuple[StageSamplers, Detector, Detector]:
        """(the CE stages' samplers around a proposal, the plain sampler, the defensive one): q inside the problem's
        window and above the gap where the outcome is decided (``proposal_window``, ``skip_decided``; q = p_target
        where the detector cannot matter), plain and with the per-step defensive mixture (``defensive``), evaluated
        together once per step (:class:`StageSamplers`). Without a window or a defensive share the proposal itself
        draws (the paper)."""
        pb = self.problem
        eps = float(self.ce.defensive)
        if not self.ce.proposal_window:  # the proposal everywhere
            samplers = StageSamplers(proposal, pb.target, eps=eps)
            return samplers, proposal, proposal if eps == 0.0 else samplers.defensive
        floor = pb.decided_below if self.ce.skip_decided else -math.inf  # below it the outcome is decided
        samplers = StageSamplers(proposal, pb.target, pb.window, floor, eps)
        return samplers, samplers.plain, samplers.defensive

    def _around(
        self, mixture: tuple[tuple[int, Detector], ...], proposal: Proposal
    ) -> tuple[tuple[int, Detector], ...]:
        """A stage's (rollouts, sampler) components with the proposal's samplers rebuilt around ``proposal`` (the
        target stays)."""
        _, plain, sampler = self._samplers_around(proposal)
        rebuilt = {id(self.plain_sampler): plain, id(self.sampler): sampler}
        return tuple((n, rebuilt.get(id(d), d)) for n, d in mixture)

    def _frozen_samplers(self, plan: StagePlan) -> tuple[tuple[int, Detector], ...]:
        """A CE stage's samplers, (rollouts, detector) each, around a copy of the current proposal (later fits
        change the proposal in place)."""
        assert self.sampler is not None and self.proposal is not None, "set by the pretraining fit"
        return self._around(plan.mixture or ((plan.n, self.sampler),), copy.deepcopy(self.proposal))

    def _smoothing(self, gamma: float) -> float:
        """alpha of a stage at threshold gamma: ``smoothing_at_failure`` once gamma reached the failure level, and
        ``final_smoothing`` (when set) in the last stage, whose fit gives the final proposal."""
        if gamma > 0.0:
            return self.ce.smoothing
        if self.ce.final_smoothing is not None and self._plan is not None and self._plan.stage >= self.ce.n_stages:
            return self.ce.final_smoothing
        return self.ce.smoothing if self.ce.smoothing_at_failure is None else self.ce.smoothing_at_failure

    def _add_steps(self, batch: RolloutBatch, index: np.ndarray, gamma: float) -> None:
        """Reduce elite rollouts to their fitted object events (:class:`EliteSteps`): inputs, actions, alpha log w_i."""
        plan, elite_steps, proposal = self._plan, self._steps, self.proposal
        assert plan is not None and elite_steps is not None and proposal is not None, "a CE stage gathers its steps"
        mask = self.step_mask(batch, gamma)  # [N, T, M]
        assert mask is not None  # fitted steps are kept only with a step mask (next_stage)
        counted = np.arange(batch.n_steps) < batch.n_steps - 1
        steps = mask.any(axis=2) & counted  # the steps whose factors enter each weight
        if plan.mixture:
            frozen_log_w = self._mixture_log_weight(batch, steps)
        else:
            frozen_log_w = masked_log_weight(batch, steps)
        rows, detected = batch.events()
        smoothed = self._smoothing(gamma) * frozen_log_w
        if self._parameters.proposal is not None:  # the parameters' fit weighs the whole rollout, theta's ratio too
            self._parameters.add(batch, self._smoothing(gamma) * self._whole_log_weight(batch))
        elite_steps.add(
            index + self._index_offset,
            batch,
            proposal.features(rows),
            mask.reshape(batch.n, -1),
            smoothed,
            (mask & counted[None, :, None]).reshape(batch.n, -1),
        )
        if batch.noise is not None and proposal.noise_shift is not None:  # the detected objects' errors
            hit = mask.reshape(batch.n, -1) & detected
            self._noise_data.append(
                (
                    rows[hit],
                    batch.noise.reshape(batch.n, -1, batch.noise.shape[-1])[hit],
                    np.broadcast_to(smoothed[:, None], hit.shape)[hit],
                )
            )

    def _fit_noise(self, fit: FitOptions) -> None:
        """The CE update of the proposal's error head on the errors of the detected objects of this stage's elites
        (:func:`pemviz.core.torch_fits.fit_noise_shift`), weighted as their rollouts in the detection fit."""
        data, self._noise_data = self._noise_data, []
        assert self.proposal is not None  # fitted by the pretraining stage
        if self.proposal.noise_shift is None or not data or not sum(len(d[0]) for d in data):
            return
        from pemviz.core.torch_fits import fit_noise_shift  # torch: a noisy target's runs only

        rows, noise, log_w = (np.concatenate(a) for a in zip(*data, strict=False))
        target = cast(NoisyDetector, self.problem.target)  # the errors' data come from a noisy target's rollouts
        loc_p, log_scale_p = target.noise_params(rows)
        family, df = target.noise_family, target.noise_df
        fit_noise_shift(self.proposal, rows, noise, loc_p, log_scale_p, family, df, log_w, fit)

    def _ce_stage(
        self, batch: RolloutBatch | None, robustness: np.ndarray, index: np.ndarray, gamma: float, n: int
    ) -> tuple[float, int, np.ndarray]:
        """The elites among ``batch`` (the stage's rollouts at or below gamma_kappa not yet settled,
        :class:`EliteCandidates`, of its ``n``) and the proposal refitted to all elites (in place); returns
        (gamma, elites, their detection rate per bin of the curve grid [G])."""
        proposal, grid = self.proposal, self.problem.curve_grid
        assert proposal is not None and self._elites is not None, "a CE stage comes after the pretraining fit"
        self.reached_failures = self.reached_failures or gamma <= 0.0  # latched: the pool's N is fixed once it starts
        elite = robustness <= gamma
        if self.ce.elite_ties == "random":
            elite = break_ties(
                robustness, gamma, self.ce.quantile_level, self.tie_rng, n, settled=self._elites.n_settled
            )
        self.check()
        fit = self._fit_options(self.ce.ce_epochs)
        if self._steps is not None:
            if batch is not None and elite.any():
                self._add_steps(batch.select(elite), index[elite], gamma)
            if self._steps is self._failure_steps and self.ce.fit_weights == "mixture":
                self._steps.reweight(self._pool_log_weight)
            self._steps.fit(proposal, fit)
            self._fit_noise(fit)
            self._parameters.refit(self.ce.fit_all_failures and gamma <= 0.0, self._own_samplers())
            return gamma, self._steps.n_rollouts, detect_rate(self._steps.counts, self._steps.hits)
        assert batch is not None  # without fitted steps none settled: the elites are all kept (EliteCandidates)
        if batch.n_objects != 1:
            raise ValueError(self.ce.whole_rollouts_refusal(batch.n_objects))
        features, detected, mask = self._fit_events(batch, self.step_mask(batch, gamma))
        ce_update(
            proposal,
            features,
            detected,
            batch.log_p,
            batch.log_q,
            elite,
            fit,
            smoothing=self._smoothing(gamma),
            weights=cast(WeightMode, self.ce.weights),
            step_mask=mask,
        )
        self._parameters.add(batch.select(elite), self._smoothing(gamma) * batch.log_weight()[elite])
        self._parameters.refit(self.ce.fit_all_failures and gamma <= 0.0, self._own_samplers())
        return gamma, int(elite.sum()), detect_rate(*elite_counts(batch, elite, grid))

    def step_mask(self, batch: RolloutBatch, level: float = 0.0) -> np.ndarray | None:
        """bool [N, T, M]: the object events whose actions enter the CE fit, or None for all of them.

        ``weights_until_failure``: the steps before the rollout reaches the stage's level (failure: the first
        step where the operand of the ``G`` safety formula is violated; with the classic metric and a level
        gamma_kappa > 0, the first step where its robustness is <= gamma_kappa: whether a rollout is an
        elite is settled there, later actions are not what made it one); ``proposal_window``: the objects
        inside the problem's window (their row's first column below it)."""
        cfg = self.config
        if not (cfg.weights_until_failure or self.ce.proposal_window):
            return None
        mask = np.ones(batch.detected.shape, bool)
        if cfg.weights_until_failure:
            level = level if cfg.metric == "classic" else 0.0
            before = np.arange(batch.n_steps)[None, :] < failure_steps(self.problem, batch, level)[:, None]
            mask &= before[:, :, None]
        if self.ce.proposal_window:
            mask &= batch.object_rows[..., 0] < self.problem.window
        return mask

    def _fit_events(
        self, batch: RolloutBatch, mask: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(the proposal's features of every object event [N, S(, k)], the detections [N, S], ``mask`` [N, S] or None),
        S = T M, events in order (:meth:`~pemviz.core.rollouts.RolloutBatch.events`)."""
        assert self.proposal is not None  # fitted (or created, for its own pretraining) before
        rows, detected = batch.events()
        return self.proposal.features(rows), detected, None if mask is None else mask.reshape(batch.n, -1)
