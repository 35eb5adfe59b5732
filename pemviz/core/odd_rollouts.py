"""Rollouts over an operating design domain: each rollout's scenario parameters drawn from the :class:`ODD` (or a
sampler's own parameter proposal) before its events, from the stage's first N x D uniforms, carried in its
observations (:class:`WithParameters`): the same rollouts for any chunk size, and every estimate one of p_ODD =
E_theta[p(theta)]."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from pemviz.core.detectors import Detector
from pemviz.core.lockstep import (
    DEFAULT_CHUNK_SIZE,
    _coupled,
    branch_rollouts,
    check_branch_args,
    check_counts,
    replay_rows,
    run_batched,
    uniform_chunks,
)
from pemviz.core.odd import ODD
from pemviz.core.odd_proposal import parameter_proposal_of
from pemviz.core.rng import RQMC_BLOCK
from pemviz.core.rollouts import RolloutBatch, draws_per_rollout

if TYPE_CHECKING:
    from pemviz.core.problems import Problem

MakeWith = Callable[[int, np.ndarray], Any]
"""``make(n, values [n, D]) -> BatchedSimulator``: n rollouts at their start, rollout i with parameters values[i]."""


class WithParameters:
    """A batched simulator whose observations end with its rollouts' parameters (constant columns named after them);
    everything else is the simulator's own.

    Raises:
        ValueError: a parameter's name is already one of the simulator's observation columns (the map and the
            rollout file would read the simulator's column for the parameter)."""

    def __init__(self, sim: Any, values: np.ndarray, names: tuple[str, ...]) -> None:
        own = tuple(sim.observation_names)
        if clash := [name for name in names if name in own]:
            raise ValueError(
                f"over an ODD, the drawn parameter {clash[0]!r} is added to the observations as a column of that "
                f"name, but the simulator already reports a column {clash[0]!r} ({', '.join(own)}): rename one of "
                "them (e.g. the observation to 'speed_now_mps')"
            )
        self.sim, self.values = sim, np.asarray(values, dtype=np.float64)
        self.observation_names = (*own, *names)

    def __getattr__(self, name: str) -> Any:  # objects, object_names, n_objects, snapshot, restore, ...
        if name in ("sim", "values"):
            raise AttributeError(name)
        return getattr(self.sim, name)

    def observation(self) -> np.ndarray:
        return np.concatenate([np.asarray(self.sim.observation(), dtype=np.float64), self.values], axis=1)

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None:
        self.sim.step(detected, noise)


def _first_rows(made: Callable[[np.ndarray], Any], values: np.ndarray, m: int) -> Any:
    """The simulator of the first ``m`` rollouts of ``values`` (a replay's, for :func:`replay_rows`)."""
    return made(values[:m])


def odd_rollout_functions(make: MakeWith, odd: ODD, n_steps: int) -> tuple[Callable, Callable, Callable]:
    """A :class:`pemviz.core.problems.Problem`'s ``simulate``, ``stream`` and ``branch`` over the ODD (module
    docstring): rollout i of a stage has parameters ``odd.draw(u_i)``, u the stage's first N x D uniforms.

    Raises (from the functions):
        ValueError: ``n`` or ``chunk_size`` not an integer >= 1."""
    names = odd.names

    def made(values: np.ndarray) -> WithParameters:
        return WithParameters(make(len(values), values), values, names)

    def stream(
        n: int,
        sampler: Detector,
        target: Detector,
        rng: np.random.Generator,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        keep_rows: bool = True,
    ) -> Iterator[RolloutBatch]:
        check_counts("odd stream", n=n, chunk_size=chunk_size)
        n = int(n)
        proposal = parameter_proposal_of(sampler)  # a proposal over the parameters, or None: the ODD itself
        u = rng.random((n, len(odd)))  # every rollout's parameters first: the same for any chunking
        values = odd.draw(u) if proposal is None else proposal.draw(u)
        size = RQMC_BLOCK if _coupled(sampler) else int(chunk_size)
        k = draws_per_rollout(made(values[:1]), target)
        for start, stop, uniforms in uniform_chunks(rng, n, n_steps, size, k):
            part = values[start:stop]
            batch = run_batched(made(part), stop - start, n_steps, sampler, target, uniforms, keep_rows=keep_rows)
            if proposal is not None:  # the parameters' density ratio, a term of each rollout's log q
                batch = batch.with_changes(log_q_params=proposal.log_ratio(part))
            if not keep_rows and batch.object_names is not None:
                rows: Callable[[int], Any] = functools.partial(_first_rows, made, part)
                batch = replace(batch, replay=functools.partial(replay_rows, rows))
            for a in range(0, batch.n, int(chunk_size)):
                yield batch if batch.n <= chunk_size else batch.select(slice(a, a + int(chunk_size)))

    def simulate(n: int, sampler: Detector, target: Detector, rng: np.random.Generator) -> RolloutBatch:
        chunks = list(stream(n, sampler, target, rng, chunk_size=max(int(n), 1)))
        return chunks[0] if len(chunks) == 1 else RolloutBatch.concatenate(chunks)

    def branch(
        parents: RolloutBatch, parent: np.ndarray, at: np.ndarray, target: Detector, rng: np.random.Generator
    ) -> RolloutBatch:
        parent = np.asarray(parent, dtype=np.int64)
        check_branch_args(parents, parent, np.asarray(at, dtype=np.int64))  # before the parents' rows are read
        cols = [tuple(parents.observation_names).index(name) for name in names]
        values = parents.observations[parent, 0][:, cols]  # each parent's parameters, as its first step holds them
        return branch_rollouts(lambda k: made(values[:k]), parents, parent, at, target, rng)

    return simulate, stream, branch


def problem_over_odd(base: Problem, make: MakeWith, odd: ODD, n_steps: int, **changes: Any) -> Problem:
    """``base`` over ``odd``: its rollouts from :func:`odd_rollout_functions` (``make``, ``n_steps``), without what
    holds at one set of parameters only (exact answers, reference, look-ahead, tilt); its verdict is its weights', as
    at one set of parameters, but where a bin of the run's map holds no failure
    (:meth:`pemviz.core.odd.OddMap.unfailed_cap`); ``changes`` replace any field besides."""
    simulate, stream, branch = odd_rollout_functions(make, odd, n_steps)
    cleared: dict[str, Any] = dict(
        exact_log_p=None,
        severity_exact={},
        reference=None,
        look_ahead=None,
        look_ahead_s=0.0,
        tilt=None,
    )
    fields = {**cleared, **changes, "simulate": simulate, "stream": stream, "branch": branch, "odd": odd}
    return dataclasses.replace(base, **fields)


def marked_over_odd(problem: Problem, odd: ODD) -> Problem:
    """``problem``, whose rollouts already draw their parameters from ``odd`` (a scenario's own factory built them with
    :func:`odd_rollout_functions` alone), marked as over it: ``odd`` set, so that a batch is simulated where its
    parameters are drawn (before its events, so that no block can be drawn apart), mapped, and proposed over by the
    default sampler, and its verdict capped where a bin of the run's map holds no failure
    (:meth:`pemviz.core.odd.OddMap.unfailed_cap`), as :func:`problem_over_odd`'s; a problem already over an ODD is
    returned as it is."""
    if problem.odd is not None:
        return problem
    return dataclasses.replace(problem, odd=odd)
