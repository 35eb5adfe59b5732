"""A scene-neutral graded score for adaptive multilevel splitting (``pemviz run --method ams --ams-score lookahead``):
how close the rollout's state is to failure if perception from now on does what it most likely does.

At a scored step t the score is the robustness of the formula's operand, minimised over the steps from t on, of the
rollout's **nominal continuation**: its own events before t, then every object detected iff the PEM says more likely
than not and its measurement errors at their medians (every uniform at 0.5:
:func:`pemviz.core.detectors.draw_step`). It needs only the problem's ``branch``, target and formula, names no scene
and learns nothing. Scored are every ``stride``-th step (stride = ceil(T / :data:`SCORED_STEPS`)) before failure
with, for a scene with a finite window, some object inside it; the others score +inf.

Splitting stays unbiased for any score that is a function of the state and the step (Brehier, Gazeau, Goudenege,
Lelievre & Rousset, "Unbiasedness of some generalized adaptive multilevel splitting algorithms", Ann. Appl. Probab.
26(6), 2016); a poor score costs variance: on a scene whose controller regulates back to one margin every particle
ties (``benchmarks/scene_neutral.py``). Every look-ahead step is counted in :attr:`LookAheadScore.steps`."""

from __future__ import annotations

import math

import numpy as np

from pemviz.core.problems import Problem, no_branch_message, step_robustness
from pemviz.core.rollouts import RolloutBatch

SCORED_STEPS = 25
"""About how many steps of a rollout are scored: the stride is ceil(T / SCORED_STEPS)."""
LOOKAHEAD_BATCH = 2048
"""The most look-aheads simulated together (rollouts of one ``branch``): the per-step cost spread over many rows,
the batch's arrays a few tens of MB."""


class MedianUniforms:
    """A stand-in for ``numpy.random.Generator`` whose every uniform is 0.5: the draws of the nominal continuation
    (each detection iff p(detect) >= 0.5, each error at its median)."""

    bit_generator = None
    """No bit generator to jump: the runners read its draws in order (:func:`pemviz.core.lockstep.uniform_chunks`)."""

    def random(self, size: int | tuple[int, ...] | None = None) -> np.ndarray:
        """0.5 in the shape ``size`` (float64)."""
        return np.full(() if size is None else size, 0.5)


class LookAheadScore:
    """The nominal look-ahead score (module docstring) as a :class:`pemviz.estimators.ams.GradedScore`: it draws the
    particles from the problem's target and scores them.

    Args:
        problem: a problem with ``branch`` and a ``G[a,b](state predicate)`` formula.
        stride: score every ``stride``-th step (None: ceil(T / :data:`SCORED_STEPS`)).
    Raises:
        ValueError: a problem without ``branch``, or a stride < 1."""

    def __init__(self, problem: Problem, stride: int | None = None) -> None:
        if problem.branch is None:
            raise ValueError(no_branch_message(problem))
        if stride is not None and stride < 1:
            raise ValueError(f"LookAheadScore: stride must be >= 1, got {stride}")
        self.problem, self.stride = problem, stride
        self.steps = 0
        """Rollout-steps the look-aheads simulated (their replayed prefixes not counted)."""

    def scored_steps(self, n_steps: int) -> range:
        """The steps scored in a rollout of ``n_steps`` steps (before the per-rollout conditions)."""
        return range(0, n_steps, self.stride or max(1, math.ceil(n_steps / SCORED_STEPS)))

    def simulate(self, n: int, rng: np.random.Generator) -> tuple[RolloutBatch, np.ndarray]:
        """``n`` rollouts of the problem's target and their scores, float64 [n, T] (metres of robustness; +inf at
        steps not scored)."""
        p = self.problem
        batch = p.simulate(n, p.target, p.target, rng)
        return batch, self.score(batch, np.full(n, -1))

    def branch(
        self, parents: RolloutBatch, parent: np.ndarray, at: np.ndarray, rng: np.random.Generator
    ) -> tuple[RolloutBatch, np.ndarray]:
        """``Problem.branch``'s rollouts [K, T] and their scores after each branching step ``at`` [K] (+inf up to
        it: the parent's hold there)."""
        p = self.problem
        assert p.branch is not None
        batch = p.branch(parents, parent, at, p.target, rng)
        return batch, self.score(batch, np.asarray(at))

    def score(self, batch: RolloutBatch, first: np.ndarray) -> np.ndarray:
        """The scores of ``batch``'s rollouts at their scored steps after ``first`` [N], float64 [N, T] (+inf
        elsewhere): the nominal continuation's least operand robustness from the step on (metres)."""
        p = self.problem
        assert p.branch is not None
        n, t_end = batch.n, batch.n_steps
        graded = np.full((n, t_end), np.inf)
        alive = np.minimum.accumulate(step_robustness(p, batch), axis=1) >= 0.0
        near = np.ones((n, t_end), bool)
        if batch.objects is not None and math.isfinite(p.window):
            near = np.any(batch.objects[:, :, :, 0] <= p.window, axis=2)
        steps = np.array(self.scored_steps(t_end))
        scored = (steps[None, :] > first[:, None]) & alive[:, steps] & near[:, steps]
        rows, which = np.nonzero(scored)
        at = steps[which]
        # every scored step's look-ahead of every row in one batch: the runner's arithmetic is row by row, so a
        # row's look-ahead is the same bits in any batch, and the per-step cost is paid once, not once per step
        light = {"events_only": True} if getattr(p.branch, "events_only", False) else {}
        for a in range(0, rows.size, LOOKAHEAD_BATCH):
            r, t = rows[a : a + LOOKAHEAD_BATCH], at[a : a + LOOKAHEAD_BATCH]
            ahead = p.branch(batch, r, t, p.target, MedianUniforms(), **light)  # type: ignore[arg-type]
            rho = step_robustness(p, ahead)
            rho[np.arange(t_end)[None, :] < t[:, None]] = np.inf
            graded[r, t] = rho.min(axis=1)
        self.steps += int((t_end - at).sum())
        return graded
