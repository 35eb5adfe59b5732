"""The detection stage of a perception stack, for any scene: a noisy detector built from the shipped PEMs, and the
log-probabilities of what it did, detections and measurement errors apart.

Per object and step, with ``x`` the object's 11 KITTI salient variables (:func:`pemviz.stack.camera.view` computes
them for a pinhole camera):

    p(a, e | x) = p_PEM(a | x) * p_noise(e | x)^a,    a in {0, 1} (missed, detected), e = (dZ, dX) metres,

the detection PEM giving the logit of p(detected) (Innes & Ramamoorthy 2022, "Testing rare downstream safety
violations via upstream adaptive sampling of perception error models", ICRA, Sec. IV-A) and the noise PEM
(``noise_hetero-t.pt``: a heteroscedastic Student-t, :class:`pemviz.pem.noise.NoisePEM`) the density of a detected
object's range and lateral errors (:class:`pemviz.pem.perception.NoisyPEM`). A missed object has no measurement, so
its error adds nothing.

:func:`camera_detector` returns that detector for a scene's object rows (a
:class:`pemviz.pem.perception.SalientDetector`, which every sampler of pemviz takes as a problem's target: the
importance samplers replace its detection logits and shift its error model inside the problem's window, and weigh
both; :func:`pemviz.core.detectors.draw_step`). :func:`pemviz.core.event_probs.event_log_probs` gives what a step's
events cost under it, kept apart: the log-probability of the detections and misses (nats, <= 0) and the log-density
of the detected objects' errors (nats, the errors in metres: a density, so it can be positive; Cover & Thomas 2006,
*Elements of Information Theory*, Sec. 8.1). Their sum is the step's ``log p`` of the rollouts
(:attr:`pemviz.core.rollouts.RolloutBatch.log_p`); :func:`pemviz.core.event_probs.batch_log_probs` splits a whole
batch's. :func:`perceive` draws a step's events from the PEMs themselves, for a scene tried by hand outside a
sampler; :func:`ahead_rows` gives a problem the rows where the PEM's detection curve is drawn.
"""

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
        ValueError: one of them missing (``who`` names the caller).
    """
    missing = [c for c in INPUT_COLUMNS if c not in names]
    if missing:
        raise ValueError(
            f"{who}: object_names lack the salient variables {missing} (the PEMs' inputs: "
            f"{', '.join(INPUT_COLUMNS)})"
        )
    return [names.index(c) for c in INPUT_COLUMNS]


def ahead_rows(object_names: Sequence[str], kind: Any, camera_height_m: float = 1.65) -> Any:
    """A problem's ``curve_rows`` (where the target's detection curve is drawn) for object rows ``object_names``: a
    function ``grid [R] -> rows float64 [R, G]`` of an object of ``kind`` (:class:`pemviz.stack.camera.ObjectKind`)
    straight ahead of the camera at each range of ``grid`` (m), facing the camera's right, fully visible: its salient
    variables (:func:`pemviz.stack.camera.view`), ``visible`` 1 and the first column the range; every other column 0.

    Raises:
        ValueError: ``object_names`` without the 11 salient variables.
    """
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
            :data:`pemviz.pem.encoding.INPUT_COLUMNS` (``class``, ``truncation``, ... ``rot_y``; consecutive or not)
            and may hold ``visible`` (:data:`VISIBLE`: rows holding 0 there are never detected, logit -inf).
        detect: the detection PEM (:class:`pemviz.pem.PEM`, :class:`pemviz.pem.TreePEM`); None: the shipped one
            (:func:`pemviz.pem.load_pem`).
        noise: the noise PEM (:class:`pemviz.pem.noise.NoiseModel`); None: the shipped ``hetero-t``
            (:func:`pemviz.pem.store.load_noise_pem`).
        errors: False: a detector that only detects (exact measurements; ``noise`` is not loaded).
    Returns:
        a :class:`pemviz.pem.perception.SalientDetector` (a :class:`pemviz.core.detectors.NoisyDetector` with
        ``noise_names`` = :data:`NOISE_NAMES`): ``detect_logit(rows [R, G]) -> [R]``, ``noise_params``,
        ``noise_from_uniforms``, ``noise_log_prob(rows, errors [R, 2]) -> [R]`` (nats).
    Raises:
        ValueError: a salient variable missing from ``object_names``, or a name twice.
        pemviz.pem.network.PemFormatError, OSError: a shipped PEM that cannot be read.
    """
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
        log_probs: their :class:`EventLogProbs` [R] under the detector that drew them.
    """

    detected: np.ndarray
    noise: np.ndarray | None
    log_probs: EventLogProbs


def perceive(detector: Any, rows: np.ndarray, rng: np.random.Generator) -> Perception:
    """Draw a step's perception of object rows [R, G] from ``detector`` itself (the PEMs, no proposal): object r is
    detected iff ``log u_r <= log_expit(logit_r)``, and a detected object's errors come from the error model's inverse
    CDF of further uniforms (as :func:`pemviz.core.detectors.draw_step` draws them). For trying a scene by hand; a
    problem's rollouts are drawn by the samplers through :func:`pemviz.core.problems.rollout_functions`.

    Returns:
        :class:`Perception`.
    """
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
