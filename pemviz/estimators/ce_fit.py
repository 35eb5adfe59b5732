"""The cross-entropy fit of the proposal (Innes & Ramamoorthy 2022, Algorithm 1, eq. 10-11): the pretraining fit to the
target's own actions, the weighted CE update on the elites' steps, the frozen- and recomputed-weight objectives, the
systematic subsample that bounds a fit's rows, and :class:`EliteSteps`, the elites' fitted steps gathered chunk by
chunk. :class:`pemviz.estimators.cross_entropy.CrossEntropy` runs the stages around them."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Literal

import numpy as np

from pemviz.core import libm
from pemviz.core.fit_settings import FitOptions
from pemviz.core.rollouts import RolloutBatch
from pemviz.core.sampling import Proposal, StateProposal, fit_proposal
from pemviz.estimators.base import elite_count, elite_counts

if TYPE_CHECKING:
    import torch
    from torch import Tensor  # inside :func:`recomputed_objective` the name ``torch`` is a local

WeightMode = Literal["frozen", "recomputed"]


def weighted_steps(
    features: np.ndarray,
    detected: np.ndarray,
    step_weight: np.ndarray,
    max_rows: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
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
        (distinct inputs [M] or [M, k] float64, counts [M, 2] float64: weight on miss, on
        detect), M <= ``max_rows``."""
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
    return rows, counts


def _action_counts(
    inputs: np.ndarray, detected: np.ndarray, row_weight: np.ndarray | None = None, drop_unweighted: bool = False
):
    """Distinct proposal inputs and the (weighted) number of misses and detections at each: an exact summary.

    q depends on its input only, so ``sum_it w_i log q(a_it | d_it) = sum_u W0(u) log q(0|u) + W1(u) log q(1|u)``.
    Rollouts share most inputs (the detector matters only inside the problem's window), so an epoch costs a forward
    pass over a few hundred distinct inputs instead of N * T.

    Args:
        inputs: [N, T] proposal inputs (the first observation column), or [N, T, k] inputs of a
            :class:`StateProposal` (distinct rows then).
        detected: bool [N, T] the detections (the actions).
        row_weight: [N] per rollout, or [N, T] per step (0 leaves a step out), or None (all 1).
        drop_unweighted: leave out the inputs whose steps all weigh 0 (e.g. outside the proposal's window), so an
            epoch does not evaluate the network where it cannot change the loss; ``inverse`` is then None.
    Returns:
        (uniq [U] (or [U, k]) float64, counts [U, 2] float64: weighted misses, detections;
        inverse [N, T] index of each entry into ``uniq``)."""
    inputs = np.asarray(inputs, dtype=np.float64)
    shape = np.shape(detected)
    if inputs.ndim == 3:
        uniq, inverse = np.unique(inputs.reshape(-1, inputs.shape[2]), axis=0, return_inverse=True)
    else:
        uniq, inverse = np.unique(inputs, return_inverse=True)
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
        return uniq[keep], counts[keep], None
    return uniq, counts, inverse


def _subsampled_fit(
    proposal: Proposal,
    inputs: np.ndarray,
    actions: np.ndarray,
    weight: np.ndarray,
    options: FitOptions,
    floor: float = 0.0,
) -> list[float]:
    """The fit on at most ``max_rows`` of the weighted steps (:func:`weighted_steps`: inputs [N, T(, k)], actions and
    weights [N, T]), its loss divided by their total weight (at least ``floor``)."""
    rng = options.rng or np.random.default_rng(0)
    rows, counts = weighted_steps(inputs, actions, weight, options.max_rows or np.size(weight), rng)
    per = max(float(counts.sum()), floor)
    return fit_proposal(proposal, rows, counts, *options.args, options.tolerance, per=per, dtype=options.dtype)


def pretrain_proposal(
    proposal: Proposal,
    inputs: np.ndarray,
    detected: np.ndarray,
    options: FitOptions,
    step_mask: np.ndarray | None = None,
) -> list[float]:
    """Fit q_phi to the PEM's own actions by maximum likelihood (full batch), in place.

    Args:
        proposal: the proposal q_phi fitted, in place.
        inputs: float64 [N, T] proposal inputs of PEM-driven rollouts (the first observation column), or [N, T, k]
            inputs of a :class:`StateProposal` (``proposal.features(observations)``).
        detected: bool [N, T] the PEM's detections.
        options: the fit's settings; a fit of at most ``max_rows`` steps runs every epoch.
        step_mask: bool [N, T] or None: only these steps are fitted (e.g. inside the proposal's window).
    Returns:
        the loss per epoch, or per L-BFGS evaluation (mean negative log-likelihood, nats per step).
    Source: Innes & Ramamoorthy 2022, Algorithm 1 (pretraining on PEM-driven rollouts)."""
    n_fitted = np.size(detected) if step_mask is None else int(np.count_nonzero(step_mask))
    if options.summed(n_fitted):
        if step_mask is None:
            uniq, counts, _ = _action_counts(inputs, detected)
            total = float(np.size(detected))
        else:
            step_mask = np.asarray(step_mask, dtype=np.float64)
            uniq, counts, _ = _action_counts(inputs, detected, step_mask, drop_unweighted=True)
            total = max(float(step_mask.sum()), 1.0)
        return fit_proposal(proposal, uniq, counts, *options.args, per=total, dtype=options.dtype)
    mask = np.ones(np.shape(detected)) if step_mask is None else np.asarray(step_mask, dtype=np.float64)
    return _subsampled_fit(proposal, inputs, detected, mask, options, floor=1.0)


def ce_update(
    proposal: Proposal,
    inputs: np.ndarray,
    detected: np.ndarray,
    log_p: np.ndarray,
    log_q: np.ndarray,
    elite: np.ndarray,
    options: FitOptions,
    *,
    smoothing: float,
    weights: WeightMode = "frozen",
    n_factors: int | None = None,
    step_mask: np.ndarray | None = None,
) -> list[float]:
    """One cross-entropy stage: minimise ``-sum_i w_i^alpha 1[elite_i] sum_t log q_phi(a_t | d_t)``, in place.

    Args:
        proposal: the proposal q_phi fitted, in place.
        inputs: [N, T] (or [N, T, k]) the proposal inputs of the stage's rollouts.
        detected: bool [N, T] their detections.
        log_p: float64 [N, T] each action's log-probability under the PEM (nats).
        log_q: float64 [N, T] each action's log-probability under the proposal that sampled them (nats).
        elite: bool [N], robustness <= gamma_kappa.
        options: the fit's settings; ``weights = "recomputed"`` always fits every step, in float64.
        smoothing: alpha in (0, 2], the power on the importance weights.
        weights: ``"frozen"``: w from the proposal that sampled the batch (textbook CE, paper eq. 10-11);
            ``"recomputed"``: w from the current q_phi with the gradient flowing through it (authors' code).
        n_factors: steps in each weight (default T - 1: the last action affects nothing).
        step_mask: bool [N, T] or None: steps that count, in the weights and in the fit (False: left out,
            e.g. outside the proposal's window or after the failure).
    Returns:
        the loss per epoch (per L-BFGS evaluation). The weights are divided by their largest value (a
        constant factor, to which Adam's steps are invariant), so that w^alpha never overflows.
    Raises:
        ValueError: if there is no elite rollout."""
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
        rows, actions = inputs[idx][mask], detected[idx][mask]
        log_w = np.broadcast_to(scaled[:, None], mask.shape)[mask]
        return fit_elite_steps(proposal, rows, actions, log_w, float(scaled.max()), options)
    if weights == "frozen":
        scaled = smoothing * frozen_log_w
        step_w = np.exp(scaled - scaled.max())[:, None] * mask
        if not options.summed(int(np.count_nonzero(step_w))):
            return _subsampled_fit(proposal, inputs[idx], detected[idx], np.broadcast_to(step_w, mask.shape), options)
        uniq, counts, _ = _action_counts(inputs[idx], detected[idx], step_w[:, 0])
        return fit_proposal(proposal, uniq, counts, *options.args, dtype=options.dtype)
    # w depends on q_phi: per-rollout sums of log q over the first k steps, through the gradient.
    uniq, _, inverse = _action_counts(inputs[idx], detected[idx])
    slot = inverse * 2 + detected[idx].astype(np.int64)
    return fit_proposal(proposal, uniq, recomputed_objective(slot, lp, mask, k, smoothing), *options.args)


def recomputed_objective(
    slot: np.ndarray, log_p: np.ndarray, mask: np.ndarray, n_factors: int, smoothing: float
) -> Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]:
    """The CE loss with importance weights recomputed from the current proposal (the authors' code), as a
    :data:`pemviz.core.fit_settings.Objective`: ``-sum_i w_i(phi) sum_t m_it log q_phi(a_it | d_it)`` with
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
    Source: Innes & Ramamoorthy 2022, eq. 10-11, with the weights differentiated as in the authors' code."""
    from pemviz.core.torch_use import torch_module

    torch = torch_module()
    slot_t, lp_t = torch.as_tensor(slot), torch.as_tensor(log_p)
    mask_t = torch.as_tensor(mask, dtype=torch.float64)
    mask_k = torch.zeros_like(mask_t)
    mask_k[:, :n_factors] = 1.0

    def loss(log_q: Tensor) -> tuple[Tensor, Tensor]:
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
    options: FitOptions,
    n_steps: int | None = None,
) -> list[float]:
    """The frozen-weight CE fit on the elites' fitted steps: minimise ``-sum_s w_s log q_phi(a_s | h_s)``, in place.

    Args:
        proposal: the proposal q_phi fitted, in place.
        rows: float64 [S] or [S, k] proposal inputs of the steps that count (the elites', inside the step mask), in
            the order drawn (rollout by rollout, step by step).
        actions: bool [S] their detections.
        log_w: float64 [S] each step's weight in log space (nats): alpha times its rollout's importance log-weight.
        log_w_max: the largest rollout log-weight (alpha log w_i) of the elites; the weights are divided by its
            exponential (a constant factor, to which Adam's steps are invariant), so that none overflows.
        options: the fit's settings.
        n_steps: the steps these rows stand for (default S; more once they were thinned as they came).
    Returns:
        the loss per epoch (per L-BFGS evaluation).
    Source: Innes & Ramamoorthy 2022, eq. 10-11 (the CE update), summed over distinct inputs. With no step to fit
    (the elites never entered the step mask) the proposal stays as it is and the loss list is empty."""
    if np.shape(actions)[0] == 0:
        return []
    w = libm.exp(np.asarray(log_w, dtype=np.float64) - log_w_max)[None]
    rows, actions = np.asarray(rows)[None], np.asarray(actions, dtype=bool)[None]
    if not options.summed(int(np.count_nonzero(w)) if n_steps is None else n_steps):
        return _subsampled_fit(proposal, rows, actions, w, options)
    uniq, counts, _ = _action_counts(rows, actions, w, drop_unweighted=True)
    # with a tolerance, from the last stage's fit (a warm start): stop once the loss per step stops falling
    per = None if options.tolerance is None else float(counts.sum())
    return fit_proposal(proposal, uniq, counts, *options.args, options.tolerance, per=per, dtype=options.dtype)


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
            (until a thinning)."""

    def __init__(
        self,
        grid: np.ndarray,
        max_rows: int | None,
        rng: np.random.Generator,
        thin_above: int | None = None,
        keep_observations: bool = False,
    ) -> None:
        self.grid, self.max_rows, self.rng = grid, max_rows, rng
        self.thin_above = None if max_rows is None else (thin_above or 20 * max_rows)
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.keep_observations = keep_observations
        self.observations: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]] = []
        """With ``keep_observations``, per part: the events' object rows [S, G], whether each counts in its
        rollout's weight, bool [S], and their measurement errors [S, D] (None: none)."""
        self.counts, self.hits = np.zeros(grid.size), np.zeros(grid.size)
        self.n_rollouts, self.n_steps, self.held, self.thinned = 0, 0, 0, False
        self.log_w_max = -np.inf

    def add(
        self,
        index: np.ndarray,
        batch: RolloutBatch,
        features: np.ndarray,
        mask: np.ndarray,
        log_w: np.ndarray,
        weighted: np.ndarray | None = None,
    ) -> None:
        """Elite rollouts ``index`` [m] of the stage: the features of their object events [m, S(, k)] (S = T M,
        :meth:`~pemviz.core.rollouts.RolloutBatch.events`), the events' mask bool [m, S], smoothed log-weights alpha
        log w_i [m] and (``keep_observations``) the events of ``mask`` whose steps count in the weights, bool [m, S]
        (None: all)."""
        if index.size == 0:
            return
        c, h = elite_counts(batch, np.ones(batch.n, bool), self.grid)
        self.counts, self.hits = self.counts + c, self.hits + h
        rows, detected = batch.events()
        order = np.broadcast_to(np.asarray(index)[:, None], mask.shape)[mask]
        self.parts.append((order, features[mask], detected[mask], np.broadcast_to(log_w[:, None], mask.shape)[mask]))
        if self.keep_observations:
            noise = None if batch.noise is None else batch.noise.reshape(batch.n, -1, batch.noise.shape[-1])[mask]
            self.observations.append(
                (rows[mask], np.ones(int(mask.sum()), bool) if weighted is None else weighted[mask], noise)
            )
        self.n_rollouts += index.size
        self.n_steps += int(mask.sum())
        self.held += int(mask.sum())
        self.log_w_max = max(self.log_w_max, float(np.max(log_w)))
        if self.thin_above is not None and self.held > self.thin_above:
            self._thin()

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rows [S(, k)], actions [S], log-weights [S]) in the order drawn."""
        order, rows, actions, log_w = (np.concatenate(a) for a in zip(*self.parts, strict=False))
        if len(self.parts) > 1 and not self.thinned:
            by = np.argsort(order, kind="stable")
            rows, actions, log_w = rows[by], actions[by], log_w[by]
        return rows, actions, log_w

    def _thin(self) -> None:
        assert self.max_rows is not None  # thinned only above thin_above, set with max_rows
        rows, actions, log_w = self.arrays()
        top = float(log_w.max())
        uniq, counts = weighted_steps(rows[None], actions[None], np.exp(log_w - top)[None], self.max_rows, self.rng)
        hit = counts > 0  # [U, 2]: (miss, detect) weights of each distinct input
        slot, action = np.nonzero(hit)
        with np.errstate(divide="ignore"):
            self.parts = [
                (np.zeros(slot.size, np.int64), uniq[slot], action.astype(bool), np.log(counts[slot, action]) + top)
            ]
        self.held, self.thinned = slot.size, True
        self.observations, self.keep_observations = [], False  # the steps no longer belong to rollouts: no reweighting

    def reweight(self, log_weight: Callable[..., np.ndarray]) -> bool:
        """Give every held step a new log-weight: ``log_weight(rollout [S], observations [S, F], actions [S],
        counts [S], noise [S, D] or None)`` -> [S] (nats), each step's rollout, whether the step counts in the
        rollout's weight, and its measurement error.

        Returns:
            False (nothing changed) without ``keep_observations`` or once thinned: the steps then no longer
            belong to whole rollouts."""
        if not self.keep_observations or self.thinned or not self.parts:
            return False
        order, rows, actions, _ = (np.concatenate(a) for a in zip(*self.parts, strict=False))
        obs, counts = (np.concatenate([o[i] for o in self.observations]) for i in (0, 1))
        noise = None if self.observations[0][2] is None else np.concatenate([o[2] for o in self.observations])
        by = np.argsort(order, kind="stable")  # rollout by rollout, step by step: the order drawn
        order, rows, actions, obs, counts = order[by], rows[by], actions[by], obs[by], counts[by]
        noise = None if noise is None else noise[by]
        log_w = np.asarray(log_weight(order, obs, actions, counts, noise), dtype=np.float64)
        self.parts, self.observations = [(order, rows, actions, log_w)], [(obs, counts, noise)]
        self.log_w_max = float(np.max(log_w, initial=-np.inf))  # -inf: no step held
        return True

    def fit(self, proposal: Proposal, options: FitOptions) -> list[float]:
        """:func:`fit_elite_steps` on the gathered steps."""
        rows, actions, log_w = self.arrays()
        return fit_elite_steps(
            proposal, rows, actions, log_w, self.log_w_max, options, self.n_steps if self.thinned else None
        )


def break_ties(
    robustness: np.ndarray,
    gamma: float,
    quantile_level: float,
    rng: np.random.Generator,
    n: int | None = None,
    settled: int = 0,
) -> np.ndarray:
    """bool [M]: every rollout below gamma plus randomly chosen ties at gamma up to ceil((1 - sigma) N) elites.

    At gamma = 0 (the failure threshold) this keeps all failures (r < 0) and admits a non-failing rollout
    with r = 0 only to reach ceil((1 - sigma) N) elites. ``n``: N, the stage's rollouts, when ``robustness``
    holds only some of them (:class:`~pemviz.estimators.base.EliteCandidates`: every one at or below gamma);
    default M. ``settled``: rollouts below gamma already taken as elites and not in ``robustness``."""
    k = elite_count(robustness.size if n is None else n, quantile_level)
    below = robustness < gamma
    ties = np.flatnonzero(robustness == gamma)
    elite = below.copy()
    elite[rng.permutation(ties)[: max(0, k - int(below.sum()) - settled)]] = True
    return elite


def new_proposal(inputs: str, h_scale: float, pretrain: RolloutBatch) -> Proposal:
    """The cross-entropy sampler's first proposal (before its pretraining fit): the paper's gap-only one (``inputs =
    "gap"``), or a :class:`~pemviz.core.sampling.StateProposal` over every column of the object rows (``"state"``): the
    first (the gap) scaled by the problem's ``h_scale`` (metres), the other columns by their largest magnitude in the
    pretraining rollouts; its curve holds them at the first row drawn. It samples in exact arithmetic
    (:meth:`~pemviz.core.sampling.Proposal.detect_logit`), whatever the fits' precision."""
    if inputs == "gap":
        return Proposal(h_scale)
    rows, _ = pretrain.events()
    scales = [h_scale] + [float(np.max(np.abs(rows[:, :, j]))) or 1.0 for j in range(1, rows.shape[2])]
    return StateProposal(tuple(range(rows.shape[2])), tuple(scales), tuple(rows[0, 0]))
