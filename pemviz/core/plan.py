"""A run's plan: the stages an estimator will run, their names and sizes, stated before the first batch
(:meth:`pemviz.estimators.base.Estimator.plan`) and handed to every listener with
:class:`pemviz.engine.events.RunStarted`. No numpy, no torch."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from pemviz.methods.ams import AMS_STAGE


def stage_label(stage: int, kind: str, n_stages: int) -> str:
    """The one name of a stage in console, panel, recording and CSVs.

    ``pretraining`` (stage 0), ``CE stage k/K`` (stages 1..K, ``n_stages`` = K; ``CE stage k`` past them, a
    retry's), ``final batch`` (stage K+1, or the only batch of mc / naive50 / mixed50), ``AMS particles`` / ``AMS
    iterations k`` (adaptive multilevel splitting); the number is the engine's ``stage`` everywhere."""
    if kind == "pretrain":
        return "pretraining"
    if kind == "ce":
        return f"CE stage {stage}/{n_stages}" if stage <= n_stages else f"CE stage {stage}"
    if kind == AMS_STAGE:
        return f"AMS iterations {stage}" if stage else "AMS particles"
    return "final batch"


@dataclass(frozen=True)
class PlannedStage:
    """One stage of a :class:`RunPlan`.

    Attributes:
        stage: the engine's number (0 = pretraining, 1..K = CE stages, K+1 = the final batch).
        kind: ``pretrain`` | ``ce`` | ``final`` | ``ams``.
        label: its one name in the console, panel and recording (:func:`pemviz.core.plan.stage_label`).
        n_rollouts: rollouts it simulates."""

    stage: int
    kind: str
    label: str
    n_rollouts: int


@dataclass(frozen=True)
class RunPlan:
    """The run an estimator states before its first batch (:meth:`Estimator.plan`), for the sinks, the panel and the
    memory check: they read it instead of working it out from the config.

    Attributes:
        stages: the stages in order.
        open_ended: more stages of the last one's kind follow until the estimator stops (AMS's groups of iterations,
            whose number depends on the particles); ``stages`` then holds the first only."""

    stages: tuple[PlannedStage, ...]
    open_ended: bool = False

    @classmethod
    def of(cls, stages: Iterable[tuple[int, str, int]], open_ended: bool = False) -> RunPlan:
        """The plan of ``(stage, kind, rollouts)`` triples, each labelled by :func:`pemviz.core.plan.stage_label`."""
        stages = tuple(stages)
        k = sum(kind == "ce" for _, kind, _ in stages)
        return cls(tuple(PlannedStage(s, kind, stage_label(s, kind, k), n) for s, kind, n in stages), open_ended)

    @property
    def n_ce(self) -> int:
        """K, the cross-entropy stages."""
        return sum(s.kind == "ce" for s in self.stages)

    @property
    def has_final_batch(self) -> bool:
        """Whether the run ends with a final batch drawn only to be weighed."""
        return any(s.kind == "final" for s in self.stages)

    @property
    def last_stage(self) -> int:
        """The number of the last stage planned (K + 1 with a final batch, K without; 1 for a single batch)."""
        return self.stages[-1].stage if self.stages else 0

    @property
    def n_simulations(self) -> int | None:
        """Rollouts simulated in all (None for an open-ended plan: not known before the run)."""
        return None if self.open_ended else sum(s.n_rollouts for s in self.stages)

    def label(self, stage: int, kind: str) -> str:
        """The name of stage ``stage`` (of kind ``kind``, for a stage beyond an open-ended plan)."""
        for s in self.stages:
            if s.stage == stage:
                return s.label
        return stage_label(stage, kind, self.n_ce)
