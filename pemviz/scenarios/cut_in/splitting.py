"""The cut-in's committor as the score of adaptive multilevel splitting (``pemviz run --method ams --ams-score
committor``): the V that tilts the cut-in's importance sampler (:mod:`pemviz.scenarios.cut_in.tilt`) ranks the
particles, a second, independent estimate to check the tilt's.

A rollout's score at step t is -log V(s_t) (nats) at the steps of the tilt's window where the cut-in car is visible
(:meth:`CutInTilt.branch_log_q <pemviz.scenarios.cut_in.tilt.CutInTilt.branch_log_q>`), +inf at the others, the
failure formula's robustness (metres, < 0) at a failing step; the prefix score is the running minimum. Splitting is
unbiased for any score that is a function of the state and the step (Brehier, Gazeau, Goudenege, Lelievre & Rousset,
Ann. Appl. Probab. 26(6), 2016). Scores are computed while the rollout is simulated; a branched rollout takes its
parent's up to its branching step. Every look-ahead step is counted (:attr:`CommittorScore.steps`)."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterator
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from pemviz.core.lockstep import replay_rows, run_batched
from pemviz.core.problems import Problem
from pemviz.core.rollouts import RolloutBatch, draws_per_rollout
from pemviz.scenarios.cut_in.batched import BatchedCutIn
from pemviz.scenarios.cut_in.lookahead import VISIBLE, features, operand, p_detect_of


class CommittorScore:
    """Rollouts of the cut-in under its PEMs with their prefix scores (module docstring), for
    :class:`pemviz.estimators.ams.Splitting`.

    Args:
        tilt: the cut-in's :class:`~pemviz.scenarios.cut_in.tilt.CutInTilt` (solved here if it is not).
        problem: the cut-in problem of the same scene and PEMs (its formula's robustness marks the failures)."""

    def __init__(self, tilt: Any, problem: Problem) -> None:
        self.tilt, self.problem = tilt, problem
        solved = tilt.solve()
        self.solve_steps = solved or 0
        """Rollout-steps the tilt's solve simulated in this run (0: reused from an earlier run of the process)."""
        self.reused = solved is None
        self._before = tilt.steps

    @property
    def steps(self) -> int:
        """Rollout-steps simulated besides the rollouts: the solve (when this run solved it) and the look-aheads."""
        return self.solve_steps + self.tilt.steps - self._before

    def simulate(self, n: int, rng: np.random.Generator) -> tuple[RolloutBatch, np.ndarray]:
        """``n`` rollouts from the PEMs and their graded scores -log V, float64 [n, T] (nats; +inf where not
        scored); one ``rng.random(n k)`` a step, k the uniforms a rollout draws a step."""
        return self._run(n, rng, None, np.full(n, -1))

    def branch(
        self, parents: RolloutBatch, parent: np.ndarray, at: np.ndarray, rng: np.random.Generator
    ) -> tuple[RolloutBatch, np.ndarray]:
        """New rollout i replays ``parents``' rollout ``parent[i]`` before step ``at[i]`` and draws the rest from the
        PEMs (as :func:`pemviz.core.lockstep.branch_rollouts`); returns the rollouts [K, T] and their graded scores
        [K, T] after each branching step (+inf up to it: the parent's hold there)."""
        noise = None if parents.noise is None else parents.noise[parent]
        return self._run(parent.size, rng, (parents.detected[parent], noise, at), at)

    def rescore(self, batch: RolloutBatch) -> np.ndarray:
        """The graded scores [N, T] of rollouts already drawn, their events replayed (every step scored): the same
        as when they were drawn, a function of the state."""
        forced = (batch.detected, batch.noise, np.full(batch.n, batch.n_steps))
        return self._run(batch.n, np.random.default_rng(0), forced, np.full(batch.n, -1))[1]

    def _run(
        self, n: int, rng: np.random.Generator, forced: tuple | None, first: np.ndarray
    ) -> tuple[RolloutBatch, np.ndarray]:
        """Simulate (``forced``: events replayed before each rollout's step, as :func:`run_batched`'s), scoring each
        rollout at its steps after ``first`` [n]."""
        p, tilt = self.tilt.params, self.tilt
        sim = BatchedCutIn(p, n)
        k = draws_per_rollout(sim, self.problem.target) * n
        w0, w1 = tilt.window
        graded = np.full((n, p.n_steps), np.inf)
        prefix_min = np.full(n, np.inf)
        zeros = np.zeros((n, p.n_objects, 3))

        def uniforms() -> Iterator[np.ndarray]:
            for t in range(p.n_steps):
                prefix_min[:] = np.minimum(prefix_min, operand(sim.observation()))
                if w0 <= t < w1:
                    rows = np.ascontiguousarray(sim.objects())
                    idx = np.flatnonzero((rows[:, 0, VISIBLE] > 0.5) & (prefix_min >= 0.0) & (t > first))
                    if idx.size:
                        graded[idx, t] = -self.log_v(sim, t, idx, zeros, rows, prefix_min)
                yield rng.random(k)

        with threadpool_limits(1, user_api="blas"):  # as the problems' own rollouts (rollout_functions)
            batch = run_batched(
                sim, n, p.n_steps, self.problem.target, self.problem.target, uniforms(), forced, keep_rows=False
            )
        batch = dataclasses.replace(batch, replay=functools.partial(replay_rows, functools.partial(BatchedCutIn, p)))
        return batch, graded

    def log_v(
        self, sim: BatchedCutIn, t: int, idx: np.ndarray, u: np.ndarray, rows: np.ndarray, prefix_min: np.ndarray
    ) -> np.ndarray:
        """log V of the rollouts ``idx`` [k] of ``sim`` at step t, float64 [k] (nats): the tilt's classes' log Q
        averaged under the PEMs' p(class), summed in one order (the same on every CPU)."""
        tilt = self.tilt
        sfeat = features(sim.state.select(idx), tilt.traj[t], tilt.errors)
        p0 = p_detect_of(tilt.target.detect_logit(rows[idx, 0]))
        return tilt.grid.log_value(p0, tilt.branch_log_q(sim, t, idx, u, rows, prefix_min, sfeat, p0))
