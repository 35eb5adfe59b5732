"""The detection stage of a perception stack, for any scene: a noisy detector built from the shipped PEMs, and the
log-probabilities of what it did, detections and measurement errors apart.

Per object and step, with ``x`` the object's 11 KITTI salient variables (:func:`pemviz.stack.camera.view`):

    p(a, e | x) = p_PEM(a | x) * p_noise(e | x)^a,    a in {0, 1} (missed, detected), e = (dZ, dX) metres,

the detection PEM giving the logit of p(detected) (Innes & Ramamoorthy 2022, ICRA, Sec. IV-A) and the noise PEM
(:class:`pemviz.pem.noise.NoisePEM`) the density of a detected object's range and lateral errors.
:func:`camera_detector` returns that detector, every sampler's target."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.special import log_expit

from pemviz.core.event_probs import EventLogProbs, event_log_probs
from pemviz.pem.encoding import INPUT_COLUMNS
from pemviz.pem.perception import SalientDetector

NOISE_NAMES: tuple[str, ...] = ("range_error_m", "lateral_error_m")
"""A detected object's measurement errors, [D]: measured minus true, along the camera axis and across it (metres), as
the noise PEM gives them (:data:`pemviz.pem.noise.NOISE_DIMS`)."""

VISIBLE = "visible"
"""The object-row column :func:`camera_detector` reads as the 0/1 flag of an object the camera can see."""


def _salient_index(names: tuple[str, ...], who: str) -> list[int]:
    """The columns of the 11 salient variables (:data:`pemviz.pem.encoding.INPUT_COLUMNS`) in the object rows
    ``names``, in the PEMs' order.

    Raises:
        ValueError: one of them missing (``who`` names the caller)."""
    missing = [c for c in INPUT_COLUMNS if c not in names]
    if missing:
        raise ValueError(
            f"{who}: object_names lack the salient variables {missing} (the PEMs' inputs: "
            f"{', '.join(INPUT_COLUMNS)})"
        )
    return [names.index(c) for c in INPUT_COLUMNS]


def ahead_rows(object_names: Sequence[str], kind: Any, camera_height_m: float = 1.65) -> Any:
    """A problem's ``curve_rows`` for object rows ``object_names``: ``grid [R] -> rows float64 [R, G]`` of an object
    of ``kind`` straight ahead of the camera at each range of ``grid`` (m), fully visible (its salient variables,
    ``visible`` 1, the first column the range, other columns 0).

    Raises:
        ValueError: ``object_names`` without the 11 salient variables."""
    from pemviz.stack.camera import view

    names = tuple(object_names)
    index = _salient_index(names, "ahead_rows")

    def rows(grid: np.ndarray) -> np.ndarray:
        grid = np.asarray(grid, dtype=np.float64)
        seen = view(kind, np.zeros_like(grid), np.maximum(grid, 1e-3), 0.0, camera_height_m)
        out = np.zeros((grid.size, len(names)))
        out[:, index] = seen.salient
        if VISIBLE in names:
            out[:, names.index(VISIBLE)] = 1.0
        out[:, 0] = grid
        return out

    return rows


def camera_detector(
    object_names: Sequence[str], detect: Any = None, noise: Any = None, errors: bool = True
) -> SalientDetector:
    """The noisy detector of a scene's objects: the detection PEM on each object row's 11 salient variables and, when
    detected, the noise PEM's range and lateral errors (module docstring).

    Args:
        object_names: the scene's object-row columns [G]; they must hold the 11 names of
            :data:`pemviz.pem.encoding.INPUT_COLUMNS` and may hold ``visible`` (:data:`VISIBLE`: rows holding 0
            there are never detected).
        detect: the detection PEM (:class:`pemviz.pem.PEM`, :class:`pemviz.pem.TreePEM`); None: the shipped one.
        noise: the noise PEM (:class:`pemviz.pem.noise.NoiseModel`); None: the shipped ``hetero-t``.
        errors: False: a detector that only detects (exact measurements; ``noise`` is not loaded).
    Returns:
        a :class:`pemviz.pem.perception.SalientDetector` with ``noise_names`` = :data:`NOISE_NAMES`.
    Raises:
        ValueError: a salient variable missing from ``object_names``, or a name twice.
        pemviz.pem.network.PemFormatError, OSError: a shipped PEM that cannot be read."""
    names = tuple(object_names)
    if len(set(names)) != len(names):
        raise ValueError(f"camera_detector: object_names must be distinct, got {names}")
    index = _salient_index(names, "camera_detector")
    salient: Any = (
        slice(index[0], index[0] + len(index))
        if index == list(range(index[0], index[0] + len(index)))
        else np.array(index)
    )
    if detect is None:
        from pemviz.pem import load_pem

        detect = load_pem()
    if errors and noise is None:
        from pemviz.pem.store import load_noise_pem

        noise = load_noise_pem("hetero-t")
    return SalientDetector(
        detect,
        salient,
        noise if errors else None,
        NOISE_NAMES if errors else (),
        names.index(VISIBLE) if VISIBLE in names else None,
    )


@dataclass(frozen=True)
class Perception:
    """One step's perception of R objects drawn from a detector (:func:`perceive`).

    Attributes:
        detected: bool [R]; noise: float64 [R, D] the errors (metres; 0 where missed), or None;
        log_probs: their :class:`EventLogProbs` [R] under the detector that drew them."""

    detected: np.ndarray
    noise: np.ndarray | None
    log_probs: EventLogProbs


def perceive(detector: Any, rows: np.ndarray, rng: np.random.Generator) -> Perception:
    """Draw a step's perception of object rows [R, G] from ``detector`` itself (no proposal), as
    :func:`pemviz.core.detectors.draw_step` draws: detected iff ``log u_r <= log_expit(logit_r)``, errors by inverse
    CDF. For trying a scene by hand.

    Returns:
        :class:`Perception`."""
    rows = np.asarray(rows, dtype=np.float64)
    n_errors = len(getattr(detector, "noise_names", ()) or ())
    u = rng.random((rows.shape[0], 1 + n_errors))
    logit = np.asarray(detector.detect_logit(rows), dtype=np.float64)
    detected = np.log(u[:, 0]) <= log_expit(logit)
    if not n_errors:
        return Perception(detected, None, event_log_probs(detector, rows, detected))
    noise = np.zeros((rows.shape[0], n_errors))
    if detected.any():
        noise[detected] = detector.noise_from_uniforms(rows[detected], u[detected, 1:])
    return Perception(detected, noise, event_log_probs(detector, rows, detected, noise))
