"""A study: why splitting ranked by the nominal look-ahead dies out on the cut-in, and what breaking its ties does.

``pemviz run --scenario cut-in --method ams --ams-score lookahead`` ends in extinction: every particle ties at one
level (:mod:`pemviz.estimators.lookahead_score`). Three modes, each printing its table:

- ``--mode onset``: plain rollouts of the PEM; the step at which the ACC first follows the cut-in car (its
  ``followed_index`` 0) against the rollout's least operand robustness (metres): the robustness is a function of that
  step alone. The ACC's IDM brakes at its clip (-6 m/s^2) from the step it follows until the closest approach, so the
  closest approach (the clearance, metres) takes one value per follow step, whatever the track's estimates.
- ``--mode classes``: N particles of the PEM; at each scored step the distinct values of the nominal look-ahead and of
  pessimistic look-aheads (:class:`MissingUniforms`: every object missed for m steps, then nominal), and the running
  minimum the splitting ranks by.
- ``--mode ams``: one splitting run (``pemviz.estimators.ams.run_ams``, the product's streams) ranked by the
  look-ahead with its ties broken (:class:`TieBrokenLookAhead`), printing each iteration's level, the distinct scores,
  the largest tie and the failures; ``--misses 1 2 3`` the pessimistic continuations, ``--trace`` the nominal
  continuation's own trace near its minimum, ``--stride`` the scored steps.

The tie-break adds less than :data:`TIE_BREAK` metres to the nominal look-ahead's score, a strictly increasing
function of the pessimistic continuations' mean least robustness (or of the trace's log-sum of exp(-(rho - min))):
a function of the state and the step, so splitting stays unbiased (Brehier, Gazeau, Goudenege, Lelievre & Rousset,
Ann. Appl. Probab. 26(6), 2016; ``research/tests/test_cut_in_ams_ties.py`` on the toy's exact 1e-3), and it orders
only particles the nominal look-ahead ties. Every look-ahead step is counted in the run's rollout-equivalents.

Measured (docs/validation.md, "Splitting on the cut-in (2026-11-30)"), one process at nice 10 on the shared 2-core
machine::

    nice -n 10 python research/cut_in_ams_ties.py --mode onset --n 20000 --seed 1
    nice -n 10 python research/cut_in_ams_ties.py --mode classes --n 200 --seed 1 --misses 2 4
    nice -n 10 python research/cut_in_ams_ties.py --mode ams --n 200 --seed 1                 # nominal: dies out
    nice -n 10 python research/cut_in_ams_ties.py --mode ams --n 200 --seed 1 --misses 2 4    # dies out
    nice -n 10 python research/cut_in_ams_ties.py --mode ams --n 200 --seed 1 --trace         # dies out
    nice -n 10 python research/cut_in_ams_ties.py --mode ams --n 200 --seeds 1 2 3 --misses 1 2 3 --stride 1
    python -m pytest research/tests/test_cut_in_ams_ties.py
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from pemviz.core.detector_noise import noise_names_of
from pemviz.core.problems import Problem, step_robustness
from pemviz.core.rollouts import RolloutBatch
from pemviz.estimators import ams
from pemviz.estimators.lookahead_score import LOOKAHEAD_BATCH, LookAheadScore, MedianUniforms

TIE_BREAK = 1e-3
"""Metres: the most a tie-break adds to the nominal look-ahead's score (far below the cut-in's 0.757 m between
follow steps, far above float64's resolution there)."""


class MissingUniforms(MedianUniforms):
    """The draws of a pessimistic continuation: rollout i's every object missed at its ``misses`` steps from ``at[i]``
    (the detection uniform just below 1: detected only where p(detect) rounds to 1), the nominal continuation's draws
    elsewhere. One ``random(n K)`` a step from step 0, rollout by rollout, K = M (1 + D), the detection first
    (:func:`pemviz.core.lockstep.run_batched`'s layout).

    Args:
        at: int [n], each rollout's first drawn step.
        misses: m >= 0, the steps missed.
        per_object: 1 + D, the uniforms an object draws a step."""

    def __init__(self, at: np.ndarray, misses: int, per_object: int) -> None:
        self.at, self.misses, self.per_object, self.t = np.asarray(at), int(misses), int(per_object), 0

    def random(self, size: int | tuple[int, ...] | None = None) -> np.ndarray:
        """Step t's uniforms, float64 ``size`` = n K (one call a step, in order)."""
        u = super().random(size).reshape(self.at.size, -1, self.per_object)
        u[(self.at <= self.t) & (self.t < self.at + self.misses), :, 0] = np.nextafter(1.0, 0.0)
        self.t += 1
        return u.reshape(size)


def continuation(problem: Problem, batch: RolloutBatch, rows: np.ndarray, at: np.ndarray, misses: int) -> np.ndarray:
    """The operand robustness of rollouts ``rows`` [K] continued from steps ``at`` [K] after ``misses`` steps of every
    object missed, nominally after them, float64 [K, T] (metres; +inf before ``at``)."""
    assert problem.branch is not None
    draws = MissingUniforms(at, misses, 1 + len(noise_names_of(problem.target))) if misses else MedianUniforms()
    light = {"events_only": True} if getattr(problem.branch, "events_only", False) else {}
    rho = step_robustness(problem, problem.branch(batch, rows, at, problem.target, draws, **light))  # type: ignore[arg-type]
    rho[np.arange(rho.shape[1])[None, :] < at[:, None]] = np.inf
    return rho


class TieBrokenLookAhead(LookAheadScore):
    """The nominal look-ahead score plus less than :data:`TIE_BREAK` metres: TIE_BREAK (1/2 + arctan(x) / pi), x the
    mean least robustness of the continuations that miss every object for each of ``misses`` steps first (metres),
    or with ``trace`` -log sum_s exp(-(rho_s - min rho)) of the nominal continuation's trace (lower: a longer dip).

    Args:
        problem: as :class:`LookAheadScore`.
        misses: the pessimistic continuations' missed steps, each >= 1.
        trace: break the ties by the nominal trace instead (its look-ahead simulated again, counted).
        stride: as :class:`LookAheadScore`."""

    def __init__(
        self, problem: Problem, misses: tuple[int, ...] = (), trace: bool = False, stride: int | None = None
    ) -> None:
        super().__init__(problem, stride)
        if any(m < 1 for m in misses):
            raise ValueError(f"TieBrokenLookAhead: misses must be >= 1 steps, got {misses}")
        self.misses, self.trace = tuple(misses), trace

    def score(self, batch: RolloutBatch, first: np.ndarray) -> np.ndarray:
        """:meth:`LookAheadScore.score` with the ties broken, float64 [N, T] (metres; +inf at steps not scored)."""
        graded = super().score(batch, first)
        if not (self.trace or self.misses):
            return graded
        rows, at = np.nonzero(np.isfinite(graded))
        for a in range(0, rows.size, LOOKAHEAD_BATCH):
            r, t = rows[a : a + LOOKAHEAD_BATCH], at[a : a + LOOKAHEAD_BATCH]
            if self.trace:
                rho = continuation(self.problem, batch, r, t, 0)
                low = rho.min(axis=1, keepdims=True)
                x = -np.log(np.exp(-(rho - low)).sum(axis=1))
            else:
                x = np.mean([continuation(self.problem, batch, r, t, m).min(axis=1) for m in self.misses], axis=0)
            graded[r, t] += TIE_BREAK * (0.5 + np.arctan(x) / np.pi)
        self.steps += int((batch.n_steps - at).sum()) * (1 if self.trace else len(self.misses))
        return graded


def onset_table(problem: Problem, n: int, seed: int) -> None:
    """Mode ``onset`` (module docstring)."""
    batch = problem.simulate(n, problem.target, problem.target, np.random.default_rng(seed))
    followed = batch.observations[:, :, batch.observation_names.index("followed_index")] == 0
    onset = np.where(followed.any(axis=1), np.argmax(followed, axis=1), -1)
    least = step_robustness(problem, batch).min(axis=1)
    print(
        f"{n} plain rollouts, seed {seed}: follow step (-1: never), rollouts, distinct least robustness (m), the "
        "most common (its rollouts), least, most"
    )
    for s in np.unique(onset):
        v = least[onset == s]
        values, counts = np.unique(np.round(v, 9), return_counts=True)
        print(
            f"  {s:4d} {v.size:6d} {values.size:4d} {values[counts.argmax()]:9.4f} ({counts.max():6d}) "
            f"{v.min():9.4f} {v.max():9.4f}"
        )


def classes_table(problem: Problem, n: int, seed: int, misses: tuple[int, ...]) -> None:
    """Mode ``classes`` (module docstring)."""
    batch = problem.simulate(n, problem.target, problem.target, np.random.default_rng(seed))
    score = LookAheadScore(problem)
    steps = np.array(score.scored_steps(batch.n_steps))
    graded = score.score(batch, np.full(n, -1))
    print(f"{n} particles, seed {seed}: the distinct values (their least, most) at each scored step")
    print("  step  nominal" + "".join(f"   {m} missed" for m in misses))
    for s in steps[np.isfinite(graded[:, steps]).all(axis=0)]:
        at, rows = np.full(n, s), np.arange(n)
        cols = [graded[:, s]] + [continuation(problem, batch, rows, at, m).min(axis=1) for m in misses]
        cells = [f"{np.unique(np.round(c, 9)).size:3d} ({c.min():6.3f}, {c.max():6.3f})" for c in cols]
        print(f"  {s:4d}  " + "  ".join(cells))
    running = ams.running_score(problem, batch, graded)[:, -1]
    values, counts = np.unique(np.round(running, 9), return_counts=True)
    print(f"  running minimum: {values.size} distinct, the largest tie {counts.max()} at {values[counts.argmax()]:.4f}")


def ams_levels(problem: Problem, n: int, seed: int, score: TieBrokenLookAhead, every: int) -> None:
    """Mode ``ams`` (module docstring): one run, its levels every ``every`` iterations and its estimate."""
    shown = ams.Splitting._check_stop

    def check(self: ams.Splitting) -> None:
        shown(self)
        if self.iterations % every == 0 or self.stop:
            s = self.score
            values, counts = np.unique(np.round(s, 12), return_counts=True)
            print(
                f"  iteration {self.iterations:3d} level {self.level:.7f} distinct {values.size:3d} largest tie "
                f"{counts.max():3d} failures {int((s < 0).sum()):3d} rollout-equivalents {self.n_simulations:7d}"
                + (f" {self.stop}" if self.stop else ""),
                flush=True,
            )

    ams.Splitting._check_stop = check  # type: ignore[method-assign]
    try:
        t0 = time.process_time()
        run = ams.run_ams(problem, n, max(1, n // 10), seed=seed, score=score)
    finally:
        ams.Splitting._check_stop = shown  # type: ignore[method-assign]
    e = run.estimate()
    p = math.exp(e.log_mu_hat) if e.log_mu_hat > -math.inf else 0.0
    print(
        f"seed {seed}: p_hat {p:.3g} {e.verdict} ({e.reason}), {run.n_simulations} rollout-equivalents, "
        f"{time.process_time() - t0:.0f} CPU s"
    )


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mode", choices=("onset", "classes", "ams"), required=True)
    ap.add_argument("--param", action="append", default=[], help="a scene parameter NAME=VALUE (as pemviz run)")
    ap.add_argument("--n", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--seeds", type=int, nargs="*", help="mode ams: these seeds in turn (default: --seed)")
    ap.add_argument("--misses", type=int, nargs="*", default=[], help="the pessimistic continuations' missed steps")
    ap.add_argument("--trace", action="store_true", help="mode ams: break the ties by the nominal trace")
    ap.add_argument("--stride", type=int, help="score every STRIDE-th step (default: the product's)")
    ap.add_argument("--every", type=int, default=1, help="mode ams: print every EVERY-th iteration")
    a = ap.parse_args(argv)
    from ams_replicas import problem_named

    problem = problem_named("cut-in", None, a.param)
    if a.mode == "onset":
        onset_table(problem, a.n, a.seed)
    elif a.mode == "classes":
        classes_table(problem, a.n, a.seed, tuple(a.misses))
    else:
        for seed in a.seeds or [a.seed]:
            ams_levels(problem, a.n, seed, TieBrokenLookAhead(problem, tuple(a.misses), a.trace, a.stride), a.every)


if __name__ == "__main__":
    main()
