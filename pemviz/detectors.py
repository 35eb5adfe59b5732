"""Detectors: what the scenario asks each step. Each gives the logit of p(detect | state).

A detector maps the scenario's observation ``obs`` (float64 [N, F], columns named by the scenario,
``gap_m`` first) to ``logit p(detect)`` float64 [N]. Working with logits keeps every log-probability
exact: ``log p(detect) = log_expit(logit)``, ``log p(miss) = log_expit(-logit)`` (``scipy.special.log_expit``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from scipy.special import log_expit

from pemviz.rng import array_rqmc_blocks

GAP_COLUMN = 0
"""Index of ``gap_m`` (metres) in every observation vector."""


@runtime_checkable
class Detector(Protocol):
    """Anything that gives ``logit p(detect | obs)``, float64 [N], for observations [N, F]."""

    def detect_logit(self, obs: np.ndarray) -> np.ndarray: ...


def action_log_prob(logit: np.ndarray, detected: np.ndarray) -> np.ndarray:
    """``log p(a | s)`` of the taken actions: log_expit(+logit) if detected else log_expit(-logit).

    Args:
        logit: float64 [...], logit of p(detect).
        detected: bool [...], the taken actions (same shape).
    Returns:
        float64 [...] log-probabilities in nats.
    """
    sign = np.where(np.asarray(detected, dtype=bool), 1.0, -1.0)
    return log_expit(sign * np.asarray(logit, dtype=np.float64))


def logit(p: float) -> float:
    """``log(p / (1 - p))``; raises ValueError unless 0 < p < 1."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"detection probability must be in (0, 1), got {p}")
    return math.log(p) - math.log1p(-p)


@dataclass(frozen=True)
class ConstantDetector:
    """Detects with the same probability at every step (the naive-50 detector when p = 0.5)."""

    p_detect: float = 0.5

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        return np.full(np.shape(obs)[0], logit(self.p_detect))


@dataclass(frozen=True)
class PEMDetector:
    """The perception error model as a detector: ``logit p_PEM(detect | salient variables(gap))``."""

    pem: object  # pemviz.pem.PEM (kept untyped to avoid importing torch models at import time)

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        return np.asarray(self.pem.logit_at_gap(np.asarray(obs)[:, GAP_COLUMN]), dtype=np.float64)


@dataclass(frozen=True)
class WindowDetector:
    """``inside`` when the gap is below ``radius_m`` (and at least ``floor_m``), ``outside`` otherwise (mixed-50:
    50 % inside 10 m)."""

    inside: Detector
    outside: Detector
    radius_m: float = 10.0
    floor_m: float = -math.inf

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """Each detector is asked only about its own rows (a proposal network costs per row)."""
        obs = np.asarray(obs)
        gap = obs[:, GAP_COLUMN]
        near = gap < self.radius_m
        if self.floor_m > -math.inf:
            near &= gap >= self.floor_m
        out = np.empty(obs.shape[0])
        for rows, detector in ((near, self.inside), (~near, self.outside)):
            if rows.any():
                out[rows] = detector.detect_logit(obs[rows])
        return out


@dataclass(frozen=True)
class ArrayRQMC:
    """``detector``, drawn by Array-RQMC: a simulator stepping rollouts together ranks them by this detector's logit
    at each step and takes their uniforms from :func:`pemviz.rng.array_rqmc_uniforms` (:func:`step_uniforms`).
    Every rollout still follows ``detector`` exactly; a simulator that does not look at ``array_rqmc`` draws i.i.d.
    uniforms, with the same expectations."""

    detector: Detector
    array_rqmc: bool = True

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """``detector``'s logit p(detect | obs), float64 [N], for observations [N, F]."""
        return self.detector.detect_logit(obs)


def step_uniforms(u: np.ndarray, sampler: Detector, q_logit: np.ndarray, obs: np.ndarray) -> np.ndarray:
    """The uniforms a simulator compares with ``sampler``'s detection probabilities at one step: ``u`` (float64 [n],
    i.i.d. U(0, 1)) as drawn, or for an :class:`ArrayRQMC` sampler the Array-RQMC uniforms of the chains ranked by
    ``q_logit`` (float64 [n], the sampler's logits at this step) and then by their observations ``obs`` [n, F],
    within each fixed block of :data:`pemviz.rng.RQMC_BLOCK` rollouts (:func:`pemviz.rng.array_rqmc_blocks`; the
    n rollouts start at a block boundary)."""
    if getattr(sampler, "array_rqmc", False) and u.size > 1:
        return array_rqmc_blocks(u, np.column_stack([q_logit, obs]))
    return u


class LastAnswer:
    """``detector``, remembering its last answer: asked again about the same observations (equal shape and values),
    it returns the same logits without asking ``detector`` again, e.g. when the sampler of a step and two mixture
    components around one proposal network are asked about the same rows. :meth:`forget` drops the answer (the
    detector changed, e.g. a proposal was fitted)."""

    def __init__(self, detector: Detector) -> None:
        self.detector = detector
        self._obs: np.ndarray | None = None
        self._logit = np.empty(0)

    def forget(self) -> None:
        """Drop the remembered answer."""
        self._obs = None

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """logit p(detect | obs), float64 [N], for observations [N, F]."""
        obs = np.asarray(obs, dtype=np.float64)
        last = self._obs
        if last is None or last.shape != obs.shape or not np.array_equal(last, obs):
            self._logit = np.asarray(self.detector.detect_logit(obs), dtype=np.float64)
            self._obs = obs.copy()
        return self._logit.copy()


class ScoredTarget:
    """The target detector that also asks ``extras`` about every observation it is asked about and keeps their
    logits, so that a mixture's component densities come out of the simulation that drew the rollouts instead of a
    second pass over them (each simulator asks its target once per step about all rollouts it steps together).

    :meth:`take` hands the kept logits over as [K, n, T] for the next ``n`` rollouts of T steps, or None when the
    asks do not fit that shape (a simulator that asks otherwise, or a remote executor whose copy of this object did
    the asking): the caller then asks ``extras`` itself.
    """

    def __init__(self, target: Detector, extras: tuple[Detector, ...]) -> None:
        self.target, self.extras = target, tuple(extras)
        self._asked: list[np.ndarray] = []

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """The target's logit p(detect | obs), float64 [N]; the extras' logits [K, N] are kept."""
        self._asked.append(np.stack([np.asarray(d.detect_logit(obs), dtype=np.float64) for d in self.extras]))
        return self.target.detect_logit(obs)

    def take(self, n: int, n_steps: int) -> np.ndarray | None:
        """The extras' logits of the next ``n`` rollouts, float64 [K, n, T], in the order simulated: groups of T asks
        of equal rows (one group per chunk of rollouts stepped together), or None (all kept logits are dropped) when
        the asks kept do not start with such groups covering ``n`` rollouts."""
        asked, parts, used, rows = self._asked, [], 0, 0
        while rows < n and used + n_steps <= len(asked):
            group = asked[used:used + n_steps]
            m = group[0].shape[1]
            if any(g.shape[1] != m for g in group):
                break
            parts.append(np.stack(group, axis=2))  # [K, m, T]
            used, rows = used + n_steps, rows + m
        if rows != n:
            self._asked = []
            return None
        del asked[:used]
        return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)
