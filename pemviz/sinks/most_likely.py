"""The console's *why* line: a run's listener that keeps its most likely failure and says which perception errors
decided it (:mod:`pemviz.core.counterfactuals`)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pemviz.core.counterfactuals import LikelyFailure, LogPParts, counterfactuals, most_likely_failure
from pemviz.core.problem_view import object_label
from pemviz.core.rollouts import RolloutBatch
from pemviz.engine.events import RolloutsSampled
from pemviz.sinks import Sink

if TYPE_CHECKING:
    from pemviz.core.problems import Problem


class MostLikelyFailure(Sink):
    """A run's listener that keeps its most likely failure (:func:`pemviz.core.counterfactuals.most_likely_failure`,
    by log p over T - 1 steps) for the console's *why* line: ``best``, its ``stage``, ``rollout``, ``log_p`` (-inf
    until a failure) and ``batch`` (the rollout as a batch of one)."""

    def __init__(self) -> None:
        self.best: LikelyFailure | None = None
        self.batch: RolloutBatch | None = None
        self.stage: int | None = None
        self.rollout: int | None = None
        self.log_p = -np.inf

    def on_rollouts_sampled(self, event: RolloutsSampled) -> None:
        best = most_likely_failure(event, self.best)
        if best is not self.best:
            assert best is not None  # None only while no failure is seen, and self.best is None then
            self.best, self.batch = best, event.batch.select(np.array([best.row]))
            self.stage, self.rollout, self.log_p = best.stage, best.rollout, best.log_p

    def parts(self, problem: Problem) -> LogPParts | None:
        """The most likely failure's log p split into the log-probability of its detections (nats, <= 0) and, where
        the PEM mislocates, the log-density of its measurement errors (nats), recomputed under ``problem.target``
        (:func:`pemviz.core.counterfactuals.failure_log_p_parts`); None before a failure."""
        if self.batch is None:
            return None
        return LogPParts.of(self.batch, 0, problem.target)

    def why(self, problem: Problem) -> str | None:
        """The console's line saying which perception errors decided the most likely failure
        (:func:`pemviz.core.counterfactuals.counterfactuals`), with its log p in its two parts (:meth:`parts`), e.g.
        ``why: the most likely failure (stage 5; over all 99 steps: log-probability of its detections -63.2 nats,
        log-density of its measurement errors +12.4 nats): ...``; None before a failure or without object rows.
        Where every failure is impossible under the PEM (log p = -inf), the line says so."""
        if self.batch is None or self.batch.objects is None:
            return None
        cf = counterfactuals(problem, self.batch, 0)
        parts = self.parts(problem)
        assert parts is not None  # None only without a batch
        m = self.batch.objects.shape[2]
        labels = tuple(object_label(getattr(problem, "object_labels", ()), j) for j in range(m))
        if not np.isfinite(self.log_p):  # every failure drawn holds an event the PEM cannot produce
            what = (
                "has probability 0 under the PEM (the log-probability of its detections is -inf)"
                if parts.errors is None
                else "is impossible under the PEM (the log-probability of its detections "
                "or the log-density of its measurement errors is -inf)"
            )
            head = f"why: every failure drawn {what}, so none is likely; one of them (stage {self.stage})"
            return f"{head}: {cf.summary(labels)}"
        span = f"over all {self.batch.n_steps - 1} steps"
        return f"why: the most likely failure (stage {self.stage}; {span}: {parts.words()}): {cf.summary(labels)}"
