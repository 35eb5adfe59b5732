"""One batch from a fixed detector, importance-weighted: plain Monte Carlo and the naive-50 / mixed-50 baselines of
Innes & Ramamoorthy (2022), Table II."""

from __future__ import annotations

import numpy as np

from pemviz.core.detectors import ConstantDetector, Detector, WindowDetector
from pemviz.core.estimate import Estimate
from pemviz.core.plan import RunPlan
from pemviz.core.problems import Problem
from pemviz.core.rollouts import RolloutBatch
from pemviz.estimators.base import StageOutcome, StagePlan, StageRollouts, pooled_estimate


class FixedSampler:
    """N rollouts drawn from one fixed detector q, weighted by p_target / q: the estimate of eq. 6 with a proposal
    that never adapts (stage 1, a ``final`` batch).

    Args:
        problem: what to estimate.
        sampler: q.
        n: rollouts.
        weights_until_failure: importance weights stop at the failure step (see
            :func:`pemviz.estimators.base.log_weight`).
        seed: the rollouts' stream, ``numpy.random.default_rng(seed)``.
        first_stage: the number of its first batch (1; after another estimator's stages, the stage after them)."""

    needs_chunk_rows = False
    """A streamed stage's chunks may come without their object rows (:attr:`pemviz.core.rollouts.RolloutBatch.replay`):
    this estimator reads the rows of failures only."""

    def __init__(
        self,
        problem: Problem,
        sampler: Detector,
        n: int,
        weights_until_failure: bool,
        seed: int = 0,
        first_stage: int = 1,
    ) -> None:
        self.problem, self.sampler, self.n, self.until_failure = problem, sampler, n, weights_until_failure
        self.first_stage = first_stage
        self.rng = np.random.default_rng(seed)
        self.stages: dict[int, StageRollouts] = {}
        """Each batch drawn: the planned one (stage 1) and the added ones (:meth:`extend`), pooled in :meth:`result`."""
        self._stage: int | None = None
        self._outcome: StageOutcome | None = None

    @staticmethod
    def run_plan(n: int, first_stage: int = 1) -> RunPlan:
        """One final batch of ``n`` rollouts, stage ``first_stage``."""
        return RunPlan.of([(first_stage, "final", n)])

    def plan(self) -> RunPlan:
        return self.run_plan(self.n, self.first_stage)

    def next_stage(self) -> StagePlan | None:
        if self._stage is not None:
            return None
        return self._open(self.plan().last_stage, self.n)

    def extend(self, n: int) -> StagePlan:
        """``n`` more rollouts from the same detector as the next stage, pooled with the others in :meth:`result`
        (every rollout alike: they are i.i.d. draws of the same q)."""
        assert self._stage is not None, "extend() before the planned batch"
        return self._open(self._stage + 1, int(n))

    def _open(self, stage: int, n: int) -> StagePlan:
        self._stage = stage
        self.stages[stage] = StageRollouts(self.problem.curve_grid)
        return StagePlan(stage, "final", n, self.sampler)

    def final_rollouts(self) -> int:
        """The rollouts drawn so far."""
        return sum(s.n for s in self.stages.values())

    def simulations_counted(self) -> int | None:
        """None: the rollouts planned are the simulations (:class:`pemviz.estimators.precision.Extensible`)."""
        return None

    def pooling(self) -> tuple[str, tuple[float, ...]] | None:
        """How :meth:`result` pools the stages drawn: every rollout alike, lambda_k = n_k / N (None: one stage)."""
        if len(self.stages) < 2:
            return None
        sizes = np.array([s.n for s in self.stages.values()], dtype=np.float64)
        return "rollouts", tuple(float(x) for x in sizes / sizes.sum())

    def observe(self, batch: RolloutBatch, failed: np.ndarray, robustness: np.ndarray | None) -> np.ndarray:
        assert self._stage is not None, "observe() before a stage was planned"
        return self.stages[self._stage].add(self.problem, batch, failed, self.until_failure)

    def finish(self) -> StageOutcome:
        assert self._stage is not None, "finish() before a stage was planned"
        self._outcome = self.stages[self._stage].failures_outcome(np.full(self.problem.curve_grid.size, np.nan))
        return self._outcome

    def result(self) -> tuple[Estimate, tuple[int, ...]]:
        assert self._outcome is not None and self._stage is not None, "result() before the batch was finished"
        if len(self.stages) == 1:
            return self._outcome.estimate, (self._stage,)
        return pooled_estimate(list(self.stages.values())), tuple(self.stages)


def monte_carlo(
    problem: Problem, n: int, weights_until_failure: bool = False, seed: int = 0, first_stage: int = 1
) -> FixedSampler:
    """Rollouts of the target detector itself: every weight is 1, mu_hat = failures / N (its first batch stage
    ``first_stage``)."""
    return FixedSampler(problem, problem.target, n, weights_until_failure, seed, first_stage)


def naive50(problem: Problem, n: int, weights_until_failure: bool = False, seed: int = 0) -> FixedSampler:
    """A detector that detects with 50 % at every step (Innes & Ramamoorthy 2022, Table II)."""
    return FixedSampler(problem, ConstantDetector(0.5), n, weights_until_failure, seed)


def mixed50(problem: Problem, n: int, weights_until_failure: bool = False, seed: int = 0) -> FixedSampler:
    """50 % inside the problem's window, where the detector can change the outcome, the target elsewhere."""
    return FixedSampler(
        problem, WindowDetector(ConstantDetector(0.5), problem.target, problem.window), n, weights_until_failure, seed
    )
