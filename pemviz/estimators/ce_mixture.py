"""The importance weights of a cross-entropy stage drawn from a mixture of samplers: a stage's rollouts weighed
under the mixture over whole rollouts it was drawn from, from the components' log-probabilities the simulation kept
(asked again where it could not keep them), and the failure pool's rollouts weighed under the samplers of every stage
in the pool (``fit_weights = "mixture"``). :class:`MixtureWeights` holds these methods of
:class:`~pemviz.estimators.cross_entropy.CrossEntropy`, which inherits them."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, cast

import numpy as np

from pemviz.core.detector_noise import noise_names_of
from pemviz.core.detectors import (
    Detector,
    NoisyDetector,
    action_log_prob,
    errors_log_density,
)
from pemviz.core.odd_proposal import parameter_log_ratio
from pemviz.core.rng import RQMC_BLOCK
from pemviz.core.rollouts import RolloutBatch
from pemviz.core.scored_target import ScoredTarget, by_rollout
from pemviz.estimators.base import StagePlan, masked_log_weight, mixture_log_weight, weighted_steps_mask

if TYPE_CHECKING:
    from pemviz.config import ExperimentConfig
    from pemviz.core.problems import Problem
    from pemviz.core.sampling import Proposal


class MixtureWeights:
    """The mixture weights of :class:`~pemviz.estimators.cross_entropy.CrossEntropy`, which keeps the state they read
    (``problem``, the planned stage ``_plan``, its scoring target ``_scored``, the proposal, the failure pool's samplers
    and log-probabilities) and the methods they call (``_around``, ``_smoothing``)."""

    # the state of CrossEntropy these methods read (set by its __init__, :mod:`pemviz.estimators.cross_entropy`)
    problem: Problem
    config: ExperimentConfig
    proposal: Proposal | None
    _plan: StagePlan | None
    _scored: ScoredTarget | None
    _seen: int
    _pool_start: int | None
    _stage_samplers: dict[int, tuple[tuple[int, Detector], ...]]
    _pool_log_q: dict[object, np.ndarray]
    _stacked: tuple[np.ndarray, np.ndarray] | None = None
    """The last batch's ``log_q_parts`` [N, K, T] (:meth:`_with_parts`) and the array it is a view of, [N, 1 + K, T]:
    its log p in slot 0, so that :meth:`_mixture_log_weight` sums all K + 1 in one pass."""

    if TYPE_CHECKING:  # CrossEntropy's methods these call

        def _around(
            self, mixture: tuple[tuple[int, Detector], ...], proposal: Proposal
        ) -> tuple[tuple[int, Detector], ...]: ...

        def _smoothing(self, gamma: float) -> float: ...

    def _mixture_log_weight(self, batch: RolloutBatch, mask: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """log p(x) - log sum_k c_k q_k(x) over the steps of ``mask`` (bool [N, T]; with ``rows``, int [R], of those
        rollouts only: [R, T]) for rollouts of the planned stage's mixture
        (:func:`~pemviz.estimators.base.mixture_log_weight`), float64 [N] or [R] (nats), from the components'
        log-probabilities the batch carries (:meth:`_with_parts`)."""
        plan, pb, scored, log_q_parts = self._plan, self.problem, self._scored, batch.log_q_parts
        assert plan is not None and scored is not None, "a mixture stage is planned (_open)"
        assert log_q_parts is not None, "the batch has its components' log-probabilities (_with_parts)"
        pick = slice(None) if rows is None else rows
        stacked = self._stacked
        if stacked is not None and stacked[0] is log_q_parts:  # log p and the parts side by side: one product
            sums = (stacked[1][pick] * mask[:, None, :]).sum(axis=2)  # each [T] row summed as (x * mask).sum(axis=1)
            log_p, by_part = sums[:, 0], sums[:, 1:].T
        else:
            log_p = (batch.log_p[pick] * mask).sum(axis=1)
            by_part = [(log_q_parts[pick, k] * mask).sum(axis=1) for k in range(log_q_parts.shape[1])]
        extras = scored.extras
        log_q = [log_p if d is pb.target else by_part[extras.index(d)] for _, d in plan.mixture]
        for k, (_, d) in enumerate(plan.mixture):  # over an ODD: its density of the parameters, relative to the ODD's
            ratio = None if d is pb.target else parameter_log_ratio(d, batch)
            if ratio is not None:
                log_q[k] = log_q[k] + ratio[pick]
        return mixture_log_weight(log_p, np.stack(log_q), np.array([k for k, _ in plan.mixture]) / plan.n)

    def _whole_log_weight(self, batch: RolloutBatch) -> np.ndarray:
        """Each rollout's importance log-weight [N] (nats) over the steps that count (:func:`weighted_steps_mask`):
        under the planned stage's mixture where it is one, else its own sampler's."""
        assert self._plan is not None, "a stage is planned (_open)"
        whole = weighted_steps_mask(self.problem, batch, self.config.weights_until_failure)
        return self._mixture_log_weight(batch, whole) if self._plan.mixture else masked_log_weight(batch, whole)

    def _with_parts(self, batch: RolloutBatch) -> RolloutBatch:
        """``batch`` (the planned mixture stage's next rollouts) with ``log_q_parts`` [N, K, T]: the log-probabilities
        of its events under the mixture's proposal components (:attr:`ScoredTarget.extras`), as the simulation asked
        them, or asked again where it could not keep them (Ray tasks; :meth:`_ask_again`)."""
        scored = self._scored
        assert scored is not None, "a mixture stage is planned (_open)"
        start, self._seen = self._seen, self._seen + batch.n
        m = batch.n_objects
        simple = m == 1 and batch.noise is None  # one object, no measurement error
        own = self._drawn_by(start, batch.n) if simple else None
        groups = scored.take(batch.n, batch.n_steps, m, skip=own)
        stacked = np.empty((batch.n, len(scored.extras) + 1, batch.n_steps))
        stacked[:, 0] = batch.log_p
        parts = stacked[:, 1:]
        if groups is not None and simple:
            self._parts_as_asked(batch, groups, stacked, own)
        else:
            logits = (
                self._ask_again(batch, start) if groups is None else by_rollout(groups, batch.n, m)[0] if groups else ()
            )
            for k, lg in enumerate(logits):  # [N, T, M]
                lq = action_log_prob(lg, batch.detected)
                parts[:, k] = lq[..., 0] if m == 1 else lq.sum(axis=2)
        if batch.noise is not None:  # each component's density of the detected objects' measurement errors
            for k, d in enumerate(scored.extras):
                parts[:, k] += errors_log_density(batch, d, self.problem.target)
        self._stacked = (parts, stacked)
        return dataclasses.replace(batch, log_q_parts=parts)

    @staticmethod
    def _parts_as_asked(
        batch: RolloutBatch, groups: list[tuple[int, np.ndarray]], stacked: np.ndarray, own: int | None
    ) -> None:
        """Fill ``stacked[:, 1:]`` [N, K, T] with the components' densities of one-object rollouts from the logits the
        simulation asked (:meth:`ScoredTarget.take`, step-major): component ``own`` drew them, so its densities are
        their log q as drawn (the same bits); the others' are the target's log p where they give way to the target
        (outside their window), else computed there (the components usually differ on the same steps: found once)."""
        for k in range(stacked.shape[1] - 1):
            stacked[:, k + 1] = batch.log_q if k == own else batch.log_p
        detected = batch.detected[..., 0]
        for row, block in groups:
            where: tuple[np.ndarray, ...] | None = None
            for k in range(block.shape[0] - 1):
                if k == own:
                    continue
                differ = block[k + 1] != block[0]  # [T, r]: step-major, as asked (each entry its own density)
                if where is None or not np.array_equal(where[0], differ):
                    t, i = np.nonzero(differ)
                    i += row
                    where = (differ, i, t, detected[i, t])
                _, i, t, taken = where
                stacked[i, k + 1, t] = action_log_prob(block[k + 1][differ], taken)

    def _drawn_by(self, start: int, n: int) -> int | None:
        """The index among :attr:`ScoredTarget.extras` of the component that drew rollouts ``start .. start + n - 1``
        of the planned mixture stage (drawn component after component, :attr:`StagePlan.parts`), or None: the
        target, or rollouts of more than one component."""
        plan, scored = self._plan, self._scored
        assert plan is not None and scored is not None, "a mixture stage is planned (_open)"
        lo = 0
        for k, d in plan.mixture:
            if lo <= start and start + n <= lo + k:
                return scored.extras.index(d) if d in scored.extras else None
            lo += k
        return None

    def _ask_again(self, batch: RolloutBatch, start: int) -> np.ndarray:
        """The extras' logits [K, N, T, M] of rollouts ``start .. start + N - 1`` of the stage, asked as a simulator
        asks them: one step at a time about the object rows of one block (:data:`pemviz.core.rng.RQMC_BLOCK`) of
        rollouts of one mixture component, so that the proposal network sees the same rows and gives the same bits as it
        gave there."""
        plan, n, n_steps, m = self._plan, batch.n, batch.n_steps, batch.n_objects
        assert plan is not None and self._scored is not None, "a mixture stage is planned (_open)"
        assert self.proposal is not None, "a mixture stage comes after the pretraining fit"
        rebuilt = dict(
            zip(
                (id(d) for _, d in plan.mixture),
                (d for _, d in self._around(plan.mixture, self.proposal)),
                strict=False,
            )
        )
        extras = [rebuilt[id(d)] for d in self._scored.extras]
        logits = np.empty((len(extras), n, n_steps, m))
        object_rows = batch.object_rows
        edges = np.cumsum([0] + [k for k, _ in plan.mixture])
        # each component's rollouts, drawn one block after another
        for lo, hi in zip(edges[:-1], edges[1:], strict=False):
            for b0 in range(int(lo), int(hi), RQMC_BLOCK):
                a, b = max(b0, start), min(b0 + RQMC_BLOCK, int(hi), start + n)
                if a >= b:
                    continue
                rows = slice(a - start, b - start)
                for t in range(n_steps):
                    obs = object_rows[rows, t].reshape((b - a) * m, -1)
                    for j, d in enumerate(extras):
                        logits[j, rows, t] = np.asarray(d.detect_logit(obs)).reshape(b - a, m)
        return logits

    def _pool_log_weight(
        self,
        rollout: np.ndarray,
        obs: np.ndarray,
        actions: np.ndarray,
        counts: np.ndarray,
        noise: np.ndarray | None = None,
    ) -> np.ndarray:
        """alpha log w of each step's rollout [S] (nats) for ``fit_weights = "mixture"``: w = p(x) / sum_j c_j q_j(x)
        over the samplers q_j of every stage in the failure pool, c_j their shares of its rollouts (the balance
        heuristic over all stages, the deterministic-mixture weight of adaptive multiple importance sampling:
        Cornuet, Marin, Mira & Robert, "Adaptive multiple importance sampling", Scand. J. Stat. 39(4), 2012;
        Owen & Zhou, "Safe and effective importance sampling", JASA 2000), over the steps that count (``counts``).
        Arguments as :meth:`EliteSteps.reweight` passes them; S may be 0 (every elite failed at its first step)."""
        pb, plan, pool_start = self.problem, self._plan, self._pool_start
        assert plan is not None and pool_start is not None, "the failure pool has started (CrossEntropy.finish)"
        ids, inverse = np.unique(rollout, return_inverse=True)
        if ids.size == 0:  # no step held (every elite failed before its first action): no weight to give
            return np.empty(0)

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
                if noise is not None:  # and its density of the detected objects' errors
                    errors = cast(NoisyDetector, detector if noise_names_of(detector) else pb.target)
                    hit = counts[steps] & actions[steps]
                    step = step + np.where(hit, errors.noise_log_prob(obs[steps], noise[steps]), 0.0)
                known[ids[todo]] = np.bincount(inverse[steps], weights=step, minlength=ids.size)[todo]
            return known[ids]

        log_p = log_prob("target", pb.target)
        parts = [
            (k, i, n, d) for k in range(pool_start, plan.stage + 1) for i, (n, d) in enumerate(self._stage_samplers[k])
        ]
        log_q = np.stack([log_p if d is pb.target else log_prob((k, i), d) for k, i, _, d in parts])
        shares = np.array([n for _, _, n, _ in parts], dtype=np.float64)
        log_w = mixture_log_weight(log_p, log_q, shares / shares.sum())
        return (self._smoothing(0.0) * log_w)[inverse]
