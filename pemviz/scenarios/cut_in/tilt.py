"""Approximate zero-variance importance sampling of the cut-in: each step's events of the cut-in car drawn in
proportion to p(event) U(after it)^beta, mixed defensively with the PEMs, every weight p / q exact
(:class:`CutInTilt`).

At each step of the window where the cut-in car is visible, its three uniforms (detection, range error, lateral
error) fall in one class of the :class:`~pemviz.scenarios.cut_in.committor.Grid`; each class's value Q comes from
the level after it and the :class:`~pemviz.scenarios.cut_in.committor.LevelChain` solved once per scene
(:meth:`CutInLookAhead.solve_beam <pemviz.scenarios.cut_in.lookahead.CutInLookAhead.solve_beam>`). The class is
drawn from q(c) = (1 - eps) p(c) Q(c)^beta / Z + eps p(c) (Hesterberg 1995, Technometrics 37(2)), the uniforms
uniformly inside it; unbiased whatever Q is (L'Ecuyer & Tuffin 2008, WSC). Every look-ahead step counts in the cost."""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import pickle
from typing import TYPE_CHECKING, Any

import numpy as np

from pemviz.core import exact
from pemviz.core.lockstep import replay_rows, run_batched
from pemviz.core.rollouts import RolloutBatch
from pemviz.scenarios.cut_in.batched import BatchedCutIn
from pemviz.scenarios.cut_in.committor import GRIDS, Grid, LevelChain, continuous_level, level
from pemviz.scenarios.cut_in.lookahead import VISIBLE, CutInLookAhead, features, operand, p_detect_of
from pemviz.scenarios.cut_in.scenario import CutInParams

if TYPE_CHECKING:
    from pemviz.core.problems import Problem

TILT_WINDOW = (10, 32)
"""The steps (first, end) at which the cut-in car's events are tilted: the window must start by step 10 (a miss at
step 11 and a range error at step 12 restart the track) and reach step 31 (plain Monte Carlo failures whose decisive
events come after step 23 exist)."""
TILT_END = 40
"""The continuations' last step."""
TILT_BEAM_WIDTH = 0.25
"""The width of a chain cell's bin of G (levels)."""
TILT_BETA = 0.7
"""The tilt's power: q proportional to p Q^beta."""
TILT_EPS = 0.3
"""The PEMs' share of each tilted step's proposal (the defensive mixture)."""

_SOLVED: dict[tuple, CutInTilt] = {}
"""This process's solved proposals by :func:`solved_key`, the :data:`SOLVED_KEPT` latest: a later run of the same
scene, PEMs and options reuses one (its chain and effect model) instead of solving it again."""
SOLVED_KEPT = 4
"""How many solved proposals a process keeps (each holds its beam's look-aheads and effect model)."""


def solved_key(params: CutInParams, target: Any, options: dict[str, Any]) -> tuple | None:
    """What a solved :class:`CutInTilt` depends on: the scene's parameters, the PEMs (the sha256 of the pickled
    detector: its networks' weights and settings) and the proposal's options; None for PEMs that cannot be pickled
    (their proposal is not kept)."""
    try:
        pems = hashlib.sha256(pickle.dumps(target)).hexdigest()
    except (pickle.PicklingError, TypeError, AttributeError):
        return None
    return params, pems, tuple(sorted(options.items()))


def solved_tilt(params: CutInParams, target: Any, **options: Any) -> CutInTilt:
    """The :class:`CutInTilt` of ``params`` and ``target`` (keyword ``options`` as its constructor's), the one this
    process solved before when the scene, the PEMs and the options match (:func:`solved_key`), else a new one that
    :meth:`CutInTilt.solve` solves and keeps for the next run."""
    key = solved_key(params, target, options)
    found = None if key is None else _SOLVED.get(key)
    if found is not None:
        return found
    tilt = CutInTilt(params, target, **options)
    tilt.cache_key = key
    return tilt


class CutInTilt(CutInLookAhead):
    """The cut-in's importance sampler (module docstring): :meth:`solve` once a scene, then :meth:`stage` per batch.

    Args:
        params: the scene.
        target: the PEMs (:class:`pemviz.pem.perception.SalientDetector`).
        grid: the name of the events' grid (:data:`~pemviz.scenarios.cut_in.committor.GRIDS`).
        window, end, beam_width, beta, eps: :data:`TILT_WINDOW`, :data:`TILT_END`, :data:`TILT_BEAM_WIDTH`,
            :data:`TILT_BETA`, :data:`TILT_EPS`.
        options: the look-ahead's (:class:`~pemviz.scenarios.cut_in.lookahead.CutInLookAhead`).
    Raises:
        ValueError: a window that does not fit the scene, eps outside (0, 1], beta outside (0, 1]."""

    def __init__(
        self,
        params: CutInParams,
        target: Any,
        grid: str = "lean",
        window: tuple[int, int] = TILT_WINDOW,
        end: int = TILT_END,
        beam_width: float = TILT_BEAM_WIDTH,
        beta: float = TILT_BETA,
        eps: float = TILT_EPS,
        **options: Any,
    ) -> None:
        if not 0 <= window[0] < window[1] <= end <= params.n_steps:
            raise ValueError(
                f"tilt window {tuple(window)}, end {end}: need 0 <= start < end of the window <= end <= "
                f"{params.n_steps} (the scene's steps)"
            )
        if not (0.0 < eps <= 1.0 and 0.0 < beta <= 1.0):
            raise ValueError(f"tilt eps {eps}, beta {beta}: need 0 < eps <= 1 (the PEMs' share) and 0 < beta <= 1")
        super().__init__(params, target, Grid(np.array(GRIDS[grid])), window, end, **options)
        self.beam_width, self.beta, self.eps = beam_width, beta, eps
        self.chain: LevelChain | None = None
        self.solve_steps = 0
        self.cache_key: tuple | None = None
        """Where :meth:`solve` keeps the solved proposal for later runs (:func:`solved_tilt`); None: not kept."""

    def solve(self) -> int | None:
        """Solve the chain (and fit the effect model) on the nominal path, :attr:`chain`; returns the rollout-steps
        simulated (also :attr:`solve_steps`), None when it was solved before (a proposal reused:
        :func:`solved_tilt`)."""
        if self.chain is not None:
            return None
        before = self.steps
        self.chain = self.solve_beam(self.beam_width)
        self.solve_steps = self.steps - before
        if self.cache_key is not None:
            while len(_SOLVED) >= SOLVED_KEPT:
                _SOLVED.pop(next(iter(_SOLVED)))
            _SOLVED[self.cache_key] = self
        return self.solve_steps

    def splitting_score(self, problem: Problem) -> Any:
        """This proposal's committor as the score of adaptive multilevel splitting, for ``problem`` (the cut-in
        problem of the same scene and PEMs): :class:`pemviz.scenarios.cut_in.splitting.CommittorScore`."""
        from pemviz.scenarios.cut_in.splitting import CommittorScore

        return CommittorScore(self, problem)

    def draw(self, n: int, rng: np.random.Generator) -> tuple[RolloutBatch, int]:
        """``n`` rollouts of the tilted proposal and the look-ahead steps simulated (:meth:`stage`; the
        :class:`pemviz.core.problems.TiltSampler` interface)."""
        batch, _, steps = self.stage(n, rng)
        return batch, steps

    def branch_log_q(
        self,
        sim: BatchedCutIn,
        t: int,
        idx: np.ndarray,
        u: np.ndarray,
        rows: np.ndarray,
        prefix_min: np.ndarray,
        sfeat: np.ndarray,
        p0: np.ndarray,
    ) -> np.ndarray:
        """log Q of every grid branch, float64 [k, NBRANCH] (nats), for the rollouts ``idx`` [k] at step ``t``: one
        look-ahead of the central draw gives each state's G, the effect model (else the chain's cell) each branch's
        shift of it, the chain U_{t+1} its value.

        Args:
            sim: the N rollouts, at step ``t``.
            t: the step.
            idx: int [k] the rollouts.
            u: the step's uniforms [N, M, 3].
            rows: its object rows [N, M, G].
            prefix_min: the operand's minimum so far [N] (metres).
            sfeat: :func:`~pemviz.scenarios.cut_in.lookahead.features` of the rollouts [k, F].
            p0: the cut-in car's p(detect) [k]."""
        assert self.chain is not None, "solve() before stage()"
        r, bfeat = self.look_ahead(sim, idx, u, rows, prefix_min, self.grid.reps[1:2])
        g0 = continuous_level(level(r[:, 0]), bfeat[:, 0, -2], bfeat[:, 0, -1])
        shifts = None
        if self.effect_model is not None and t in self.chain.effects:
            shifts = self.effect_model.predict(self.effect_inputs(sim.state.select(idx), t, g0))
        return self.chain.log_q_branches(t, g0, self.regime(sfeat, t), shifts)

    def drawn(self, t: int, idx: np.ndarray, cls: np.ndarray, pc: np.ndarray) -> None:
        """Told each tilted step's classes ``cls`` [k] of rollouts ``idx`` and their p(class) [k, C] (a study's hook;
        nothing here)."""

    def stage(
        self, n: int, rng: np.random.Generator, given: np.ndarray | None = None
    ) -> tuple[RolloutBatch, np.ndarray, int]:
        """``n`` rollouts drawn from the tilted proposal.

        Args:
            n: the rollouts.
            rng: the draws: per step ``rng.random((n, M, 3))``, then at a tilted step one uniform a rollout for its
                class and three inside it.
            given: float64 [T, n, M, 3]: replay these uniforms (their classes scored, nothing drawn).
        Returns:
            (the batch, whose ``log_q`` is the proposal's: log p less each step's log p(c) / q(c); the log importance
            weights [n] (nats, summed over the whole rollout); the look-ahead steps simulated)."""
        p, target, g = self.params, self.target, self.grid
        m, w0, w1 = p.n_objects, *self.window
        sim = BatchedCutIn(p, n)
        log_w, prefix_min = np.zeros(n), np.full(n, np.inf)
        step_w = np.zeros((n, p.n_steps))
        before = self.steps

        def uniforms() -> Any:
            for t in range(p.n_steps):
                u = rng.random((n, m, 3)) if given is None else given[t].copy()
                prefix_min[:] = np.minimum(prefix_min, operand(sim.observation()))
                if w0 <= t < w1:
                    rows = np.ascontiguousarray(sim.objects())
                    idx = np.flatnonzero((rows[:, 0, VISIBLE] > 0.5) & (prefix_min >= 0.0))
                    if idx.size:
                        sfeat = features(sim.state.select(idx), self.traj[t], self.errors)
                        p0 = p_detect_of(target.detect_logit(rows[idx, 0]))
                        lqb = self.branch_log_q(sim, t, idx, u, rows, prefix_min, sfeat, p0)
                        pc, qc = g.proposal(p0, self.beta * lqb, self.eps)
                        if given is None:
                            cum = np.cumsum(qc, axis=1)
                            cls = np.minimum(
                                (cum < rng.random(idx.size)[:, None] * cum[:, -1:]).sum(axis=1), pc.shape[1] - 1
                            )
                            u[idx, 0] = g.draw(cls, p0, rng.random((idx.size, 3)))
                        else:
                            cls = g.classify(u[idx, 0], p0)
                        rr = np.arange(idx.size)
                        step_w[idx, t] = exact.log(pc[rr, cls]) - exact.log(qc[rr, cls])
                        log_w[idx] += step_w[idx, t]
                        self.drawn(t, idx, cls, pc)
                yield u.reshape(-1)

        with np.errstate(divide="ignore"):
            batch = run_batched(sim, n, p.n_steps, target, target, uniforms(), keep_rows=False)
        batch = dataclasses.replace(
            batch, log_q=batch.log_p - step_w, replay=functools.partial(replay_rows, functools.partial(BatchedCutIn, p))
        )
        return batch, log_w, self.steps - before
