"""What every estimator shares: the interface the engine drives, importance weights up to the failure step, and the
per-rollout numbers of a stage. An estimator states its run (:class:`RunPlan`), plans each batch
(:class:`StagePlan`), is shown its rollouts (:meth:`Estimator.observe`), closes the stage (:meth:`Estimator.finish`)
and gives the answer (:meth:`Estimator.result`); the engine does simulation, robustness, events and cancellation."""

from __future__ import annotations

import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import numpy as np

from pemviz import stl
from pemviz.config import ExperimentConfig
from pemviz.core import libm
from pemviz.core.detectors import Detector
from pemviz.core.estimate import Estimate, estimate
from pemviz.core.plan import RunPlan
from pemviz.core.problems import Problem
from pemviz.core.rollouts import RolloutBatch
from pemviz.estimators.pooling import pool

Check = Callable[[], None]
"""Called between and inside fits; raises to abandon the run (the engine's cancel token)."""


@dataclass(frozen=True)
class StagePlan:
    """The next batch an estimator wants drawn.

    Attributes:
        stage: 0 = pretraining, 1..K = CE stages, K+1 = the final batch (1 for a single-batch estimator).
        kind: ``pretrain`` | ``ce`` | ``final`` | ``ams``.
        n: rollouts.
        sampler: the detector that draws them (q); the problem's target (p) weighs them.
        draw: None (the engine simulates ``n`` rollouts from ``sampler``) or ``draw(rng) -> RolloutBatch``, the
            estimator's own (AMS).
        mixture: a defensive mixture over whole rollouts, ``((n_1, detector_1), ...)`` summing to n, each rollout
            weighing p / sum_k (n_k / n) q_k (:func:`mixture_log_weight`); empty: all from ``sampler``.
        target: None (the problem's target) or a detector with the same logits that keeps more
            (:class:`pemviz.core.scored_target.ScoredTarget`)."""

    stage: int
    kind: str
    n: int
    sampler: Detector
    draw: Callable[[np.random.Generator], RolloutBatch] | None = None
    mixture: tuple[tuple[int, Detector], ...] = ()
    target: Detector | None = None

    @property
    def parts(self) -> list[tuple[int, Detector]]:
        """(rollouts, detector) in the order drawn, none empty."""
        return [(k, d) for k, d in (self.mixture or ((self.n, self.sampler),)) if k > 0]


@dataclass(frozen=True)
class StageOutcome:
    """What a stage gave: its threshold, elites, estimate and the proposal after its fit."""

    gamma: float
    """Stage threshold gamma_kappa (nan for pretraining and final batches)."""
    n_elites: int
    estimate: Estimate
    proposal_curve: np.ndarray
    """q(detect | d) on the problem's ``curve_grid`` after the stage, float64 [G] (nan without a proposal)."""
    elite_detect_rate: np.ndarray
    """Elite rollouts' empirical detection rate per bin of the ``curve_grid`` (nan where empty), [G]."""


class OwnsSettings:
    """An estimator that owns its settings, as a scikit-learn estimator owns its parameters: :attr:`SETTINGS` names
    the :class:`~pemviz.config.ExperimentConfig` fields it reads besides the run-level ones
    (:func:`pemviz.settings.settings_of`; :data:`pemviz.settings.SETTINGS` says what each one is), :meth:`get_params`
    gives their values."""

    SETTINGS: ClassVar[tuple[str, ...]] = ()
    config: ExperimentConfig

    def get_params(self) -> dict[str, Any]:
        """This estimator's settings and their values (``name -> value``, in :attr:`SETTINGS` order)."""
        return {name: self.config.value(name) for name in self.SETTINGS}


class Estimator(Protocol):
    """A rare-event estimator as the engine drives it: ``while (plan := next_stage())``: draw ``plan.n`` rollouts
    from ``plan.sampler``, ``observe`` them (in one or more chunks), ``finish`` the stage; then ``result``.

    ``rng`` is the stream the rollouts' detections are drawn from (the estimator seeds it, with its other streams)."""

    rng: np.random.Generator

    def plan(self) -> RunPlan:
        """The run's stages, as they will be drawn (stated before the first)."""
        ...

    def next_stage(self) -> StagePlan | None:
        """The next batch to draw, or None when the estimate is complete."""
        ...

    def observe(self, batch: RolloutBatch, failed: np.ndarray, robustness: np.ndarray | None) -> np.ndarray:
        """Take (a chunk of) the planned batch; returns its importance log-weights [N] (nats).

        ``failed``: bool [N] (classic robustness < 0); ``robustness``: [N] under the configured metric. A stage of
        many rollouts comes in chunks, in the order drawn: keep per-rollout numbers, not the chunks."""
        ...

    def finish(self) -> StageOutcome:
        """Close the planned stage: thresholds, elites, the proposal's fit, the stage's estimate."""
        ...

    def result(self) -> tuple[Estimate, tuple[int, ...]]:
        """The run's estimate and the stages whose rollouts it uses."""
        ...


def failure_steps(problem: Problem, batch: RolloutBatch, level: float = 0.0) -> np.ndarray:
    """The step at which each rollout fails, int [N] (T when it does not): :func:`pemviz.stl.first_violation` of
    the problem's safety formula on the batch's signals (robustness of the operand <= ``level``; < 0 at level 0).

    Raises:
        ValueError: if the formula is not ``G[a,b](operand)`` with a time-free operand (horizon 0)."""
    global _LAST_FAILURE_STEPS
    known = _LAST_FAILURE_STEPS  # read once: another thread may replace it
    if known is not None and known[0]() is batch.observations and known[1] is problem and known[2] == level:
        return known[3]
    steps = stl.first_violation(problem.formula, problem.signal_arrays(batch), level)
    steps.flags.writeable = False
    _LAST_FAILURE_STEPS = (weakref.ref(batch.observations), problem, level, steps)
    return steps


_LAST_FAILURE_STEPS: tuple | None = None
"""(a weak reference to a batch's observations, the problem, the level, its :func:`failure_steps`): an estimator asks
for the same rollouts' failure steps two or three times (their weights, their NLL, their fitted steps), and a batch
given its mixture's densities (``dataclasses.replace``) keeps its observations array."""


def log_weight(problem: Problem, batch: RolloutBatch, until_failure: bool) -> np.ndarray:
    """Importance log-weights sum_t log p(a_t | s_t) - log q(a_t | s_t), float64 [N] (nats; Innes & Ramamoorthy
    2022, eq. 6): over the first T - 1 steps (the last action affects nothing), or with ``until_failure`` over
    the steps before the failure step, where later actions change nothing either.

    Raises:
        ValueError: ``until_failure`` with a formula :func:`failure_steps` cannot read."""
    if not until_failure:
        return batch.log_weight()
    return masked_log_weight(batch, weighted_steps_mask(problem, batch, until_failure))


def masked_log_weight(batch: RolloutBatch, mask: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
    """sum_t log p - log q over the steps of ``mask`` (bool [N, T]; with ``rows``, int [R], of those rollouts only:
    [R, T]), less the parameters' term over an ODD (:attr:`~pemviz.core.rollouts.RolloutBatch.log_q_params`), float64
    [N] or [R] (nats); a step the mask drops may hold -inf - -inf (an action after the failure), never summed."""
    pick = slice(None) if rows is None else rows
    with np.errstate(invalid="ignore"):
        log_w = np.where(mask, batch.log_p[pick] - batch.log_q[pick], 0.0).sum(axis=1)
    return log_w if batch.log_q_params is None else log_w - batch.log_q_params[pick]


def weighted_steps_mask(problem: Problem, batch: RolloutBatch, until_failure: bool) -> np.ndarray:
    """bool [N, T]: the steps whose actions enter the importance weight (:func:`log_weight`): the first T - 1, or
    with ``until_failure`` those before the failure step too."""
    k = np.full(batch.n, batch.n_steps - 1)
    if until_failure:
        k = np.minimum(failure_steps(problem, batch), k)
    return np.arange(batch.n_steps)[None, :] < k[:, None]


def look_ahead_weights(
    problem: Problem, batch: RolloutBatch, weigh: Weigh | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The conditional Monte Carlo weights of the problem's look-ahead
    (:attr:`pemviz.core.problems.Problem.look_ahead`; None without one): (log w_i + log V_i where V_i > 0, else log
    w_i; V_i > 0; log w_i), [N] each in nats, w_i the weight before rollout i's start and V_i = P(failure | its
    state there), so E_q[w V] = p."""
    if problem.look_ahead is None:
        return None
    start, log_v = problem.look_ahead(batch)
    mask = np.arange(batch.n_steps)[None, :] < np.minimum(start, batch.n_steps - 1)[:, None]
    log_w = weigh(mask) if weigh is not None else masked_log_weight(batch, mask)
    reach = np.isfinite(log_v)
    return np.where(reach, log_w + np.where(reach, log_v, 0.0), log_w), reach, log_w


def mixture_log_weight(log_p: np.ndarray, log_q: np.ndarray, shares: np.ndarray) -> np.ndarray:
    """Importance log-weights of rollouts drawn from a mixture of K samplers, float64 [N] (nats): ``log p(x) - log
    sum_k c_k q_k(x)``, the balance heuristic (Veach & Guibas, SIGGRAPH 1995); with the target among the q_k at
    share c every weight is at most 1 / c (Hesterberg, Technometrics 1995; Owen & Zhou, "Safe and effective
    importance sampling", JASA 2000).

    Args:
        log_p: log p(x) of each rollout under the target, float64 [N] (nats, over the weighted steps).
        log_q: log q_k(x) of each rollout under each sampler, float64 [K, N] (nats, the same steps).
        shares: c_k >= 0, [K], summing to 1."""
    with np.errstate(divide="ignore"):
        log_c = libm.log(np.asarray(shares, dtype=np.float64))[:, None]
    return np.asarray(log_p, dtype=np.float64) - libm.logsumexp(log_c + np.asarray(log_q, dtype=np.float64), axis=0)


def log_p_before_failure(problem: Problem, batch: RolloutBatch) -> np.ndarray:
    """sum_{t < t_fail} log p_target(a_t | s_t), float64 [N] (nats), for the NLL of the failures: the actions
    before the failure step whatever the sampler, so that the NLLs of every preset compare (T - 1 steps for a
    rollout that does not fail, or when the safety formula is not ``G[a,b](state predicate)``)."""
    try:
        k = np.minimum(failure_steps(problem, batch), batch.n_steps - 1)
    except ValueError:
        k = np.full(batch.n, batch.n_steps - 1)
    return np.where(np.arange(batch.n_steps)[None, :] < k[:, None], batch.log_p, 0.0).sum(axis=1)  # -inf after


class SeenFailures:
    """The probability of the distinct failures a run has drawn: a lower bound of p, whatever the samplers. Where
    the detections are a rollout's only randomness and its start is fixed, each distinct failing prefix of
    detections is a disjoint event of probability prod_{t < t_f} p(a_t | s_t) that implies the failure; at most
    :data:`KEEP` of the likeliest are kept."""

    KEEP: ClassVar[int] = 20_000

    def __init__(self) -> None:
        self._log_p: dict[bytes, float] = {}
        self.applies = True
        """False once a batch has measurement errors or a formula without a failure step: no bound then."""

    def add(self, problem: Problem, batch: RolloutBatch, failed: np.ndarray) -> None:
        """Record the failing rollouts of ``batch`` (``failed`` bool [N]). Over an operating design domain
        (``problem.odd``) the bound does not apply: a path's probability there also holds its parameters' law."""
        if not self.applies or not failed.any():
            return
        if batch.noise is not None or getattr(problem, "odd", None) is not None:
            self.applies = False
            return
        try:
            steps = failure_steps(problem, batch)
        except ValueError:
            self.applies = False
            return
        rows = np.flatnonzero(failed)
        log_p = log_p_before_failure(problem, batch)[rows]
        k = steps[rows]
        detected = batch.detected.reshape(batch.n, batch.n_steps, -1)[rows]
        detected = detected & (np.arange(batch.n_steps)[None, :, None] < k[:, None, None])  # the prefix before t_f
        keys = np.concatenate(
            [np.packbits(detected.reshape(rows.size, -1), axis=1), k.astype("<u4").view(np.uint8).reshape(-1, 4)],
            axis=1,
        )
        # each prefix once per batch, in the order of its bytes: one bytes object per distinct row, made by numpy
        as_bytes = np.ascontiguousarray(keys).view(f"V{keys.shape[1]}").ravel()
        distinct, first = np.unique(as_bytes, return_index=True)
        self._log_p.update(zip(distinct.tolist(), log_p[first].tolist(), strict=False))
        if len(self._log_p) > 2 * self.KEEP:  # the KEEP most likely, ties in the order seen
            values = np.fromiter(self._log_p.values(), float, len(self._log_p))
            order = np.argsort(-values, kind="stable")[: self.KEEP]
            held = list(self._log_p)
            self._log_p = {held[i]: float(values[i]) for i in order.tolist()}

    @property
    def log_p(self) -> float | None:
        """log of the sum of p over the distinct failing prefixes seen (nats), or None: none seen, or no bound."""
        if not self.applies or not self._log_p:
            return None
        return float(libm.logsumexp(np.fromiter(self._log_p.values(), float)))


def elite_counts(batch: RolloutBatch, elite: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Object events of the elite rollouts per bin of ``grid`` (nearest grid value of each object row's first
    column, the window's: e.g. the braking scenario's gap) and the detections among them, float64 [G] each."""
    if batch.rows_elided:  # rebuild the elites' rows only
        d = batch.object_rows_of(elite)[..., 0].ravel()
    else:
        d = batch.object_rows[..., 0][elite].ravel()  # the first column, then the elites: no copy of the other columns
    a = batch.detected[elite].ravel()
    idx = np.searchsorted((grid[1:] + grid[:-1]) / 2, d, side="right")  # the bin whose midpoints bracket d
    counts = np.bincount(idx, minlength=grid.size).astype(float)
    hits = np.bincount(idx, weights=a.astype(float), minlength=grid.size)
    return counts, hits


def detect_rate(counts: np.ndarray, hits: np.ndarray) -> np.ndarray:
    """hits / counts per bin, nan where a bin is empty, float64 [G]."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, hits / np.maximum(counts, 1), np.nan)


Weigh = Callable[..., np.ndarray]
"""``weigh(mask, rows=None)``: the importance log-weights [N] (nats) of a batch over the steps of ``mask`` (bool
[N, T]; with ``rows``, int [R], of those rollouts only: [R] over a mask [R, T]), e.g. a mixture's
(:func:`mixture_log_weight`); None where the weights are sum (log p - log q) over the masked steps."""


def severity_arrays(
    problem: Problem,
    batch: RolloutBatch,
    failed: np.ndarray,
    until_failure: bool,
    log_w: np.ndarray,
    weigh: Weigh | None = None,
    log_p: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Per severity level of ``problem.severity``: each rollout's importance log-weight up to the step tau_x its
    event is decided (with ``until_failure``; else over the first T - 1), the event, and log p over the same steps;
    rollouts that miss the level keep ``log_w`` and ``log_p`` (None: :func:`log_p_before_failure`).

    Returns:
        (log-weights, events, log p), float64 / bool / float64 [L, N] (nats), or None: no severity scale, the
        signal missing from the batch, or a formula without a failure step."""
    scale = problem.severity
    if scale is None or not scale.levels:
        return None
    signal = problem.signal_arrays(batch).get(scale.signal)
    if signal is None:
        return None
    try:
        fail_step = failure_steps(problem, batch)
    except ValueError:
        return None
    from pemviz.core.severity import level_events

    hit, step = level_events(signal, failed, fail_step, np.asarray(scale.levels))
    n_steps = batch.n_steps
    last = np.minimum(step, n_steps - 1) if until_failure else np.full(step.shape, n_steps - 1)
    steps = np.arange(n_steps)[None, :]
    base_lp = log_p_before_failure(problem, batch) if log_p is None else log_p
    out_w, out_p = np.repeat(log_w[None, :], hit.shape[0], axis=0), np.repeat(base_lp[None, :], hit.shape[0], axis=0)
    for level, rows in enumerate(hit):
        rows = np.flatnonzero(rows)
        if rows.size == 0:
            continue
        mask = steps < last[level, rows][:, None]  # [n_hit, T]
        if weigh is not None:
            out_w[level, rows] = weigh(mask, rows)
        else:
            out_w[level, rows] = masked_log_weight(batch, mask, rows)
        out_p[level, rows] = np.where(mask, batch.log_p[rows], 0.0).sum(axis=1)
    return out_w, hit, out_p


def alternative_log_weights(
    problem: Problem, batch: RolloutBatch, failed: np.ndarray, until_failure: bool, log_w: np.ndarray
) -> np.ndarray | None:
    """Each failing rollout's importance log-weight under each of ``problem.alternatives`` (other PEMs, shifted PEMs:
    :mod:`pemviz.core.reweight`), float64 [K, N] (nats), or None without alternatives: ``log_w`` plus the detections'
    log-likelihood ratio over the same steps (:func:`pemviz.core.reweight.detection_log_ratios`). A rollout that does
    not fail keeps ``log_w``: it enters no estimate's sum, only the mean-weight check of its verdict."""
    alternatives = problem.alternatives
    if not alternatives:
        return None
    from pemviz.core.reweight import detection_log_ratios

    out = np.repeat(np.asarray(log_w, dtype=np.float64)[None, :], len(alternatives), axis=0)
    rows = np.flatnonzero(failed)
    if rows.size:
        mask = weighted_steps_mask(problem, batch, until_failure)[rows]
        detected = batch.detected.reshape(batch.n, batch.n_steps, -1)[rows]
        ratios = detection_log_ratios(
            problem.target, [a.detector for a in alternatives], batch.object_rows_of(rows), detected, mask
        )
        out[:, rows] = out[:, rows] + ratios
    return out


class StageRollouts:
    """The per-rollout numbers of one stage, gathered chunk by chunk: log-weights, failures, log p before the
    failure ([N] each), the same per severity level where the problem has a scale ([L, N] each;
    :func:`severity_arrays`), the log-weights under the problem's alternative PEMs ([K, N];
    :func:`alternative_log_weights`), and the failures' detections per bin of the curve grid."""

    def __init__(self, grid: np.ndarray) -> None:
        self.grid = grid
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.severity_parts: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = []
        self.alternative_parts: list[np.ndarray | None] = []
        self.counts, self.hits = np.zeros(grid.size), np.zeros(grid.size)

    def add(
        self,
        problem: Problem,
        batch: RolloutBatch,
        failed: np.ndarray,
        until_failure: bool,
        count_failures: bool = True,
        log_w: np.ndarray | None = None,
        weigh: Weigh | None = None,
    ) -> np.ndarray:
        """Add a chunk (``count_failures``: bin its failures' detections too); returns its log-weights [N]
        (``log_w``: given, e.g. by a mixture, :func:`mixture_log_weight`, with ``weigh`` the same over any steps;
        None: :func:`log_weight`)."""
        if log_w is None:
            log_w = log_weight(problem, batch, until_failure)
        log_p = log_p_before_failure(problem, batch)
        conditional = look_ahead_weights(problem, batch, weigh)
        self.parts.append((log_w, failed, log_p) if conditional is None else (*conditional[:2], log_p))
        self.severity_parts.append(severity_arrays(problem, batch, failed, until_failure, log_w, weigh, log_p))
        self.alternative_parts.append(alternative_log_weights(problem, batch, failed, until_failure, log_w))
        if count_failures:
            c, h = elite_counts(batch, failed, self.grid)
            self.counts, self.hits = self.counts + c, self.hits + h
        return log_w

    @property
    def n(self) -> int:
        """The stage's rollouts so far."""
        return sum(part[0].size for part in self.parts)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(log-weights, failed, log p before the failure), [N] each, over every chunk."""
        if len(self.parts) == 1:
            return self.parts[0]
        return tuple(np.concatenate(a) for a in zip(*self.parts, strict=False))  # type: ignore[return-value]

    def severity_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(log-weights, events, log p), [L, N] each over every chunk (:func:`severity_arrays`), or None where a chunk
        has none."""
        if not self.severity_parts or any(part is None for part in self.severity_parts):
            return None
        if len(self.severity_parts) == 1:
            return self.severity_parts[0]
        return tuple(
            np.concatenate(a, axis=1)  # type: ignore[return-value]
            for a in zip(*self.severity_parts, strict=False)
        )

    def alternative_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(log-weights under each alternative [K, N], failed [K, N], log p before the failure [K, N]) over every
        chunk (:func:`alternative_log_weights`), or None where a chunk has none."""
        if not self.alternative_parts or any(part is None for part in self.alternative_parts):
            return None
        log_w = np.concatenate([part for part in self.alternative_parts if part is not None], axis=1)
        _, failed, log_p = self.arrays()
        k = log_w.shape[0]
        return log_w, np.repeat(failed[None, :], k, axis=0), np.repeat(log_p[None, :], k, axis=0)

    def failures_outcome(self, proposal_curve: np.ndarray) -> StageOutcome:
        """A batch drawn only to be weighed: its failures are its elites, no threshold."""
        log_w, failed, log_p = self.arrays()
        return StageOutcome(
            float("nan"),
            int(failed.sum()),
            estimate(log_w, failed, log_p),
            proposal_curve,
            detect_rate(self.counts, self.hits),
        )


def elite_count(n: int, quantile_level: float) -> int:
    """ceil((1 - sigma) N), at least 1: the rollouts at or below the stage threshold gamma_kappa (Innes &
    Ramamoorthy 2022, Algorithm 1; 5 of N = 100 at sigma = 0.95)."""
    return max(1, int(np.ceil((1.0 - quantile_level) * n - 1e-9)))


def quantile_threshold(robustness: np.ndarray, quantile_level: float, floor: float = 0.0) -> float:
    """gamma_kappa = max(floor, the ceil((1 - sigma) N)-th smallest robustness).

    With sigma = 0.95 and N = 100 this is the 5th smallest value (Innes & Ramamoorthy 2022, Algorithm 1). ``floor``
    is the failure threshold gamma (0): once enough rollouts fail, every failure is an elite."""
    r = np.asarray(robustness, dtype=np.float64)
    return kth_threshold(r, elite_count(r.size, quantile_level), floor)


def kth_threshold(robustness: np.ndarray, k: int, floor: float = 0.0) -> float:
    """max(floor, the k-th smallest of ``robustness`` [M]), 1 <= k <= M."""
    return max(floor, float(np.partition(robustness, k - 1)[k - 1]))


class EliteCandidates:
    """The rollouts of a stage that can still be elites, kept as its chunks arrive: [N] robustness values and only
    the rollouts at or below a falling bound max(floor, the k-th smallest seen, k = :func:`elite_count`), so the
    same elites in the same order as from one batch; once the bound is the floor, :meth:`settle` hands the sure
    elites over.

    Args:
        n: N, rollouts of the stage.
        quantile_level: sigma.
        floor: the failure level (0): every rollout at or below it is kept."""

    def __init__(self, n: int, quantile_level: float, floor: float = 0.0) -> None:
        self.n, self.k, self.floor = n, elite_count(n, quantile_level), float(floor)
        self.robustness = np.empty(n)
        self.seen = 0
        self.n_settled = 0
        self._kept: list[tuple[RolloutBatch, np.ndarray, np.ndarray]] = []

    def bound(self) -> float:
        """The largest robustness that can still be an elite (inf until k rollouts were seen)."""
        if self.seen < self.k:
            return float("inf")
        return kth_threshold(self.robustness[: self.seen], self.k, self.floor)

    def add(self, batch: RolloutBatch, robustness: np.ndarray) -> None:
        """Take the next chunk (rollouts ``seen .. seen + n - 1``) and its robustness [n]."""
        r = np.asarray(robustness, dtype=np.float64)
        index = np.arange(self.seen, self.seen + r.size)
        self.robustness[self.seen : self.seen + r.size] = r
        self.seen += r.size
        self._kept = self._select(self._kept + [(batch, r, index)], lambda rb: rb <= self.bound())

    @staticmethod
    def _select(parts: list, keep) -> list:
        out = []
        for b, rb, ib in parts:
            k = keep(rb)
            if k.all():
                out.append((b, rb, ib))
            elif k.any():
                out.append((b.select(k), rb[k], ib[k]))
        return out

    def settle(self) -> tuple[RolloutBatch | None, np.ndarray]:
        """The kept rollouts that are elites whatever comes next (below the floor, once the bound is the floor),
        removed from the pool: (their batch or None, their numbers in the stage [m])."""
        if self.bound() > self.floor:
            return None, np.zeros(0, np.int64)
        below = self._select(self._kept, lambda rb: rb < self.floor)
        self._kept = self._select(self._kept, lambda rb: rb >= self.floor)
        if not below:
            return None, np.zeros(0, np.int64)
        self.n_settled += sum(b.n for b, _, _ in below)
        if len(below) == 1:  # no copy of a part already selected
            return below[0][0], below[0][2]
        return RolloutBatch.concatenate([b for b, _, _ in below]), np.concatenate([i for _, _, i in below])

    def gamma(self) -> float:
        """gamma_kappa over all N rollouts (once they were all added)."""
        return self.bound()

    def candidates(self) -> tuple[RolloutBatch | None, np.ndarray, np.ndarray]:
        """(the kept rollouts or None, their robustness [M], their numbers in the stage [M]), in the order drawn;
        with the :attr:`n_settled` ones, M + n_settled >= k."""
        if not self._kept:
            return None, np.zeros(0), np.zeros(0, np.int64)
        if len(self._kept) == 1:
            return self._kept[0]
        return (
            RolloutBatch.concatenate([b for b, _, _ in self._kept]),
            np.concatenate([r for _, r, _ in self._kept]),
            np.concatenate([i for _, _, i in self._kept]),
        )


def pooled_estimate(stages: list[StageRollouts], stage_weights: np.ndarray | None = None) -> Estimate:
    """mu_hat over the rollouts of several stages together, each weighted by the proposal that drew it (see
    :meth:`pemviz.estimators.cross_entropy.CrossEntropy.result` for why the pooled mean is unbiased); :func:`pool` of
    their arrays.

    Args:
        stages: K stages of n_k rollouts each.
        stage_weights: lambda_k >= 0, [K], summing to 1, or None (:func:`pool`)."""
    return pool([s.arrays() for s in stages], stage_weights)
