"""The toy braking model with several obstacles and a mislocating detector: a multi-object problem with an exact
answer.

A car starts ``total`` units from the nearest of M obstacles (obstacle m ``offsets[m]`` further) and moves 1 unit
per step. Each step the detector sees each obstacle with probability ``p_detect`` and measures its distance with an
error e ~ N(0, ``noise_sd``^2); the car stops for good at the first detection measured at most ``braking`` away, and
fails below ``safe``. So

    P(trigger_m(t)) = p_detect * Phi((braking - d_m(t)) / noise_sd),     d_m(t) = total + offsets[m] - t,

    p_fail = prod_{t < t_fail} prod_m (1 - P(trigger_m(t)))     (:func:`crowd_log_failure_probability`).

It checks M object rows per step, their measurement errors in the weights and the proposal's per-object inputs
against a closed form. Units: abstract distance units, one step per unit of travel."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import log_ndtr

from pemviz.core.detector_noise import noise_log_density, noise_quantile
from pemviz.core.detectors import logit

OBSERVATION_NAMES: tuple[str, ...] = ("gap_m", "stopped")
"""The scene's signals: the distance to the nearest obstacle (units) and 1.0 once stopped or crashed."""

OBJECT_NAMES: tuple[str, ...] = ("distance", "offset", "stopped")
"""Each obstacle's row: its distance (units; the window's column), how much further than the nearest it stands, and
1.0 once the car stopped or crashed."""

NOISE_NAMES: tuple[str, ...] = ("distance_error",)
"""The measurement error of a detected obstacle's distance (units)."""


@dataclass(frozen=True)
class CrowdParams:
    """The crowd toy's constants.

    Attributes:
        total: the nearest obstacle's start distance (units, integer).
        braking: a detection measured at a distance <= ``braking`` stops the car.
        safe: failure = the nearest distance drops below ``safe``; 1 <= safe <= braking < total.
        p_detect: p(detect) of every obstacle at every step, in (0, 1).
        offsets: each obstacle's distance beyond the nearest (units, >= 0, the first 0): M = len(offsets).
        noise_sd: the standard deviation of a detected obstacle's distance error (units, >= 0; 0: exact).
    Raises:
        ValueError: parameters outside these ranges."""

    total: int = 20
    braking: int = 8
    safe: int = 3
    p_detect: float = 0.6
    offsets: tuple[float, ...] = (0.0, 1.5, 3.0)
    noise_sd: float = 1.0

    def __post_init__(self) -> None:
        if not 1 <= self.safe <= self.braking < self.total:
            raise ValueError(
                f"CrowdParams: need 1 <= safe <= braking < total, got {self.total}, {self.braking}, " f"{self.safe}"
            )
        if not 0.0 < self.p_detect < 1.0 or self.noise_sd < 0.0:
            raise ValueError(
                f"CrowdParams: p_detect must be in (0, 1) and noise_sd >= 0, got {self.p_detect}, " f"{self.noise_sd}"
            )
        if not self.offsets or self.offsets[0] != 0.0 or min(self.offsets) < 0.0:
            raise ValueError(f"CrowdParams: offsets must start at 0 and be >= 0, got {self.offsets}")

    @property
    def steps(self) -> int:
        """T: long enough to observe a failure at the last step (as the toy's)."""
        return self.total - self.safe + 2

    @property
    def window(self) -> float:
        """Where the proposal may differ from the detector: a detection stops the car with probability above
        Phi(-3) = 0.13 % only below ``braking + 3 noise_sd`` (units; half a unit beyond ``braking`` without noise);
        beyond, drawing from the detector itself costs next to nothing and keeps the weights even."""
        return self.braking + max(3.0 * self.noise_sd, 0.5)


@dataclass(frozen=True)
class CrowdDetector:
    """The crowd toy's detector, a :class:`~pemviz.core.detectors.NoisyDetector`: every obstacle detected with
    probability ``p_detect``, its distance measured with an N(0, ``noise_sd``^2) error (units)."""

    params: CrowdParams

    @property
    def noise_names(self) -> tuple[str, ...]:
        """The measured distance's error, or none when the measurements are exact (``noise_sd`` = 0)."""
        return NOISE_NAMES if self.params.noise_sd > 0.0 else ()

    def detect_logit(self, rows: np.ndarray) -> np.ndarray:
        """logit p(detect), float64 [R], for object rows [R, 3]."""
        return np.full(np.shape(rows)[0], logit(self.params.p_detect))

    noise_family = "normal"
    noise_df = None

    def noise_params(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(loc 0 [R, 1], log scale log(noise_sd) [R, 1]) (units) of the distance error."""
        r = np.shape(rows)[0]
        return np.zeros((r, 1)), np.full((r, 1), math.log(self.params.noise_sd))

    def noise_from_uniforms(self, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Distance errors float64 [R, 1] (units) from uniforms [R, 1] by the normal's inverse CDF."""
        return noise_quantile(self.noise_family, None, *self.noise_params(rows), u)

    def noise_log_prob(self, rows: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """log N(error; 0, noise_sd^2), float64 [R] (nats), for errors [R, 1]."""
        return noise_log_density(self.noise_family, None, *self.noise_params(rows), noise)


class BatchedCrowd:
    """n rollouts of the crowd toy stepped together, a :class:`~pemviz.core.rollouts.BatchedSimulator` with M object
    rows and their measurement errors."""

    observation_names = OBSERVATION_NAMES
    object_names = OBJECT_NAMES

    def __init__(self, params: CrowdParams, n: int) -> None:
        self.params, self.n_objects = params, len(params.offsets)
        self.offsets = np.asarray(params.offsets, dtype=np.float64)
        self.distance = np.full(n, float(params.total))
        self.stopped = np.zeros(n, dtype=bool)

    def observation(self) -> np.ndarray:
        """float64 [n, 2]: the nearest obstacle's distance and whether the car stopped."""
        return np.stack([self.distance, self.stopped.astype(np.float64)], axis=1)

    def objects(self) -> np.ndarray:
        """float64 [n, M, 3]: each obstacle's distance, offset and the stopped flag."""
        n, m = self.distance.size, self.n_objects
        rows = np.empty((n, m, 3))
        rows[:, :, 0] = self.distance[:, None] + self.offsets
        rows[:, :, 1] = self.offsets
        rows[:, :, 2] = self.stopped[:, None]
        return rows

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None:
        """``detected`` bool [n, M], ``noise`` float64 [n, M, 1] (units; None: exact measurements)."""
        p = self.params
        measured = self.distance[:, None] + self.offsets + (0.0 if noise is None else noise[:, :, 0])
        trigger = (np.asarray(detected, dtype=bool) & (measured <= p.braking)).any(axis=1)
        crashed = self.distance < p.safe
        self.stopped = self.stopped | crashed | trigger
        self.distance = np.where(self.stopped, self.distance, self.distance - 1.0)


def crowd_log_failure_probability(params: CrowdParams) -> float:
    """log p_fail of the crowd toy, exact (module docstring): ``sum_{t < t_fail} sum_m log(1 - p Phi((braking -
    d_m(t)) / sd))`` in nats, each term by ``log1p`` of a probability computed in log space (``log_ndtr``)."""
    p = params
    total = 0.0
    t = 0
    while p.total - t >= p.safe:  # the car is still moving and safe at step t: a trigger stops it
        d = p.total - t + np.asarray(p.offsets, dtype=np.float64)
        if p.noise_sd > 0.0:
            log_trigger = math.log(p.p_detect) + log_ndtr((p.braking - d) / p.noise_sd)
        else:
            log_trigger = np.where(d <= p.braking, math.log(p.p_detect), -np.inf)
        total += float(np.sum(np.log1p(-np.exp(log_trigger))))
        t += 1
    return total
