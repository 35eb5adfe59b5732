"""Which perception errors decided a failure: each error of a failing rollout undone alone, the rollout replayed.

For each miss or measurement error before the failure, the rollout is replayed through the problem's ``branch`` with
that event alone changed (the miss flipped to an exact detection, the error set to zero); an event is **decisive**
when its replay no longer fails. Nothing is drawn; any scene, any number of objects. Source: counterfactual
explanation by single interventions, as in Innes & Ramamoorthy, "Adaptive Splitting of Reusable Temporal Monitors
for Rare Traffic Violations" (arXiv 2405.15771)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pemviz.core.detectors import SamplerView
from pemviz.core.event_probs import batch_log_probs
from pemviz.core.problem_view import object_label
from pemviz.core.rollouts import RolloutBatch
from pemviz.core.scored_target import ScoredTarget

if TYPE_CHECKING:
    from pemviz.core.problems import Problem

MISS = "miss"
"""An object missed at a step, flipped to a detection measured exactly."""
ERROR = "error"
"""An object's measurement error at a step, set to zero."""


@dataclass(frozen=True)
class Intervention:
    """One perception error undone: the step, the object, the kind (:data:`MISS` or :data:`ERROR`), the error it
    undid (metres per component; empty for a miss), and the replay's classic robustness (< 0: still fails)."""

    step: int
    obj: int
    kind: str
    error: tuple[float, ...]
    robustness: float

    @property
    def decisive(self) -> bool:
        """Whether undoing this error alone avoids the failure."""
        return self.robustness >= 0.0


@dataclass(frozen=True)
class Counterfactuals:
    """Every single intervention on one failing rollout, in step order, with its robustness before any (< 0)."""

    rollout: int
    robustness: float
    failure_step: int
    interventions: tuple[Intervention, ...]

    @property
    def decisive(self) -> tuple[Intervention, ...]:
        """The interventions that avoid the failure alone."""
        return tuple(i for i in self.interventions if i.decisive)

    def summary(self, object_names: tuple[str, ...] | None = None, dt_s: float | None = None) -> str:
        """One line: which object's errors, at which steps, were decisive (or that none was alone).

        Args:
            object_names: what each object is called (:attr:`pemviz.core.problems.Problem.object_labels`); None or
                empty: ``object m``.
            dt_s: seconds per step, to give each step's time too (None: steps only)."""

        def who(i: Intervention) -> str:
            name = object_label(object_names, i.obj)
            when = f"step {i.step}" + (f" ({i.step * dt_s:.2f} s)" if dt_s else "")
            what = "missed" if i.kind == MISS else "mislocated by " + ", ".join(f"{e:+.2f} m" for e in i.error)
            return f"{name} {what} at {when}"

        n_miss = sum(i.kind == MISS for i in self.interventions)
        n_err = len(self.interventions) - n_miss
        misses = f"{n_miss} miss{'' if n_miss == 1 else 'es'}"
        errors = f"{n_err} measurement error{'' if n_err == 1 else 's'}"
        head = f"{misses} and {errors} before the failure at step {self.failure_step}"
        if not self.decisive:
            return f"{head}; none of them alone decides it"
        return f"{head}; decisive alone: " + "; ".join(who(i) for i in self.decisive)


def counterfactuals(
    problem: Problem, batch: RolloutBatch, index: int, *, max_interventions: int = 4096
) -> Counterfactuals:
    """Undo each perception error of rollout ``index`` of ``batch`` alone and replay it (module docstring).

    Args:
        problem: a :class:`pemviz.core.problems.Problem` with ``branch`` (its simulator replays given events).
        batch: rollouts of ``problem`` (detected [N, T, M], noise [N, T, M, D] or None).
        index: the failing rollout.
        max_interventions: the most replays (the earliest errors first).
    Returns:
        :class:`Counterfactuals`, its interventions in step and object order, misses before errors at a step.
    Raises:
        ValueError: the problem cannot replay (no ``branch``), or rollout ``index`` did not fail."""
    from pemviz import stl

    if problem.branch is None:
        raise ValueError(f"counterfactuals: {problem.name} cannot replay rollouts (no branch)")
    one = batch.select(np.array([index]))
    rho = float(problem.robustness(one, "classic")[0])
    if rho >= 0.0:
        raise ValueError(f"counterfactuals: rollout {index} did not fail (classic robustness {rho:.4g} >= 0)")
    t_fail = int(stl.first_violation(problem.formula, problem.signal_arrays(one))[0])
    det = one.detected[0]  # [T, M]
    rows = one.objects[0] if one.objects is not None else one.observations[0][:, None, :]
    logit = np.asarray(problem.target.detect_logit(rows.reshape(-1, rows.shape[-1])), dtype=np.float64)
    seeable = np.isfinite(logit).reshape(det.shape) | det
    candidates: list[tuple[int, int, str]] = []
    for t in range(min(t_fail, one.n_steps)):
        for m in range(det.shape[1]):
            if not det[t, m] and seeable[t, m]:
                candidates.append((t, m, MISS))
        if one.noise is not None:
            for m in range(det.shape[1]):
                if det[t, m] and np.any(one.noise[0, t, m] != 0.0):
                    candidates.append((t, m, ERROR))
    candidates = candidates[:max_interventions]
    if not candidates:
        return Counterfactuals(index, rho, t_fail, ())
    k = len(candidates)
    variants = one.select(np.zeros(k, dtype=np.int64))
    detected, noise = variants.detected.copy(), None if variants.noise is None else variants.noise.copy()
    for j, (t, m, kind) in enumerate(candidates):
        if kind == MISS:
            detected[j, t, m] = True
        if noise is not None:
            noise[j, t, m] = 0.0
    variants = RolloutBatch(
        variants.observations,
        detected,
        variants.log_p,
        variants.log_q,
        variants.observation_names,
        objects=variants.objects,
        object_names=variants.object_names,
        noise=noise,
        noise_names=variants.noise_names,
    )
    last = np.full(k, one.n_steps - 1)  # every event is replayed; the last step's event changes no signal
    replays = problem.branch(variants, np.arange(k), last, problem.target, np.random.default_rng(0))
    rho_k = np.asarray(problem.robustness(replays, "classic"), dtype=np.float64)
    errors = one.noise  # not None where an ERROR candidate was found
    out = tuple(
        Intervention(
            t,
            m,
            kind,
            tuple(float(e) for e in errors[0, t, m]) if kind == ERROR and errors is not None else (),
            float(r),
        )
        for (t, m, kind), r in zip(candidates, rho_k, strict=False)
    )
    return Counterfactuals(index, rho, t_fail, out)


@dataclass(frozen=True)
class LikelyFailure:
    """Which failing rollout is the most likely failure, and how likely.

    Attributes:
        stage: the stage of the :class:`pemviz.engine.events.RolloutsSampled` that carried it (0 = pretraining).
        row: its row in that event's batch.
        rollout: its number in the stage (``event.rollout_numbers[row]``: the row, except in a streamed stage,
            whose listeners see a sample of its rollouts).
        log_p: its log p under the PEM (nats; :func:`failure_log_p`): the log-probability of its detections plus,
            where the PEM mislocates, the log-density of its measurement errors (:func:`failure_log_p_parts`)."""

    stage: int
    row: int
    rollout: int
    log_p: float


def failure_log_p(batch: RolloutBatch, failed: np.ndarray) -> np.ndarray:
    """The log p under the PEM of each failing rollout, float64 [N] (nats), -inf where ``failed`` [N] is False: the
    sum of ``log p_target(a_t | s_t)`` over the first T - 1 steps
    (:meth:`pemviz.core.rollouts.RolloutBatch.log_likelihood`), by which the console, panel and recording choose the
    most likely failure; with measurement errors a log-likelihood that can be positive
    (:func:`failure_log_p_parts`).

    Raises:
        ValueError: ``failed`` is not of shape [N]."""
    failed = np.asarray(failed, dtype=bool)
    if failed.shape != (batch.n,):
        raise ValueError(f"failure_log_p: failed needs shape ({batch.n},), got {failed.shape}")
    return np.where(failed, batch.log_likelihood(), -np.inf)


def scoring_detector(target: object) -> object:
    """The PEM behind a run's target detector: ``target`` itself, or the detector that a
    :class:`pemviz.core.scored_target.ScoredTarget` (a mixture stage's target, which keeps every logit it is asked for)
    or a stage's target view (:class:`pemviz.core.detectors.SamplerView` 0, whose answers are the target's) wraps.
    Asking it about a rollout after the stage changes nothing the run keeps."""
    while True:
        if isinstance(target, ScoredTarget):
            target = target.target
        elif isinstance(target, SamplerView) and target.index == 0:
            target = target.samplers.target_detector
        else:
            return target


def failure_log_p_parts(
    batch: RolloutBatch, target: object | None, n_factors: int | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Each rollout's log p under the PEM (:func:`failure_log_p`, over the first ``n_factors`` steps, default T - 1)
    split by the kind of event it sums: the log-probability of its detections (<= 0) and the log-density of its
    detected objects' measurement errors.

    The second is a density in metres, so it and the sum can be positive (Cover & Thomas, "Elements of Information
    Theory", 2nd ed., 2006, Sec. 8.1). Both are recomputed from the rollout's object rows, detections and errors
    under ``target`` (:func:`scoring_detector`, :func:`pemviz.core.event_probs.batch_log_probs`) and add up to
    :func:`failure_log_p` to about 1e-12 relative; a batch without errors is not asked.

    Args:
        batch: N rollouts (detected bool [N, T, M]; object rows [N, T, M, G]; noise [N, T, M, D] or None).
        target: the PEM the rollouts are weighed under; only read when the batch has errors.
        n_factors: the steps summed (default T - 1, as :meth:`RolloutBatch.log_likelihood`).
    Returns:
        (log-probability of the detections [N], log-density of the measurement errors [N] or None), nats.
    Raises:
        ValueError: a batch with errors and no ``target``."""
    k = batch.n_steps - 1 if n_factors is None else int(n_factors)
    if batch.noise is None:
        return batch.log_likelihood(k), None
    if target is None:
        raise ValueError("failure_log_p_parts: a batch with measurement errors needs the target detector (the PEM)")
    parts = batch_log_probs(batch, scoring_detector(target))  # [N, T] each
    errors = parts.errors
    assert errors is not None  # the batch has errors: so do its parts
    return parts.detections[:, :k].sum(axis=1), errors[:, :k].sum(axis=1)


@dataclass(frozen=True)
class LogPParts:
    """A rollout's log p under the PEM (over T - 1 steps) as its two kinds of terms (:func:`failure_log_p_parts`).

    Attributes:
        detections: the log-probability of its detections and misses (nats, <= 0).
        errors: the log-density of its detected objects' measurement errors (nats, with the errors in metres; can be
            positive), or None where the detector does not mislocate."""

    detections: float
    errors: float | None = None

    @staticmethod
    def of(batch: RolloutBatch, row: int, target: object | None) -> LogPParts:
        """Rollout ``row`` of ``batch`` split under ``target`` (:func:`failure_log_p_parts`)."""
        one = batch.select(np.array([int(row)]))
        detections, errors = failure_log_p_parts(one, target)
        return LogPParts(float(detections[0]), None if errors is None else float(errors[0]))

    @property
    def total(self) -> float:
        """Their sum, the log p by which the most likely failure is chosen (nats; :func:`failure_log_p`)."""
        return self.detections + (0.0 if self.errors is None else self.errors)

    def words(self, digits: int = 1, whose: str = "its ") -> str:
        """``log-probability of its detections -63.2 nats, log-density of its measurement errors +12.4 nats`` (the
        second only with errors), each to ``digits`` decimals."""
        head = f"log-probability of {whose}detections {_nats(self.detections, digits)} nats"
        if self.errors is None:
            return head
        return f"{head}, log-density of {whose}measurement errors {_nats(self.errors, digits, sign=True)} nats"


def _nats(x: float, digits: int, sign: bool = False) -> str:
    """``x`` to ``digits`` decimals (``+`` before a positive one when ``sign``), ``-inf`` spelled so."""
    if math.isinf(x):
        return "-inf" if x < 0 else "+inf"
    return format(x + 0.0, f"{'+' if sign else ''}.{digits}f")


def likeliest_failures(batch: RolloutBatch, failed: np.ndarray, k: int) -> np.ndarray:
    """Rows of the ``k`` failing rollouts (``failed``: bool [N]) with the largest :func:`failure_log_p`, int64
    [min(k, failures)], likeliest first (ties: the lower row); empty when none fails or ``k`` <= 0."""
    rows = np.flatnonzero(np.asarray(failed, dtype=bool))
    if rows.size == 0 or k <= 0:
        return np.zeros(0, np.int64)
    log_p = failure_log_p(batch, failed)[rows]
    return rows[np.argsort(-log_p, kind="stable")[:k]].astype(np.int64)


def most_likely_failure(event, best: LikelyFailure | None = None) -> LikelyFailure | None:
    """The most likely failure of a run after ``event``: ``best`` (the run's so far, or None) or the failing rollout
    of ``event`` (a :class:`pemviz.engine.events.RolloutsSampled`) with the largest :func:`failure_log_p`, whichever
    has the larger log p. Ties keep the earlier: ``best``, then the lower row. Returns ``best`` itself (the same
    object) when the event has no likelier failure; None while no failure has been seen."""
    rows = likeliest_failures(event.batch, event.failed, 1)
    if rows.size == 0:
        return best
    row = int(rows[0])
    log_p = float(failure_log_p(event.batch, event.failed)[row])
    if best is not None and best.log_p >= log_p:
        return best
    return LikelyFailure(int(event.stage), row, int(event.rollout_numbers[row]), log_p)
