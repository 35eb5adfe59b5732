"""Whole splitting runs on the run's worker processes (``pemviz run --method ams --ams-replicas R``, executor
``local`` with two or more workers): the R independent replicas run side by side, each drawn from its own streams
(:func:`pemviz.estimators.ams.replica_streams`), and are shown to the engine afterwards stage by stage, replica after
replica, as one process running them in turn shows them: the same particles, outcomes, estimate and cost, bit for
bit, whatever the workers."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future, wait
from dataclasses import dataclass
from typing import Any

from pemviz.config import ExperimentConfig
from pemviz.core.estimate import Estimate
from pemviz.core.problems import Problem
from pemviz.core.rollouts import RolloutBatch
from pemviz.estimators.base import Check, StageOutcome
from pemviz.plugins import resolve


@dataclass(frozen=True)
class ReplicaRun:
    """One whole splitting run as the engine shows it (:func:`pemviz.estimators.ams.run_replica`).

    Attributes:
        stages: per stage, the particles after it [N, T], its outcome and the run's rollout-equivalents so far.
        estimate: the run's estimate.
        n_simulations: its rollout-equivalents."""

    stages: tuple[tuple[RolloutBatch, StageOutcome, int], ...]
    estimate: Estimate
    n_simulations: int


class PooledRuns:
    """R runs handed to worker processes (futures of :class:`ReplicaRun`, in order) and the one being shown.

    Args:
        futures: the runs' futures, in the order they are shown.
        check: called while a run is awaited (the engine's cancel token: it raises to abandon the run)."""

    def __init__(self, futures: list[Future[ReplicaRun]], check: Check) -> None:
        self.futures, self.check = futures, check
        self.done: list[tuple[Estimate, int]] = []
        """The runs shown: their estimates and rollout-equivalents."""
        self._run: ReplicaRun | None = None
        self._shown = 0

    def next_batch(self) -> RolloutBatch | None:
        """The particles after the next stage to show (waiting for its run), or None once every run is shown."""
        if self._run is not None and self._shown == len(self._run.stages):
            self.done.append((self._run.estimate, self._run.n_simulations))
            self._run = None
        if self._run is None:
            if len(self.done) == len(self.futures):
                return None
            future = self.futures[len(self.done)]
            while not future.done():
                self.check()
                wait([future], timeout=0.2)
            self._run, self._shown = future.result(), 0
        return self._run.stages[self._shown][0]

    def finish(self) -> StageOutcome:
        """The outcome of the stage :meth:`next_batch` gave, as its run closed it."""
        assert self._run is not None, "finish() before next_batch()"
        self._shown += 1
        return self._run.stages[self._shown - 1][1]

    @property
    def n_simulations(self) -> int:
        """Rollout-equivalents of the runs shown and of the stages shown of the current one."""
        now = self._run.stages[self._shown - 1][2] if self._run is not None and self._shown else 0
        return now + sum(sims for _, sims in self.done)


def pooled_runs(
    config: ExperimentConfig,
    run: Callable[[Problem, ExperimentConfig, int], ReplicaRun],
    problem: Problem,
    check: Check,
) -> PooledRuns | None:
    """``run(problem, config, r)`` for r < ``ams_replicas`` R >= 2 on the run's worker processes, where its executor
    is ``local`` with two or more workers (:meth:`pemviz.engine.pool.LocalExecutor.submit`); else None (the runs are
    made here, one after another)."""
    if config.ams.ams_replicas < 2:
        return None
    executor: Any = resolve("pemviz.engine.experiment:run_executor")(config)
    if getattr(executor, "workers", 1) < 2 or not hasattr(executor, "submit"):
        return None
    return PooledRuns([executor.submit(run, problem, config, r) for r in range(config.ams.ams_replicas)], check)
