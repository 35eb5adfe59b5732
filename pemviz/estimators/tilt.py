"""Approximate zero-variance importance sampling with the scenario's own proposal (``method = "tilt"``,
:attr:`pemviz.core.problems.Problem.tilt`, e.g. :class:`pemviz.scenarios.cut_in.tilt.CutInTilt`): each step's events
drawn in proportion to p(event) times an approximate committor, mixed defensively with the PEMs, every weight p / q
exact. This estimator solves it once, draws its batches and pools them as plain Monte Carlo (Kollman, Baggerly, Cox
& Picard 1999, Ann. Appl. Probab. 9(2); L'Ecuyer & Tuffin 2008, WSC); unbiased whatever the committor's errors.
Simulations count the look-aheads' steps too, in rollout-equivalents."""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass

import numpy as np

from pemviz.core.detectors import Detector
from pemviz.core.problems import Problem, TiltSampler
from pemviz.core.rollouts import RolloutBatch
from pemviz.estimators.base import StagePlan
from pemviz.estimators.fixed import FixedSampler


@dataclass(frozen=True)
class SceneProposal:
    """The scenario's tilted proposal as a stage's sampler: its density is each batch's ``log_q``, made along each
    rollout, not a function of an observation, so a rollout file declares no weight bound and ``detect_logit`` shows
    the target's.

    Attributes:
        target: the problem's target (p)."""

    target: Detector

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """The target's logit p(detect | obs), float64 [N] (see the class docstring)."""
        return self.target.detect_logit(obs)


class CommittorTilt(FixedSampler):
    """N rollouts from the problem's tilted proposal (module docstring), weighed by their batch's log p - log q.

    Args:
        problem: what to estimate; its ``tilt`` makes the proposal.
        n: rollouts.
        weights_until_failure: importance weights stop at the failure step.
        seed: the rollouts' stream, ``numpy.random.default_rng(seed)``.
    Raises:
        ValueError: a problem without a tilted proposal."""

    def __init__(self, problem: Problem, n: int, weights_until_failure: bool, seed: int = 0) -> None:
        if problem.tilt is None:
            where = (
                ""
                if problem.stream is not None
                else (" on this simulator (a scenario's may run on its batched " "twin only: --sim batched)")
            )
            raise ValueError(
                f"method tilt: the {problem.name} problem has no tilted proposal of its own{where}; use "
                f"adaptive or mc"
            )
        super().__init__(problem, problem.target, n, weights_until_failure, seed)
        self.sampler_of_scene: TiltSampler | None = None
        self.look_ahead_steps = 0
        """Rollout-steps the proposal's look-aheads simulated, its solve included."""
        self.prepared: str | None = None
        """How the proposal was prepared, one line: solved by this run (at what cost) or reused from an earlier run of
        the same scene, PEMs and options (:attr:`pemviz.engine.events.FinalEstimate.prepared`)."""

    def _open(self, stage: int, n: int) -> StagePlan:
        return dataclasses.replace(
            super()._open(stage, n), draw=functools.partial(self._draw, n), sampler=SceneProposal(self.problem.target)
        )

    def _draw(self, n: int, rng: np.random.Generator) -> RolloutBatch:
        """``n`` rollouts of the tilted proposal (solved first, once a run), on one BLAS thread (as the problems'
        own rollouts: :func:`pemviz.core.problems.rollout_functions`)."""
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1, user_api="blas"):
            if self.sampler_of_scene is None:
                assert self.problem.tilt is not None
                self.sampler_of_scene = self.problem.tilt()
                t0 = time.perf_counter()
                solve_steps = self.sampler_of_scene.solve()
                same = "the same scene, PEMs and options"
                if solve_steps is None:
                    self.prepared = (
                        f"the scenario's proposal reused from an earlier run of {same} in this process "
                        "(no solve counted)"
                    )
                elif solve_steps > 0:
                    self.look_ahead_steps += solve_steps
                    eq = solve_steps / max(1, self.problem.n_steps or 1)
                    self.prepared = (
                        f"the scenario's proposal solved by this run ({eq:,.0f} rollout-equivalents, "
                        f"{time.perf_counter() - t0:.1f} s; a later run of {same} in this process reuses "
                        "it)"
                    )
            batch, steps = self.sampler_of_scene.draw(n, rng)
        self.look_ahead_steps += steps
        return batch

    def simulations_counted(self) -> int:
        """:attr:`n_simulations` (:class:`pemviz.estimators.precision.Extensible`)."""
        return self.n_simulations

    @property
    def n_simulations(self) -> int:
        """The rollout-equivalents simulated so far: the rollouts plus the look-aheads' steps over T."""
        return self.final_rollouts() + round(self.look_ahead_steps / max(1, self.problem.n_steps or 1))
