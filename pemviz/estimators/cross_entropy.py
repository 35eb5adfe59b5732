"""Cross-entropy adaptive importance sampling of detector outputs (Innes & Ramamoorthy 2022, Algorithm 1), with
pemviz's improvements over the paper (each switched by a field of :class:`~pemviz.config.ExperimentConfig`).

Stage 0 pretrains the proposal on rollouts of the target detector (the PEM); each CE stage draws N rollouts from
the proposal, takes the elites (robustness <= gamma_kappa, the (1 - sigma) quantile, floored at the failure level
0) and refits the proposal to them with importance weights raised to the power alpha (:func:`ce_update`); a
final batch of N_e rollouts from the last proposal gives the estimate, alone or pooled with the CE stages drawn
from proposals fitted to failures. The whole stage lives here: elites, weights, step masks, the fit's data and
loss (the optimiser and the proposal networks are in :mod:`pemviz.sampling`).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass
from typing import Callable, Literal

import numpy as np
import torch
from scipy.special import log_expit

from pemviz.config import ExperimentConfig, settings_of
from pemviz.detectors import Detector, LastAnswer, ScoredTarget, WindowDetector, action_log_prob, logit
from pemviz.estimate import Estimate, estimate
from pemviz.estimators.base import (
    Check,
    EliteCandidates,
    OwnsSettings,
    StageOutcome,
    StagePlan,
    StageRollouts,
    detect_rate,
    elite_count,
    elite_counts,
    failure_steps,
    mixture_log_weight,
    pool_stage_weights,
    pooled_estimate,
    weighted_steps_mask,
)
from pemviz.plan import RunPlan
from pemviz.problems import Problem
from pemviz.rng import RQMC_BLOCK
from pemviz.sampling import Proposal, StateProposal, fit_proposal
from pemviz.scenarios import RolloutBatch

WeightMode = Literal["frozen", "recomputed"]


def weighted_steps(
    features: np.ndarray,
    detected: np.ndarray,
    step_weight: np.ndarray,
    max_rows: int,
    rng: np.random.Generator,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The steps of positive weight as fitting rows, at most ``max_rows`` of them, and their weights.

    With more than ``max_rows`` weighted steps, ``max_rows`` are drawn by systematic resampling in
    proportion to the weights (Kitagawa 1996; Douc, Cappe & Moulines 2005): step j is drawn
    ``c_j`` times with ``E[c_j] = max_rows w_j / W`` (W = sum of weights), and enters with weight
    ``c_j W / max_rows``, so ``sum_j w_j log q(a_j | s_j)`` keeps its expectation for every q, and a step
    whose weight exceeds ``W / max_rows`` is always kept. Cost O(N T) numpy, whatever the fit.

    Args:
        features: float64 [N, T] or [N, T, k] proposal inputs.
        detected: bool [N, T] actions.
        step_weight: float64 [N, T] weights >= 0 (0 leaves a step out).
        max_rows: the most rows returned (>= 1).
        rng: draws the resampling offset.
    Returns:
        (distinct inputs [M] or [M, k] float64 tensor, counts [M, 2] float64 tensor: weight on miss, on
        detect), M <= ``max_rows``.
    """
    w = np.asarray(step_weight, dtype=np.float64).reshape(-1)
    keep = np.flatnonzero(w > 0)
    if keep.size > max_rows:
        cum = np.cumsum(w[keep])
        total = float(cum[-1])
        picks = np.searchsorted(cum, (rng.random() + np.arange(max_rows)) * (total / max_rows), side="right")
        picks, times = np.unique(np.minimum(picks, keep.size - 1), return_counts=True)
        keep, weight = keep[picks], times * (total / max_rows)
    else:
        weight = w[keep]
    f = np.asarray(features, dtype=np.float64)
    rows = f.reshape(-1, f.shape[2])[keep] if f.ndim == 3 else f.reshape(-1)[keep]
    # Steps at the same input share one row (rollouts agree until their first different action).
    rows, inverse = np.unique(rows, axis=0, return_inverse=True)
    slot = inverse.reshape(-1) * 2 + np.asarray(detected, dtype=bool).reshape(-1)[keep]
    counts = np.bincount(slot, weights=weight, minlength=2 * len(rows)).reshape(len(rows), 2)
    return torch.as_tensor(rows), torch.as_tensor(counts)


def _action_counts(
    gap_m: np.ndarray, detected: np.ndarray, row_weight: np.ndarray | None = None, drop_unweighted: bool = False
):
    """Distinct proposal inputs and the (weighted) number of misses and detections at each: an exact summary.

    q depends on the gap only, so ``sum_it w_i log q(a_it | d_it) = sum_u W0(u) log q(0|u) + W1(u) log q(1|u)``.
    Rollouts share most gaps (the detector matters only inside 10 m), so an epoch costs a forward pass
    over a few hundred distinct gaps instead of N * T.

    Args:
        gap_m: [N, T] gaps, or [N, T, k] inputs of a :class:`StateProposal` (distinct rows then).
        row_weight: [N] per rollout, or [N, T] per step (0 leaves a step out), or None (all 1).
        drop_unweighted: leave out the inputs whose steps all weigh 0 (e.g. outside the proposal's window), so an
            epoch does not evaluate the network where it cannot change the loss; ``inverse`` is then None.
    Returns:
        (uniq [U] (or [U, k]) float64 tensor, counts [U, 2] float64 tensor: weighted misses, detections;
        inverse [N, T] index of each entry into ``uniq``).
    """
    gap_m = np.asarray(gap_m, dtype=np.float64)
    shape = np.shape(detected)
    if gap_m.ndim == 3:
        uniq, inverse = np.unique(gap_m.reshape(-1, gap_m.shape[2]), axis=0, return_inverse=True)
    else:
        uniq, inverse = np.unique(gap_m, return_inverse=True)
    inverse = inverse.reshape(shape)
    if row_weight is None:
        w = np.ones(shape)
    else:
        row_weight = np.asarray(row_weight, dtype=np.float64)
        w = np.broadcast_to(row_weight if row_weight.ndim == 2 else row_weight[:, None], shape)
    slot = inverse * 2 + np.asarray(detected, dtype=np.int64)
    counts = np.bincount(slot.ravel(), weights=w.ravel(), minlength=2 * len(uniq)).reshape(len(uniq), 2)
    if drop_unweighted:
        keep = counts.sum(axis=1) > 0.0
        return torch.as_tensor(uniq[keep]), torch.as_tensor(counts[keep]), None
    return torch.as_tensor(uniq), torch.as_tensor(counts), inverse


def _summed_fit(fit: str, max_rows: int | None, n_fitted: int) -> bool:
    """Whether a fit of ``n_fitted`` weighted steps is the paper's: every step, summed over distinct inputs (with a
    ``tolerance``, a CE stage's such fit stops once converged, as the others do). The other fits (more than
    ``max_rows`` steps, or L-BFGS) see at most ``max_rows`` steps, with a loss normalised to nats per step, and stop
    once converged (``tolerance``): their cost is bounded whatever the number of rollouts."""
    return fit == "adam" and (max_rows is None or n_fitted <= max_rows)


def pretrain_proposal(
    proposal: Proposal,
    gap_m: np.ndarray,
    detected: np.ndarray,
    *,
    epochs: int = 1000,
    lr: float = 1e-3,
    check: Callable[[], None] | None = None,
    step_mask: np.ndarray | None = None,
    fit: str = "adam",
    max_rows: int | None = None,
    rng: np.random.Generator | None = None,
    tolerance: float | None = None,
) -> list[float]:
    """Fit q_phi to the PEM's own actions by maximum likelihood (full batch), in place.

    Args:
        gap_m: float64 [N, T] gaps of PEM-driven rollouts (metres), or [N, T, k] inputs of a
            :class:`StateProposal` (``proposal.features(observations)``).
        detected: bool [N, T] the PEM's detections.
        epochs: Adam epochs, or the most L-BFGS iterations (``fit``).
        check: called every :data:`pemviz.sampling.CHECK_EVERY` epochs; may raise to abandon the fit (cancel).
        step_mask: bool [N, T] or None: only these steps are fitted (e.g. inside the proposal's window).
        fit: one of :data:`pemviz.config.FITS`.
        max_rows: None (``adam``: every step, summed over distinct inputs, the paper's fit) or the most steps
            the fit sees: a uniform systematic subsample of the fitted steps beyond that (:func:`weighted_steps`).
        rng: draws that subsample (default: seeded 0).
        tolerance: early stopping of a fit of more than ``max_rows`` steps (nats per step;
            :func:`pemviz.sampling.fit_proposal`), None: every epoch; a fit of at most ``max_rows`` steps runs every epoch.
    Returns:
        the loss per epoch, or per L-BFGS evaluation (mean negative log-likelihood, nats per step).
    Source: Innes & Ramamoorthy 2022, Algorithm 1 (pretraining on PEM-driven rollouts).
    """
    n_fitted = np.size(detected) if step_mask is None else int(np.count_nonzero(step_mask))
    if _summed_fit(fit, max_rows, n_fitted):
        if step_mask is None:
            uniq, counts, _ = _action_counts(gap_m, detected)
            total = float(np.size(detected))
        else:
            step_mask = np.asarray(step_mask, dtype=np.float64)
            uniq, counts, _ = _action_counts(gap_m, detected, step_mask, drop_unweighted=True)
            total = max(float(step_mask.sum()), 1.0)
        return fit_proposal(proposal, uniq, counts, epochs, lr, check, per=total)
    mask = np.ones(np.shape(detected)) if step_mask is None else np.asarray(step_mask, dtype=np.float64)
    rows, counts = weighted_steps(gap_m, detected, mask, max_rows or mask.size, rng or np.random.default_rng(0))
    total = max(float(counts.sum()), 1.0)
    return fit_proposal(proposal, rows, counts, epochs, lr, check, fit, tolerance, per=total)  # fmt: skip


def ce_update(
    proposal: Proposal,
    gap_m: np.ndarray,
    detected: np.ndarray,
    log_p: np.ndarray,
    log_q: np.ndarray,
    elite: np.ndarray,
    *,
    smoothing: float,
    epochs: int = 500,
    lr: float = 1e-3,
    weights: WeightMode = "frozen",
    n_factors: int | None = None,
    check: Callable[[], None] | None = None,
    step_mask: np.ndarray | None = None,
    fit: str = "adam",
    max_rows: int | None = None,
    rng: np.random.Generator | None = None,
    tolerance: float | None = None,
) -> list[float]:
    """One cross-entropy stage: minimise ``-sum_i w_i^alpha 1[elite_i] sum_t log q_phi(a_t | d_t)``, in place.

    Args:
        gap_m, detected, log_p, log_q: [N, T] from the stage's rollouts (log_p under the PEM, log_q
            under the proposal that sampled them; nats).
        elite: bool [N], robustness <= gamma_kappa.
        smoothing: alpha in (0, 2], the power on the importance weights.
        weights: ``"frozen"``: w from the proposal that sampled the batch (textbook CE, paper eq. 10-11);
            ``"recomputed"``: w from the current q_phi with the gradient flowing through it (authors' code).
        n_factors: steps in each weight (default T - 1: the last action affects nothing).
        check: called every :data:`pemviz.sampling.CHECK_EVERY` epochs; may raise to abandon the update (cancel).
        step_mask: bool [N, T] or None: steps that count, in the weights and in the fit (False: left out,
            e.g. outside the proposal's window or after the failure).
        fit: one of :data:`pemviz.config.FITS`; ``epochs`` are then Adam epochs or the most L-BFGS iterations.
        max_rows: None (``adam``: every elite step, summed over distinct inputs, the paper's fit) or the most
            steps the fit sees: beyond that a weighted systematic subsample whose weighted log-likelihood has
            the same expectation (:func:`weighted_steps`); the loss is then divided by the total weight.
            ``weights = "recomputed"`` always fits every step.
        rng: draws that subsample (default: seeded 0).
        tolerance: early stopping of a fit of more than ``max_rows`` steps, or of ``lbfgs`` (nats per step;
            :func:`pemviz.sampling.fit_proposal`), None: every epoch; a fit of at most ``max_rows`` steps with ``adam``
            runs every epoch (the paper's fit).
    Returns:
        the loss per epoch (per L-BFGS evaluation). The weights are divided by their largest value (a
        constant factor, to which Adam's steps are invariant), so that w^alpha never overflows.
    Raises:
        ValueError: if there is no elite rollout.
    """
    idx = np.flatnonzero(elite)
    if idx.size == 0:
        raise ValueError("ce_update: no elite rollouts (robustness <= gamma) to fit the proposal to")
    k = detected.shape[1] - 1 if n_factors is None else n_factors
    mask = np.ones(detected.shape, bool) if step_mask is None else np.asarray(step_mask, dtype=bool)
    mask = mask[idx]
    lp = (log_p[idx, :k] * mask[:, :k]).sum(axis=1)
    frozen_log_w = ((log_p[idx, :k] - log_q[idx, :k]) * mask[:, :k]).sum(axis=1)
    if weights == "frozen" and step_mask is not None:
        scaled = smoothing * frozen_log_w
        rows, actions = gap_m[idx][mask], detected[idx][mask]
        return fit_elite_steps(proposal, rows, actions, np.broadcast_to(scaled[:, None], mask.shape)[mask],
                               float(scaled.max()), epochs=epochs, lr=lr, check=check, fit=fit, max_rows=max_rows,
                               rng=rng, tolerance=tolerance)  # fmt: skip
    if weights == "frozen":
        scaled = smoothing * frozen_log_w
        step_w = np.exp(scaled - scaled.max())[:, None] * mask
        if not _summed_fit(fit, max_rows, int(np.count_nonzero(step_w))):
            step_w = np.broadcast_to(step_w, detected[idx].shape)
            rows, counts = weighted_steps(gap_m[idx], detected[idx], step_w, max_rows or step_w.size,
                                           rng or np.random.default_rng(0))  # fmt: skip
            total = float(counts.sum())
            return fit_proposal(proposal, rows, counts, epochs, lr, check, fit, tolerance, per=total)  # fmt: skip
        uniq, counts, _ = _action_counts(gap_m[idx], detected[idx], step_w[:, 0])
        return fit_proposal(proposal, uniq, counts, epochs, lr, check, fit)
    # w depends on q_phi: per-rollout sums of log q over the first k steps, through the gradient.
    uniq, _, inverse = _action_counts(gap_m[idx], detected[idx])
    slot = inverse * 2 + detected[idx].astype(np.int64)
    return fit_proposal(proposal, uniq, recomputed_objective(slot, lp, mask, k, smoothing), epochs, lr, check, fit)


def recomputed_objective(
    slot: np.ndarray, log_p: np.ndarray, mask: np.ndarray, n_factors: int, smoothing: float
) -> Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]:
    """The CE loss with importance weights recomputed from the current proposal (the authors' code), as a
    :data:`pemviz.sampling.Objective`: ``-sum_i w_i(phi) sum_t m_it log q_phi(a_it | d_it)`` with
    ``w_i(phi) = exp(alpha (log p_i - sum_{t < k} m_it log q_phi(a_it | d_it)) - c)`` (c: their largest exponent,
    held constant), and its gradient in log q, which flows through the weights.

    Args:
        slot: int64 [n, T] where each elite step's log q sits in the flattened log q [M * 2] (input row x 2 + action).
        log_p: float64 [n] each elite's sum of log p over its first k masked steps (nats).
        mask: bool [n, T] the steps that count.
        n_factors: k, the steps in each weight.
        smoothing: alpha in (0, 2].
    Returns:
        log q [M, 2] -> (loss, d loss / d log q [M, 2]): the operations autograd would run, in its order, so a fit
        gives the same bits as differentiating the loss with autograd (a test checks it).
    Source: Innes & Ramamoorthy 2022, eq. 10-11, with the weights differentiated as in the authors' code.
    """
    slot_t, lp_t = torch.as_tensor(slot), torch.as_tensor(log_p)
    mask_t = torch.as_tensor(mask, dtype=torch.float64)
    mask_k = torch.zeros_like(mask_t)
    mask_k[:, :n_factors] = 1.0

    def loss(log_q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        log_q_now = log_q.reshape(-1)[slot_t] * mask_t
        scaled = smoothing * (lp_t - log_q_now[:, :n_factors].sum(dim=1))
        w = torch.exp(scaled - scaled.max())
        per_rollout = log_q_now.sum(dim=1)
        grad_w_term = per_rollout * w * smoothing  # d loss / d (sum_{t<k} log q) of each rollout
        grad_now = (-w)[:, None].expand_as(log_q_now) + grad_w_term[:, None] * mask_k
        grad = torch.zeros(log_q.numel(), dtype=log_q.dtype).index_put_((slot_t,), grad_now * mask_t, accumulate=True)
        return -(w * per_rollout).sum(), grad.reshape(log_q.shape)

    return loss


def fit_elite_steps(
    proposal: Proposal,
    rows: np.ndarray,
    actions: np.ndarray,
    log_w: np.ndarray,
    log_w_max: float,
    *,
    epochs: int,
    lr: float,
    check: Callable[[], None] | None = None,
    fit: str = "adam",
    max_rows: int | None = None,
    rng: np.random.Generator | None = None,
    tolerance: float | None = None,
    n_steps: int | None = None,
) -> list[float]:
    """The frozen-weight CE fit on the elites' fitted steps: minimise ``-sum_s w_s log q_phi(a_s | h_s)``, in place.

    Args:
        rows: float64 [S] or [S, k] proposal inputs of the steps that count (the elites', inside the step mask), in
            the order drawn (rollout by rollout, step by step).
        actions: bool [S] their detections.
        log_w: float64 [S] each step's weight in log space (nats): alpha times its rollout's importance log-weight.
        log_w_max: the largest rollout log-weight (alpha log w_i) of the elites; the weights are divided by its
            exponential (a constant factor, to which Adam's steps are invariant), so that none overflows.
        n_steps: the steps these rows stand for (default S; more once they were thinned as they came).
        epochs, lr, check, fit, max_rows, rng, tolerance: see :func:`ce_update`.
    Returns:
        the loss per epoch (per L-BFGS evaluation).
    Source: Innes & Ramamoorthy 2022, eq. 10-11 (the CE update), summed over distinct inputs.
    """
    w = np.exp(np.asarray(log_w, dtype=np.float64) - log_w_max)[None]
    rows, actions = np.asarray(rows)[None], np.asarray(actions, dtype=bool)[None]
    if not _summed_fit(fit, max_rows, int(np.count_nonzero(w)) if n_steps is None else n_steps):
        fitted, counts = weighted_steps(rows, actions, w, max_rows or w.size, rng or np.random.default_rng(0))
        total = float(counts.sum())
        return fit_proposal(proposal, fitted, counts, epochs, lr, check, fit, tolerance, per=total)  # fmt: skip
    uniq, counts, _ = _action_counts(rows, actions, w, drop_unweighted=True)
    if tolerance is None:
        return fit_proposal(proposal, uniq, counts, epochs, lr, check, fit)
    # the proposal starts from the last stage's fit (a warm start): stop once the loss per step stops falling
    return fit_proposal(proposal, uniq, counts, epochs, lr, check, fit, tolerance, per=float(counts.sum()))


class EliteSteps:
    """The fitted steps of a stage's elites, gathered rollout by rollout as chunks arrive: proposal inputs, actions
    and log-weights of the steps inside the step mask only, so that a stage of any N holds at most
    ``thin_above`` steps. Beyond that they are thinned to ``max_rows`` weighted steps by systematic resampling
    (:func:`weighted_steps`; each thinning keeps the expected weighted log-likelihood, so the fit's objective
    keeps its expectation). Also the elites' detections per bin of the curve grid.

    Args:
        grid: the problem's curve grid [G].
        max_rows: the fit's ``max_rows`` (None: never thinned).
        rng: draws the thinning.
        thin_above: steps held before a thinning (default 20 x ``max_rows``).
        keep_observations: also hold each step's observation, so that :meth:`reweight` can compute new weights
            (until a thinning).
    """

    def __init__(self, grid: np.ndarray, max_rows: int | None, rng: np.random.Generator,
                 thin_above: int | None = None, keep_observations: bool = False) -> None:  # fmt: skip
        self.grid, self.max_rows, self.rng = grid, max_rows, rng
        self.thin_above = None if max_rows is None else (thin_above or 20 * max_rows)
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.keep_observations = keep_observations
        self.observations: list[tuple[np.ndarray, np.ndarray]] = []
        """With ``keep_observations``, per part: the steps' observations [S, F] and whether each counts in its
        rollout's weight, bool [S]."""
        self.counts, self.hits = np.zeros(grid.size), np.zeros(grid.size)
        self.n_rollouts, self.n_steps, self.held, self.thinned = 0, 0, 0, False
        self.log_w_max = -np.inf

    def add(self, index: np.ndarray, batch: RolloutBatch, features: np.ndarray, mask: np.ndarray,
            log_w: np.ndarray, weighted: np.ndarray | None = None) -> None:  # fmt: skip
        """Elite rollouts ``index`` [m] of the stage: their features [m, T(, k)], step mask bool [m, T],
        smoothed log-weights alpha log w_i [m] and (``keep_observations``) the steps of ``mask`` that count in
        the weights, bool [m, T] (None: all)."""
        if index.size == 0:
            return
        c, h = elite_counts(batch, np.ones(batch.n, bool), self.grid)
        self.counts, self.hits = self.counts + c, self.hits + h
        order = np.broadcast_to(np.asarray(index)[:, None], mask.shape)[mask]
        self.parts.append((order, features[mask], batch.detected[mask], np.broadcast_to(log_w[:, None], mask.shape)[mask]))
        if self.keep_observations:
            self.observations.append((batch.observations[mask], np.ones(int(mask.sum()), bool) if weighted is None
                                      else weighted[mask]))  # fmt: skip
        self.n_rollouts += index.size
        self.n_steps += int(mask.sum())
        self.held += int(mask.sum())
        self.log_w_max = max(self.log_w_max, float(np.max(log_w)))
        if self.thin_above is not None and self.held > self.thin_above:
            self._thin()

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows [S(, k)], actions [S], log-weights [S]) in the order drawn."""
        order, rows, actions, log_w = (np.concatenate(a) for a in zip(*self.parts))
        if len(self.parts) > 1 and not self.thinned:
            by = np.argsort(order, kind="stable")
            rows, actions, log_w = rows[by], actions[by], log_w[by]
        return rows, actions, log_w

    def _thin(self) -> None:
        rows, actions, log_w = self.arrays()
        top = float(log_w.max())
        uniq, counts = weighted_steps(rows[None], actions[None], np.exp(log_w - top)[None], self.max_rows, self.rng)
        uniq, counts = uniq.numpy(), counts.numpy()
        hit = counts > 0  # [U, 2]: (miss, detect) weights of each distinct input
        slot, action = np.nonzero(hit)
        with np.errstate(divide="ignore"):
            self.parts = [(np.zeros(slot.size, np.int64), uniq[slot], action.astype(bool),
                           np.log(counts[slot, action]) + top)]  # fmt: skip
        self.held, self.thinned = slot.size, True
        self.observations, self.keep_observations = [], False  # the steps no longer belong to rollouts: no reweighting

    def reweight(self, log_weight: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]) -> bool:
        """Give every held step a new log-weight: ``log_weight(rollout [S], observations [S, F], actions [S],
        counts [S])`` -> [S] (nats), each step's rollout and whether the step counts in the rollout's weight.

        Returns:
            False (nothing changed) without ``keep_observations`` or once thinned: the steps then no longer
            belong to whole rollouts.
        """
        if not self.keep_observations or self.thinned or not self.parts:
            return False
        order, rows, actions, _ = (np.concatenate(a) for a in zip(*self.parts))
        obs, counts = (np.concatenate(a) for a in zip(*self.observations))
        by = np.argsort(order, kind="stable")  # rollout by rollout, step by step: the order drawn
        order, rows, actions, obs, counts = order[by], rows[by], actions[by], obs[by], counts[by]
        log_w = np.asarray(log_weight(order, obs, actions, counts), dtype=np.float64)
        self.parts, self.observations = [(order, rows, actions, log_w)], [(obs, counts)]
        self.log_w_max = float(np.max(log_w))
        return True

    def fit(self, proposal: Proposal, **kwargs) -> list[float]:
        """:func:`fit_elite_steps` on the gathered steps (``kwargs``: epochs, lr, check, fit, max_rows, rng,
        tolerance)."""
        rows, actions, log_w = self.arrays()
        return fit_elite_steps(proposal, rows, actions, log_w, self.log_w_max,
                               n_steps=self.n_steps if self.thinned else None, **kwargs)  # fmt: skip


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


def break_ties(robustness: np.ndarray, gamma: float, quantile_level: float, rng: np.random.Generator,
               n: int | None = None, settled: int = 0) -> np.ndarray:  # fmt: skip
    """bool [M]: every rollout below gamma plus randomly chosen ties at gamma up to ceil((1 - sigma) N) elites.

    At gamma = 0 (the failure threshold) this keeps all failures (r < 0) and admits a non-failing rollout
    with r = 0 only to reach ceil((1 - sigma) N) elites. ``n``: N, the stage's rollouts, when ``robustness``
    holds only some of them (:class:`~pemviz.estimators.base.EliteCandidates`: every one at or below gamma);
    default M. ``settled``: rollouts below gamma already taken as elites and not in ``robustness``.
    """
    k = elite_count(robustness.size if n is None else n, quantile_level)
    below = robustness < gamma
    ties = np.flatnonzero(robustness == gamma)
    elite = below.copy()
    elite[rng.permutation(ties)[: max(0, k - int(below.sum()) - settled)]] = True
    return elite


class CrossEntropy(OwnsSettings):
    """Algorithm 1 of Innes & Ramamoorthy (2022) as configured by ``config`` (``method = "adaptive"``).

    Stages: 0 pretraining (``pretrain_rollouts``), 1..K cross-entropy (``n_per_stage`` each), K+1 the final batch
    (``n_final``; none with ``final_estimate = "last-stage"``).

    Random streams, one per purpose, all from ``config.seed``: the rollouts' detections (:attr:`rng`, which the
    engine draws from); the fits' subsamples
    (``(seed, 1)``); tie-breaking (``(seed, 2)``); the proposal's initial weights (torch, seeded in a fork of the
    process's generator), so turning one option on leaves the other streams as they were.

    Args:
        config: the sampler's settings.
        problem: what to estimate.
        check: called between and inside fits; may raise to abandon the run.
    """

    SETTINGS = settings_of("adaptive")

    def __init__(self, config: ExperimentConfig, problem: Problem, check: Check | None = None) -> None:
        self.config, self.problem = config, problem
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
        self._memos: tuple[LastAnswer, ...] = ()
        """The proposal as both samplers around it ask it (they share its answer about a step's observations), and
        the two samplers, each remembering its last answer (the mixture's target asks both about every step)."""
        self._seen = 0
        """Rollouts of the planned stage observed so far."""
        self._scored: ScoredTarget | None = None
        """The planned mixture stage's target, keeping its proposal components' logits while the rollouts are drawn."""
        self.tolerance = config.fit_tolerance if config.fit == "adam" else None
        """Early stopping of the CE stages' Adam fits (L-BFGS stops at its own tolerance)."""

    # -- the interface --------------------------------------------------------------------------------------------
    @staticmethod
    def run_plan(config: ExperimentConfig) -> RunPlan:
        """Stage 0 pretraining, 1..K cross-entropy stages, K+1 the final batch (none with ``last-stage``)."""
        final = [(config.n_stages + 1, "final", config.n_final)] if config.has_final_batch else []
        return RunPlan.of([(0, "pretrain", config.pretrain_rollouts)]
                          + [(k, "ce", config.n_per_stage) for k in range(1, config.n_stages + 1)] + final)  # fmt: skip

    def plan(self) -> RunPlan:
        return self.run_plan(self.config)

    def next_stage(self) -> StagePlan | None:
        cfg, k = self.config, (-1 if self._plan is None else self._plan.stage) + 1
        if k == 0:
            plan = StagePlan(0, "pretrain", cfg.pretrain_rollouts, self._pretrain_sampler())
        elif k <= cfg.n_stages:
            if self.reached_failures:
                self.pooled.append(k)
            plan = StagePlan(k, "ce", cfg.n_per_stage, self.sampler, mixture=self._mixture(cfg.n_per_stage))
            if cfg.fit_weights == "mixture":
                self._stage_samplers[k] = self._frozen_samplers(plan)
            self._elites = EliteCandidates(plan.n, cfg.quantile_level, floor=0.0)
            if self._failure_steps is not None:  # every failure since the failure level was reached
                self._steps = self._failure_steps
            elif cfg.weights == "frozen" and (cfg.weights_until_failure or cfg.proposal_window):
                self._steps = EliteSteps(self.problem.curve_grid, cfg.fit_rows, self.fit_rng,
                                         keep_observations=cfg.fit_weights == "mixture")  # fmt: skip
        elif k == cfg.n_stages + 1 and cfg.final_estimate != "last-stage":
            plan = StagePlan(k, "final", cfg.n_final, self.sampler, mixture=self._mixture(cfg.n_final))
        else:
            return None
        for memo in self._memos:
            memo.forget()  # the proposal was fitted since it last answered
        self._scored, self._seen = None, 0
        if plan.mixture:
            extras = tuple(dict.fromkeys(d for _, d in plan.mixture if d is not self.problem.target))
            self._scored = ScoredTarget(self.problem.target, extras)
            plan = dataclasses.replace(plan, target=self._scored)
        self._plan = plan
        self.stages[k] = StageRollouts(self.problem.curve_grid)
        return plan

    def _mixture(self, n: int) -> tuple[tuple[int, Detector], ...]:
        """The mixture over whole rollouts of a CE or final stage of ``n`` (:attr:`StagePlan.mixture`):
        round(``target_share`` n) rollouts from the target, round(``plain_share`` n) from the proposal without the
        per-step defensive mixture, the rest from :attr:`sampler`; none with both shares 0."""
        cfg = self.config
        if cfg.target_share + cfg.plain_share == 0.0:
            return ()
        # before the failure level the target's rollouts would not reach the stage's level: none are drawn
        n_p = int(round(cfg.target_share * n)) if self.reached_failures else 0
        n_q = int(round(cfg.plain_share * n))
        n_q = min(n_q, n - n_p)
        return ((n_p, self.problem.target), (n_q, self.plain_sampler), (n - n_p - n_q, self.sampler))

    def _mixture_log_weight(self, batch: RolloutBatch, mask: np.ndarray) -> np.ndarray:
        """log p(x) - log sum_k c_k q_k(x) over the steps of ``mask`` (bool [N, T]) for rollouts of the planned
        stage's mixture (:func:`~pemviz.estimators.base.mixture_log_weight`), float64 [N] (nats), from the
        components' log-probabilities the batch carries (:meth:`_with_parts`)."""
        plan, pb = self._plan, self.problem
        log_p = (batch.log_p * mask).sum(axis=1)
        extras = self._scored.extras
        log_q = [log_p if d is pb.target else (batch.log_q_parts[:, extras.index(d)] * mask).sum(axis=1)
                 for _, d in plan.mixture]  # fmt: skip
        return mixture_log_weight(log_p, np.stack(log_q), np.array([k for k, _ in plan.mixture]) / plan.n)

    def _with_parts(self, batch: RolloutBatch) -> RolloutBatch:
        """``batch`` (the planned mixture stage's next rollouts) with ``log_q_parts`` [N, K, T]: the log-probabilities
        of its actions under the mixture's proposal components (:attr:`ScoredTarget.extras`), as the simulation asked
        them, or asked again where it could not keep them (Ray tasks; :meth:`_ask_again`)."""
        start, self._seen = self._seen, self._seen + batch.n
        logits = self._scored.take(batch.n, batch.n_steps)
        if logits is None:
            logits = self._ask_again(batch, start)
        parts = np.stack([action_log_prob(lg, batch.detected) for lg in logits], axis=1)
        return dataclasses.replace(batch, log_q_parts=parts)

    def _ask_again(self, batch: RolloutBatch, start: int) -> np.ndarray:
        """The extras' logits [K, N, T] of rollouts ``start .. start + N - 1`` of the stage, asked as a simulator asks
        them: one step at a time about the rollouts of one block (:data:`pemviz.rng.RQMC_BLOCK`) of one mixture
        component, so that the proposal network sees the same rows and gives the same bits as it gave there."""
        plan, n, n_steps = self._plan, batch.n, batch.n_steps
        rebuilt = dict(zip((id(d) for _, d in plan.mixture), (d for _, d in self._around(plan.mixture, self.proposal))))
        extras = [rebuilt[id(d)] for d in self._scored.extras]
        logits = np.empty((len(extras), n, n_steps))
        edges = np.cumsum([0] + [k for k, _ in plan.mixture])
        for lo, hi in zip(edges[:-1], edges[1:]):  # each component's rollouts, drawn one block after another
            for b0 in range(int(lo), int(hi), RQMC_BLOCK):
                a, b = max(b0, start), min(b0 + RQMC_BLOCK, int(hi), start + n)
                if a >= b:
                    continue
                rows = slice(a - start, b - start)
                for t in range(n_steps):
                    obs = batch.observations[rows, t]
                    for j, d in enumerate(extras):
                        logits[j, rows, t] = d.detect_logit(obs)
        return logits

    def observe(self, batch: RolloutBatch, failed: np.ndarray, robustness: np.ndarray | None) -> np.ndarray:
        plan = self._plan
        if plan.mixture:
            batch = self._with_parts(batch)
        if plan.kind == "pretrain":
            self._chunks.append(batch)
        elif plan.kind == "ce":
            self._elites.add(batch, robustness)
            if self._steps is not None:  # failures of a stage at the failure level: only their fitted steps are kept
                settled, index = self._elites.settle()
                if settled is not None:
                    self._add_steps(settled, index, self._elites.floor)
        until = self.config.weights_until_failure
        log_w = self._mixture_log_weight(batch, weighted_steps_mask(self.problem, batch, until)) if plan.mixture else None
        return self.stages[plan.stage].add(self.problem, batch, failed, until, count_failures=plan.kind == "final",
                                           log_w=log_w)  # fmt: skip

    def finish(self) -> StageOutcome:
        plan, grid = self._plan, self.problem.curve_grid
        if plan.kind == "final":
            outcome = self.stages[plan.stage].failures_outcome(self.proposal.curve(grid))
        else:
            if plan.kind == "pretrain":
                batch = RolloutBatch.concatenate(self._chunks) if len(self._chunks) > 1 else self._chunks[0]
                self._chunks = []
                gamma, n_elites, rate = float("nan"), 0, detect_rate(*elite_counts(batch, np.zeros(batch.n, bool), grid))
                self._pretrain(batch)
            else:
                batch, r, index = self._elites.candidates()
                gamma, n_elites, rate = self._ce_stage(batch, r, index, self._elites.gamma(), plan.n)
                if self.config.fit_all_failures and gamma <= 0.0 and self._steps is not None:
                    self._failure_steps = self._steps
                    self._index_offset += plan.n
                    self._pool_start = plan.stage if self._pool_start is None else self._pool_start
                self._elites = self._steps = None
            log_w, failed, log_p = self.stages[plan.stage].arrays()
            outcome = StageOutcome(gamma, n_elites, estimate(log_w, failed, log_p), self.proposal.curve(grid), rate)
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
        adaptive importance sampling", NeurIPS 2018).
        """
        stage, est = self._last
        if self.config.final_estimate == "pooled" and self.reached_failures and self.pooled:
            used = (*self.pooled, stage)
            stages = [self.stages[k] for k in used]
            return pooled_estimate(stages, pool_stage_weights(self.config.pool_weights, [s.n for s in stages])), used
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
        cfg = self.config
        with torch.random.fork_rng(devices=[]):  # the proposal's initial weights, without reseeding the process
            torch.manual_seed(cfg.seed)
            self.proposal = proposal = self._new_proposal(batch)
        pretrain_proposal(
            proposal, proposal.features(batch.observations), batch.detected,
            epochs=cfg.pretrain_epochs if cfg.fit == "adam" else cfg.fit_max_steps, lr=cfg.learning_rate,
            check=self.check, step_mask=self.step_mask(batch) if cfg.proposal_window else None,
            fit=cfg.fit, max_rows=cfg.fit_rows, rng=self.fit_rng, tolerance=self.tolerance,
        )  # fmt: skip
        if cfg.defensive > 0.0:  # two samplers share the proposal's answer about a step: the network runs once a step
            shared = LastAnswer(proposal)
            self._memos = (shared, *(LastAnswer(d) for d in self._samplers(shared)))
            self.plain_sampler, self.sampler = self._memos[1:]
        else:
            self.plain_sampler, self.sampler = self._samplers(proposal)

    def _samplers(self, proposal: Detector) -> tuple[Detector, Detector]:
        """(the plain sampler, the CE stages' sampler) around a proposal (or a :class:`LastAnswer` around one): q
        inside the problem's window (``proposal_window``; q = p_target where the detector cannot matter), and that
        with the per-step defensive mixture (``defensive``)."""
        cfg, pb = self.config, self.problem
        floor = pb.decided_below if cfg.skip_decided else -math.inf  # below it the outcome is decided

        def windowed(sampler: Detector) -> Detector:
            return WindowDetector(sampler, pb.target, pb.window, floor) if cfg.proposal_window else sampler

        plain = windowed(proposal)
        if cfg.defensive > 0.0:  # every outcome keeps probability >= eps / 2 at every step
            return plain, windowed(DefensiveDetector(proposal, float(cfg.defensive)))
        return plain, plain

    def _around(self, mixture: tuple[tuple[int, Detector], ...],
                proposal: Proposal) -> tuple[tuple[int, Detector], ...]:  # fmt: skip
        """A stage's (rollouts, sampler) components with the proposal's samplers rebuilt around ``proposal`` (the
        target stays), which remembers its last answer: the plain and the defensive sampler, asked about the same
        observations, evaluate the network once."""
        plain, sampler = self._samplers(LastAnswer(proposal))
        rebuilt = {id(self.plain_sampler): plain, id(self.sampler): sampler}
        return tuple((n, rebuilt.get(id(d), d)) for n, d in mixture)

    def _frozen_samplers(self, plan: StagePlan) -> tuple[tuple[int, Detector], ...]:
        """A CE stage's samplers, (rollouts, detector) each, around a copy of the current proposal (later fits
        change the proposal in place)."""
        return self._around(plan.mixture or ((plan.n, self.sampler),), copy.deepcopy(self.proposal))

    def _pool_log_weight(self, rollout: np.ndarray, obs: np.ndarray, actions: np.ndarray,
                         counts: np.ndarray) -> np.ndarray:  # fmt: skip
        """alpha log w of each step's rollout [S] (nats) for ``fit_weights = "mixture"``: w = p(x) / sum_j c_j q_j(x)
        over the samplers q_j of every stage in the failure pool, c_j their shares of its rollouts (the balance
        heuristic over all stages, the deterministic-mixture weight of adaptive multiple importance sampling:
        Cornuet, Marin, Mira & Robert, "Adaptive multiple importance sampling", Scand. J. Stat. 39(4), 2012;
        Owen & Zhou, "Safe and effective importance sampling", JASA 2000), over the steps that count (``counts``).
        Arguments as :meth:`EliteSteps.reweight` passes them."""
        pb = self.problem
        ids, inverse = np.unique(rollout, return_inverse=True)

        def log_prob(key: object, detector: Detector) -> np.ndarray:
            """Per rollout, over the steps that count; each (sampler, rollout) computed once (a rollout's steps do
            not change once held)."""
            known = self._pool_log_q.get(key, np.empty(0))
            if known.size <= ids[-1]:
                known = np.concatenate([known, np.full(ids[-1] + 1 - known.size, np.nan)])
                self._pool_log_q[key] = known
            todo = np.isnan(known[ids])
            if todo.any():
                steps = todo[inverse]
                step = np.where(counts[steps], action_log_prob(detector.detect_logit(obs[steps]), actions[steps]), 0.0)
                known[ids[todo]] = np.bincount(inverse[steps], weights=step, minlength=ids.size)[todo]
            return known[ids]

        log_p = log_prob("target", pb.target)
        parts = [(k, i, n, d) for k in range(self._pool_start, self._plan.stage + 1)
                 for i, (n, d) in enumerate(self._stage_samplers[k])]  # fmt: skip
        log_q = np.stack([log_p if d is pb.target else log_prob((k, i), d) for k, i, _, d in parts])
        shares = np.array([n for _, _, n, _ in parts], dtype=np.float64)
        log_w = mixture_log_weight(log_p, log_q, shares / shares.sum())
        return (self._smoothing(0.0) * log_w)[inverse]

    def _smoothing(self, gamma: float) -> float:
        """alpha of a stage at threshold gamma: ``smoothing_at_failure`` once gamma reached the failure level, and
        ``final_smoothing`` (when set) in the last stage, whose fit gives the final proposal."""
        cfg = self.config
        if gamma > 0.0:
            return cfg.smoothing
        if cfg.final_smoothing is not None and self._plan is not None and self._plan.stage >= cfg.n_stages:
            return cfg.final_smoothing
        return cfg.smoothing if cfg.smoothing_at_failure is None else cfg.smoothing_at_failure

    def _add_steps(self, batch: RolloutBatch, index: np.ndarray, gamma: float) -> None:
        """Reduce elite rollouts to their fitted steps (:class:`EliteSteps`): inputs, actions, alpha log w_i."""
        mask = self.step_mask(batch, gamma)
        k = batch.n_steps - 1
        if self._plan.mixture:
            frozen_log_w = self._mixture_log_weight(batch, mask & (np.arange(batch.n_steps) < k))
        else:
            frozen_log_w = ((batch.log_p[:, :k] - batch.log_q[:, :k]) * mask[:, :k]).sum(axis=1)
        self._steps.add(index + self._index_offset, batch, self.proposal.features(batch.observations), mask,
                        self._smoothing(gamma) * frozen_log_w, mask & (np.arange(batch.n_steps) < k))  # fmt: skip

    def _ce_stage(self, batch: RolloutBatch | None, robustness: np.ndarray, index: np.ndarray, gamma: float,
                  n: int) -> tuple[float, int, np.ndarray]:  # fmt: skip
        """The elites among ``batch`` (the stage's rollouts at or below gamma_kappa not yet settled,
        :class:`EliteCandidates`, of its ``n``) and the proposal refitted to all elites (in place); returns
        (gamma, elites, their detection rate per bin of the curve grid [G])."""
        cfg, proposal, grid = self.config, self.proposal, self.problem.curve_grid
        self.reached_failures = self.reached_failures or gamma <= 0.0  # latched: the pool's N is fixed once it starts
        elite = robustness <= gamma
        if cfg.elite_ties == "random":
            elite = break_ties(robustness, gamma, cfg.quantile_level, self.tie_rng, n, settled=self._elites.n_settled)
        self.check()
        epochs = cfg.ce_epochs if cfg.fit == "adam" else cfg.fit_max_steps
        fit = dict(epochs=epochs, lr=cfg.learning_rate, check=self.check, fit=cfg.fit, max_rows=cfg.fit_rows,
                   rng=self.fit_rng, tolerance=self.tolerance)  # fmt: skip
        if self._steps is not None:
            if batch is not None and elite.any():
                self._add_steps(batch.select(elite), index[elite], gamma)
            if self._steps is self._failure_steps and self.config.fit_weights == "mixture":
                self._steps.reweight(self._pool_log_weight)
            self._steps.fit(proposal, **fit)
            return gamma, self._steps.n_rollouts, detect_rate(self._steps.counts, self._steps.hits)
        ce_update(
            proposal, proposal.features(batch.observations), batch.detected, batch.log_p, batch.log_q, elite,
            smoothing=self._smoothing(gamma), weights=cfg.weights, step_mask=self.step_mask(batch, gamma), **fit,
        )  # fmt: skip
        return gamma, int(elite.sum()), detect_rate(*elite_counts(batch, elite, grid))

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
