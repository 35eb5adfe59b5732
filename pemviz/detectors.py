"""Detectors: what the scenario asks each step. Each gives the logit of p(detect | state).

A detector maps the scenario's observation ``obs`` (float64 [N, F], columns named by the scenario,
``gap_m`` first) to ``logit p(detect)`` float64 [N]. Working with logits keeps every log-probability
exact: ``log p(detect) = log_expit(logit)``, ``log p(miss) = log_expit(-logit)`` (``scipy.special.log_expit``).
"""

from __future__ import annotations

import hashlib
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
    """``inside`` when the gap is below ``radius_m``, ``outside`` otherwise (mixed-50: 50 % inside 10 m)."""

    inside: Detector
    outside: Detector
    radius_m: float = 10.0

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """Each detector is asked only about its own rows (a proposal network costs per row)."""
        obs = np.asarray(obs)
        near = obs[:, GAP_COLUMN] < self.radius_m
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
    """``detector``, remembering its last answer: asked again about the same observations (the same shape and
    bytes, compared by a 128-bit BLAKE2b digest), it returns the same logits without asking ``detector`` again,
    e.g. when two mixture components around one proposal network weigh the same rollouts."""

    def __init__(self, detector: Detector) -> None:
        self.detector = detector
        self._key: tuple | None = None
        self._logit = np.empty(0)

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """logit p(detect | obs), float64 [N], for observations [N, F]."""
        obs = np.ascontiguousarray(obs, dtype=np.float64)
        key = (obs.shape, hashlib.blake2b(obs.data, digest_size=16).digest())
        if key != self._key:
            self._logit, self._key = np.asarray(self.detector.detect_logit(obs), dtype=np.float64), key
        return self._logit.copy()
