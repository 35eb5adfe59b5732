"""What a detector's perception events cost, the two kinds apart: the log-probability of each detection or miss
(nats, <= 0) and the log-density of each detected object's error (nats; a density in metres, so it can be positive:
Cover & Thomas, *Elements of Information Theory*, 2006, Sec. 8.1). A rollout's ``log p`` is their sum
(:attr:`pemviz.core.rollouts.RolloutBatch.log_p`). :func:`event_log_probs` gives them for object rows,
:func:`batch_log_probs` for a batch."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pemviz.core.detectors import action_log_prob


@dataclass(frozen=True)
class EventLogProbs:
    """What perception events cost under a detector, the two kinds apart (float64 arrays of the events' shape, nats).

    Attributes:
        detections: ``log p(a | x)`` of each detection or miss (<= 0; 0 for an unseen object missed).
        errors: ``log p_noise(e | x)`` of each detected object's measurement error (metres; 0 where missed), or None
            for a detector that only detects."""

    detections: np.ndarray
    errors: np.ndarray | None

    @property
    def total(self) -> np.ndarray:
        """Their sum, ``log p(a, e | x)`` (nats): what the importance weights multiply."""
        return self.detections if self.errors is None else self.detections + self.errors


def event_log_probs(
    detector: Any, rows: np.ndarray, detected: np.ndarray, noise: np.ndarray | None = None
) -> EventLogProbs:
    """The log-probability of each detection or miss and the log-density of each detected object's error under
    ``detector``, apart (:class:`EventLogProbs`).

    Args:
        detector: any detector (``detect_logit``; with ``noise_log_prob`` when it mislocates).
        rows: float64 ``S + [G]`` object rows (e.g. ``[N, M, G]``).
        detected: bool ``S``.
        noise: float64 ``S + [D]`` the errors (metres; read where detected), or None: the detector only detects.
    Returns:
        :class:`EventLogProbs` of shape ``S``.
    Raises:
        ValueError: shapes that do not fit, or errors given to a detector without an error model."""
    rows = np.array(rows, dtype=np.float64)  # a copy: nothing a detector does to it reaches the caller's rows
    detected = np.asarray(detected, dtype=bool)
    shape = rows.shape[:-1]
    if detected.shape != shape:
        raise ValueError(
            f"event_log_probs: detected must be bool {list(shape)} for rows {list(rows.shape)}, got shape "
            f"{detected.shape}"
        )
    flat = rows.reshape(-1, rows.shape[-1])
    hit = detected.reshape(-1)
    logit = np.asarray(detector.detect_logit(flat), dtype=np.float64)
    detections = action_log_prob(logit, hit).reshape(shape)
    if noise is None:
        return EventLogProbs(detections, None)
    if not hasattr(detector, "noise_log_prob"):
        raise ValueError(f"event_log_probs: {type(detector).__name__} has no error model; give noise=None")
    noise = np.asarray(noise, dtype=np.float64)
    if noise.shape[:-1] != shape:
        raise ValueError(f"event_log_probs: noise must be float64 {list(shape)} + [D], got shape {noise.shape}")
    density = np.zeros(hit.size)
    if hit.any():
        errors = noise.reshape(hit.size, -1)
        density[hit] = np.asarray(detector.noise_log_prob(flat[hit], errors[hit]), dtype=np.float64)
    return EventLogProbs(detections, density.reshape(shape))


def batch_log_probs(batch: Any, detector: Any) -> EventLogProbs:
    """Each step's events of a batch of rollouts (a :class:`pemviz.core.rollouts.RolloutBatch` with object rows)
    under ``detector`` (e.g. the problem's target), summed over the step's objects: float64 ``[N, T]`` each (nats);
    their sum is the batch's ``log_p`` where ``detector`` is the target that scored it, up to rounding."""
    shape = batch.detected.shape  # [N, T, M]
    rows = batch.object_rows.reshape(*shape, -1)
    noise = None if batch.noise is None else batch.noise.reshape(*shape, -1)
    parts = event_log_probs(detector, rows, batch.detected, noise)
    return EventLogProbs(parts.detections.sum(axis=-1), None if parts.errors is None else parts.errors.sum(axis=-1))
