"""Scenarios: black-box simulators that query a detector once per step, and the rollout runner.

A :class:`Simulator` exposes ``reset()``, ``observation()`` (float64 [F], ``gap_m`` first),
``step(detected)`` and ``params.n_steps``. :func:`simulate` runs N of them in lockstep: each step it
gathers the N observations, evaluates the sampling detector and the target (PEM) detector on the whole
batch in one call each, draws the detections, and steps every simulator.

Optional capability (:class:`Snapshotting`): ``snapshot()`` returns the simulator's whole state at the
current step and ``restore(state)`` puts it back, so a rollout can be continued from any of its steps
(:func:`branch`, used by adaptive multilevel splitting, :mod:`pemviz.estimators.ams`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol, Sequence

import numpy as np

from pemviz.detectors import Detector, action_log_prob, step_uniforms
from pemviz.rng import by_blocks


class Simulator(Protocol):
    """A black-box scenario stepped by the detector's output; its only randomness is the detector."""

    observation_names: Sequence[str]

    def reset(self) -> None: ...

    def observation(self) -> np.ndarray: ...

    def step(self, detected: bool) -> None: ...


class Snapshotting(Simulator, Protocol):
    """A :class:`Simulator` whose state can be saved and put back (the optional snapshot/restore capability).

    ``restore(snapshot())`` on any simulator of the same scenario, then the same detections, gives exactly
    the observations the snapshotted simulator would have reported (bit for bit).
    """

    def snapshot(self) -> object: ...

    def restore(self, state: object) -> None: ...


def can_snapshot(sim: object) -> bool:
    """Whether ``sim`` has the snapshot/restore capability (:class:`Snapshotting`)."""
    return callable(getattr(sim, "snapshot", None)) and callable(getattr(sim, "restore", None))


@dataclass(frozen=True)
class RolloutBatch:
    """N rollouts of T steps, with the log-probabilities of every detection under both detectors.

    Attributes:
        observations: float64 [N, T, F] states reported at each step (``observation_names``).
        detected: bool [N, T] the detector outputs taken.
        log_p: float64 [N, T] log p_target(a_t | s_t) (nats), target = the PEM.
        log_q: float64 [N, T] log q(a_t | s_t) (nats) under the detector that sampled.
        observation_names: names of the F columns.
        log_q_parts: None, or float64 [N, K, T] log q_k(a_t | s_t) (nats) under each of K other detectors, e.g. the
            components of a mixture over rollouts, as an estimator asked them while the rollouts were drawn.
    """

    observations: np.ndarray
    detected: np.ndarray
    log_p: np.ndarray
    log_q: np.ndarray
    observation_names: tuple[str, ...]
    log_q_parts: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(self.detected.shape[0])

    @property
    def n_steps(self) -> int:
        return int(self.detected.shape[1])

    def signal(self, name: str) -> np.ndarray:
        """One observed signal, float64 [N, T]; raises KeyError naming the known signals."""
        try:
            return self.observations[:, :, self.observation_names.index(name)]
        except ValueError:
            raise KeyError(f"unknown signal {name!r}; this batch has {self.observation_names}") from None

    @property
    def gap_m(self) -> np.ndarray:
        return self.signal("gap_m")

    def log_weight(self, n_factors: int | None = None) -> np.ndarray:
        """Importance log-weights ``sum_t log p - log q`` over the first ``n_factors`` steps, float64 [N].

        The last action of a rollout affects nothing (Innes & Ramamoorthy (2022), Algorithm 1), so the default is T - 1 factors.
        """
        k = self.n_steps - 1 if n_factors is None else n_factors
        return (self.log_p[:, :k] - self.log_q[:, :k]).sum(axis=1)

    def log_likelihood(self, n_factors: int | None = None) -> np.ndarray:
        """``sum_t log p_target(a_t | s_t)`` over the first ``n_factors`` steps (default T - 1, as
        :meth:`log_weight`), float64 [N] (nats): how likely each rollout's detections are under the PEM."""
        k = self.n_steps - 1 if n_factors is None else n_factors
        return self.log_p[:, :k].sum(axis=1)

    def select(self, rows: np.ndarray) -> "RolloutBatch":
        """The rollouts ``rows`` (bool [N] mask or int indices), copied: a batch of its own, in their order."""
        parts = None if self.log_q_parts is None else self.log_q_parts[rows]
        return RolloutBatch(self.observations[rows], self.detected[rows], self.log_p[rows], self.log_q[rows],
                            self.observation_names, parts)  # fmt: skip

    @staticmethod
    def concatenate(batches: Sequence["RolloutBatch"]) -> "RolloutBatch":
        """Stack batches of equal T along N (``log_q_parts`` too where every batch has them)."""
        parts = [b.log_q_parts for b in batches]
        return RolloutBatch(
            np.concatenate([b.observations for b in batches]),
            np.concatenate([b.detected for b in batches]),
            np.concatenate([b.log_p for b in batches]),
            np.concatenate([b.log_q for b in batches]),
            batches[0].observation_names,
            None if any(x is None for x in parts) else np.concatenate(parts),
        )


def simulate(
    make_simulator: Callable[[], Simulator],
    n: int,
    sampler: Detector,
    target: Detector,
    rng: np.random.Generator | None,
    n_steps: int,
    uniforms: np.ndarray | None = None,
) -> RolloutBatch:
    """Run ``n`` rollouts in lockstep, detections drawn from ``sampler``, scored under ``target``.

    A detection happens iff ``u <= q(detect | s)`` with ``u ~ U(0, 1)`` from ``rng`` (one [n] draw per
    step), as in the authors' code. The detectors are asked about one fixed block of :data:`pemviz.rng.RQMC_BLOCK`
    rollouts at a time, and an Array-RQMC sampler couples the rollouts of each block (``uniforms`` must then start at
    a block boundary of the batch), so that chunks of whole blocks simulated elsewhere give the same bits.

    Args:
        make_simulator: builds a fresh simulator at its start state.
        n: number of rollouts (>= 1).
        sampler: the detector that draws the actions (proposal q, the PEM, a constant ...).
        target: the PEM whose probabilities weight the rollouts (may be ``sampler`` itself).
        rng: numpy Generator; the same seed gives the same batch (unused, may be None, with ``uniforms``).
        n_steps: T, steps per rollout.
        uniforms: optional float64 [T, n] pre-drawn u's, row t used at step t instead of ``rng.random(n)``.
            ``rng.random((T, n))`` holds exactly the numbers of T calls ``rng.random(n)``, so a column slice
            ``[:, a:b]`` of it reproduces rollouts a..b-1 of the serial run elsewhere (pemviz.executors).
    Returns:
        :class:`RolloutBatch` with arrays [n, T].
    Raises:
        ValueError: ``n < 1``, or ``uniforms`` not of shape [T, n] with values in [0, 1).
    """
    if n < 1:
        raise ValueError(f"simulate: n must be >= 1, got {n}")
    if uniforms is not None:
        uniforms = np.asarray(uniforms, dtype=np.float64)
        if uniforms.shape != (n_steps, n) or not np.all((uniforms >= 0.0) & (uniforms < 1.0)):
            raise ValueError(f"simulate: uniforms must be float64 [T, n] = [{n_steps}, {n}] in [0, 1), "
                             f"got shape {uniforms.shape}")
    sims = [make_simulator() for _ in range(n)]
    names = tuple(sims[0].observation_names)
    obs = np.empty((n, n_steps, len(names)))
    detected = np.empty((n, n_steps), dtype=bool)
    log_p = np.empty((n, n_steps))
    log_q = np.empty((n, n_steps))
    for t in range(n_steps):
        o = np.stack([s.observation() for s in sims])
        q_logit = by_blocks(sampler.detect_logit, o)  # one fixed block at a time, as on every executor
        p_logit = q_logit if target is sampler else by_blocks(target.detect_logit, o)
        u = step_uniforms(rng.random(n) if uniforms is None else uniforms[t], sampler, q_logit, o)
        # u <= sigmoid(logit)  <=>  log u <= log_expit(logit): exact in log-space.
        a = np.log(u) <= action_log_prob(q_logit, np.ones(n, dtype=bool))
        obs[:, t] = o
        detected[:, t] = a
        log_q[:, t] = action_log_prob(q_logit, a)
        log_p[:, t] = action_log_prob(p_logit, a)
        for s, a_i in zip(sims, a):
            s.step(bool(a_i))
    return RolloutBatch(obs, detected, log_p, log_q, names)


def branch(
    make_simulator: Callable[[], Simulator],
    parents: RolloutBatch,
    parent: np.ndarray,
    at: np.ndarray,
    target: Detector,
    rng: np.random.Generator,
) -> RolloutBatch:
    """Continue rollouts from given steps of earlier ones, detections drawn from ``target``: K new rollouts.

    New rollout i copies rollout ``parent[i]`` of ``parents`` up to step ``at[i]`` (its observations at steps
    ``0..at[i]`` and its actions at steps ``0..at[i] - 1``) and draws its actions from step ``at[i]`` on from
    ``target`` (``log_q = log_p``). Each parent is replayed once on one simulator (deterministic: the only
    randomness is the detector), snapshotted at the steps where its children branch, and every child starts
    from ``restore(snapshot)`` on a fresh simulator; the children then advance in lockstep, one
    ``rng.random(K)`` per step 0..T - 1 (rows not yet branched ignore theirs), as the vectorised twins
    (:func:`pemviz.scenarios.batched.branch_batched`, :func:`pemviz.scenarios.toy.branch_toy`) draw.

    Args:
        make_simulator: builds a fresh :class:`Snapshotting` simulator at its start state.
        parents: the rollouts to branch from, [M, T].
        parent: int [K] row of ``parents`` for each new rollout.
        at: int [K] branching steps, in [0, T - 1].
    Returns:
        :class:`RolloutBatch` [K, T].
    Raises:
        ValueError: a simulator without snapshot/restore, or ``parent`` / ``at`` out of range.
    """
    parent, at = np.asarray(parent, dtype=np.int64), np.asarray(at, dtype=np.int64)
    n, n_steps = parent.size, parents.n_steps
    check_branch_args(parents, parent, at)
    probe = make_simulator()
    if not can_snapshot(probe):
        raise ValueError(f"branch: {type(probe).__name__} has no snapshot/restore")
    sims: list[Snapshotting] = [None] * n  # type: ignore[list-item]
    for j in np.unique(parent):
        children = np.flatnonzero(parent == j)
        sim = probe if j == parent.min() else make_simulator()
        sim.reset()
        t = 0
        for i in children[np.argsort(at[children], kind="stable")]:
            while t < at[i]:
                sim.step(bool(parents.detected[j, t]))
                t += 1
            sims[i] = make_simulator()
            sims[i].restore(sim.snapshot())
    out = parents.select(parent)
    obs, detected, log_p = out.observations, out.detected, out.log_p
    rows = np.arange(n)
    for t in range(n_steps):
        u = rng.random(n)  # one draw per step, as the vectorised twins draw (the same rollouts for a seed)
        if t < at.min():
            continue
        live = rows[at <= t]
        o = np.stack([sims[i].observation() for i in live])
        logit = target.detect_logit(o)
        a = np.log(u[live]) <= action_log_prob(logit, np.ones(live.size, dtype=bool))
        obs[live, t], detected[live, t], log_p[live, t] = o, a, action_log_prob(logit, a)
        for i, a_i in zip(live, a):
            sims[i].step(bool(a_i))
    return RolloutBatch(obs, detected, log_p, log_p.copy(), parents.observation_names)


def check_branch_args(parents: RolloutBatch, parent: np.ndarray, at: np.ndarray) -> None:
    """Raise ValueError unless ``parent`` and ``at`` are int [K >= 1] rows of ``parents`` and steps in [0, T - 1]."""
    if parent.ndim != 1 or parent.size < 1 or at.shape != parent.shape:
        raise ValueError(f"branch: parent and at must be int [K >= 1] of one shape, got {parent.shape}, {at.shape}")
    if parent.min() < 0 or parent.max() >= parents.n or at.min() < 0 or at.max() >= parents.n_steps:
        raise ValueError(f"branch: parent must be in [0, {parents.n - 1}] and at in [0, {parents.n_steps - 1}]")
