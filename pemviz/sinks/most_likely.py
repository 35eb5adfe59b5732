"""The console's *why* line: a run's listener that keeps its most likely failure and says which perception errors
decided it (:mod:`pemviz.core.counterfactuals`)."""

from __future__ import annotations

import numpy as np

from pemviz.core.counterfactuals import LikelyFailure, counterfactuals, most_likely_failure
from pemviz.core.rollouts import RolloutBatch
from pemviz.engine.events import RolloutsSampled
from pemviz.sinks import Sink


class MostLikelyFailure(Sink):
    """A run's listener that keeps its most likely failure (:func:`pemviz.core.counterfactuals.most_likely_failure`,
    log p in nats over T - 1 steps: :func:`pemviz.core.counterfactuals.failure_log_p`) for the console's *why* line:
    ``best`` (None until a failure is seen), its ``stage``, ``rollout`` number and ``log_p`` (-inf until then), and
    ``batch``, the rollout as a batch of one."""

    def __init__(self) -> None:
        self.best: LikelyFailure | None = None
        self.batch: RolloutBatch | None = None
        self.stage: int | None = None
        self.rollout: int | None = None
        self.log_p = -np.inf

    def on_rollouts_sampled(self, event: RolloutsSampled) -> None:
        best = most_likely_failure(event, self.best)
        if best is not self.best:
            self.best, self.batch = best, event.batch.select(np.array([best.row]))
            self.stage, self.rollout, self.log_p = best.stage, best.rollout, best.log_p

    def why(self, problem) -> str | None:
        """The console's line saying which perception errors decided the most likely failure
        (:func:`pemviz.core.counterfactuals.counterfactuals`, replayed through ``problem``); None before a failure or
        for rollouts without object rows. Where every failure drawn has probability 0 under the PEM (log p = -inf),
        the line says so instead of calling one of them the most likely."""
        if self.batch is None or self.batch.objects is None:
            return None
        cf = counterfactuals(problem, self.batch, 0)
        if not np.isfinite(self.log_p):  # every failure drawn holds an event the PEM cannot produce
            return (f"why: every failure drawn has probability 0 under the PEM (log p = -inf), so none is likely; "
                    f"one of them (stage {self.stage}): {cf.summary()}")  # fmt: skip
        return f"why: the most likely failure (stage {self.stage}, log p {self.log_p:.1f} nats): {cf.summary()}"
