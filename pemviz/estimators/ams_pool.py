"""Whole splitting runs on the run's worker processes (``pemviz run --method ams --ams-replicas R``, executor
``local`` with two or more workers): replicas 1..R-1 run side by side in worker processes while replica 0 runs here,
each drawn from its own streams (:func:`pemviz.estimators.ams.replica_streams`), and are shown to the engine after
replica 0 stage by stage, replica after replica, as one process running them in turn shows them: the same particles,
outcomes, estimate and cost, bit for bit, whatever the workers."""

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

REPLICAS_PAY_S = 2.0
"""CPU seconds of the replicas left from which they go to worker processes: a worker's start costs about 1 s (its
imports and the problem's unpickling), and each replica is handed back once."""


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
    cpu_s: float,
) -> PooledRuns | None:
    """``run(problem, config, r)`` for replicas r = 1..R-1 of ``ams_replicas`` R >= 2 on the run's worker processes,
    while replica 0 goes on here: where the executor is ``local`` with two or more workers and the R - 1 replicas
    take at least :data:`REPLICAS_PAY_S` at ``cpu_s`` CPU seconds each (replica 0's initial particles: a lower
    bound); else None (the replicas are run here, one after another)."""
    r = config.ams.ams_replicas
    if r < 2 or (r - 1) * cpu_s < REPLICAS_PAY_S:
        return None
    executor: Any = resolve("pemviz.engine.experiment:run_executor")(config)
    if getattr(executor, "workers", 1) < 2 or not hasattr(executor, "submit"):
        return None
    return PooledRuns([executor.submit(run, problem, config, i) for i in range(1, r)], check)
