"""The recording's *Explain* tab: the most likely failure of a run, logged as entities under ``explain/``.

The most likely failure is the failing rollout with the largest log p under the PEM (T - 1 steps) among the rollouts
the engine reported, the "most likely failure" of adaptive stress testing (Lee et al., "Adaptive Stress Testing", JAIR
69, 2020): p(detect) of the PEM and q(detect) of the sampler along it, its misses, and where the drawing object
explains it, its outcome in words and one lane of its scene. The entities are listed in docs/recording.md."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
import rerun as rr

from pemviz.core.counterfactuals import LogPParts
from pemviz.core.problem_view import ProblemView, object_scene
from pemviz.core.proposal_view import prob_detect
from pemviz.core.rollouts import RolloutBatch
from pemviz.engine.events import RolloutsSampled
from pemviz.sinks import colours as C
from pemviz.sinks.drawing import recording_hooks
from pemviz.sinks.rerun_blueprint import EXPLAIN_PATH
from pemviz.sinks.rerun_views import (
    BRAKE_RGBA,
    CRASH_RGBA,
    DETECTED_RGBA,
    MISSED_RGBA,
    PEM_PLOT_RGBA,
    Indexes,
    log_scene_lane,
    log_thresholds,
)

if TYPE_CHECKING:
    from rerun.components import MarkerShapeLike

E = EXPLAIN_PATH
UNSEEN_RGBA = C.rgba(C.NEUTRAL)
"""An object the camera cannot see (its PEM never detects it)."""
AXIS_LABEL_RGBA = C.rgba(C.ON_DARK)
MARKER_ROW = -0.06
"""Height of the miss markers under the p / q curves (probability units, below 0)."""
OBJECT_BAND = 0.8
"""Several objects: each object's p(detect) and q(detect) are drawn from its row j (probability 0) to j + 0.8 (1)."""
ROLE_RGBA = {
    "failure": CRASH_RGBA[:3] + (255,),
    "detected": DETECTED_RGBA,
    "missed": MISSED_RGBA,
    "window": BRAKE_RGBA,
    "replay": C.rgba(C.VIOLET),
    "ego_speed": C.rgba(C.EGO_SPEED),
    "object_speed": C.rgba(C.OBJECT_SPEED),
}
"""The colour of each role a drawing's explanation names (:data:`pemviz.sinks.drawing.ROLES`)."""


def _series(
    stream: rr.RecordingStream,
    path: str,
    name: str,
    rgba: Sequence[int],
    values: np.ndarray,
    indexes: Indexes,
    steps: np.ndarray | None = None,
    width: float = 2.0,
) -> None:
    """A line ``values`` [T] (or at ``steps`` only), named and coloured, on ``step``."""
    v = np.asarray(values, dtype=np.float64)
    t = np.arange(v.size) if steps is None else np.asarray(steps, dtype=np.int64)
    stream.log(path, rr.SeriesLines(colors=[rgba], widths=[width], names=[name]), static=True)
    stream.send_columns(path, indexes=indexes(step=t), columns=rr.Scalars.columns(scalars=v))


def _markers(
    stream: rr.RecordingStream,
    path: str,
    name: str,
    rgba: Sequence[int],
    marker: MarkerShapeLike,
    steps: np.ndarray,
    values: np.ndarray,
    indexes: Indexes,
    size: float = 4.0,
) -> None:
    """Points at ``steps`` [k] with heights ``values`` [k] (nothing when ``steps`` is empty)."""
    steps = np.asarray(steps, dtype=np.int64)
    if steps.size == 0:
        return
    stream.log(path, rr.SeriesPoints(colors=[rgba], names=[name], markers=[marker], marker_sizes=[size]), static=True)
    stream.send_columns(
        path, indexes=indexes(step=steps), columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=np.float64))
    )


def log_explanation(
    stream: rr.RecordingStream,
    failure: RolloutsSampled | None,
    log_p: float,
    n_failures: int,
    view: ProblemView,
    stage_name: str,
    indexes: Indexes,
    object_detect: tuple[np.ndarray, np.ndarray] | None = None,
    parts: LogPParts | None = None,
) -> Mapping[str, Any] | None:
    """Log the Explain tab's entities for ``failure``, a one-rollout event (its stage, number, batch row).

    Args:
        stream: the recording logged to.
        failure: the most likely failure as a batch of one rollout; None: the run found no failure (the summary says
            so).
        log_p: its log p under the PEM over T - 1 steps (nats).
        n_failures: failing rollouts it was chosen among.
        view: the problem's view (signals, thresholds; its drawing object explains the failure).
        stage_name: the plan's name of its stage (``CE stage 4/10``).
        indexes: the sink's time columns for ``send_columns`` (with its repetition).
        object_detect: several objects: each one's p(detect) under the PEM and q(detect) under the sampler, float64
            [T, M] each (:func:`pemviz.core.proposal_view.object_detect_probabilities`); None: not drawn.
        parts: ``log_p`` as its two parts (:func:`pemviz.core.counterfactuals.failure_log_p_parts`); None: split
            from the failure's own batch where it holds no measurement errors, else only the sum is stated.
    Returns:
        the drawing object's explanation of the rollout (None without one or without a failure)."""
    s = stream
    if failure is None:
        text = "# No failure found\n\nThe run found no failing rollout: nothing to explain."
        s.log(f"{E}/summary", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)
        return None
    b = failure.batch
    col = view.signals[0].column
    trace = b.signal(col)[0]
    detected = np.asarray(b.detected[0, :, 0], dtype=bool)
    misses = np.flatnonzero(~detected)
    if view.objects_xy is not None and b.objects is not None:
        _log_objects(s, view, b, indexes)
    p_det, q_det = prob_detect(b.log_p[0], detected), prob_detect(b.log_q[0], detected)
    number = int(failure.rollout_numbers[0])
    drawing = recording_hooks(view.drawing)
    tale = drawing.explanation(b, 0) if drawing is not None else None

    if b.n_objects == 1:
        _series(s, f"{E}/detect/pem", "p(detect), PEM", PEM_PLOT_RGBA, p_det, indexes)
        _series(s, f"{E}/detect/sampler", "q(detect), sampler", C.rgba(C.BLUE), q_det, indexes)
        _markers(
            s, f"{E}/detect/misses", "miss", MISSED_RGBA, "cross", misses, np.full(misses.size, MARKER_ROW), indexes
        )
    else:  # log p sums every object's events and error densities: each object's events instead, a row each
        _log_object_events(s, view, b, object_detect, indexes)
    words = str(tale["words"]) if tale is not None else "failure"
    _series(s, f"{E}/{col}/recorded", f"as recorded: {words}", CRASH_RGBA[:3] + (255,), trace, indexes, width=2.5)
    log_thresholds(s, view, trace.size, indexes, path=f"{E}/{col}/thresholds")
    _markers(s, f"{E}/{col}/misses", "miss", MISSED_RGBA, "cross", misses, trace[misses], indexes)

    if parts is None and b.noise is None:  # detections only: log p is their log-probability
        parts = LogPParts.of(b, 0, None)
    props = _failure_props(failure, stage_name, log_p, n_failures, misses, trace.size, parts)
    chosen = _chosen_words(failure, log_p, parts, n_failures, misses, drawing, trace.size)
    lines = [f"## Most likely failure: {stage_name}, rollout {number}" + (f": {words}" if tale else ""), ""]
    if tale is not None:
        lines += _log_drawn(s, tale, indexes, props)
        log_scene_lane(s, f"{E}/scene", 0, failure, 0, drawing, indexes)
    lines.append(chosen)
    s.log(f"{E}/summary", rr.TextDocument("\n".join(lines) + "\n", media_type=rr.MediaType.MARKDOWN), static=True)
    s.log(f"{E}/failure", rr.AnyValues(**props), static=True)
    return tale


def _log_object_events(
    s: rr.RecordingStream,
    view: ProblemView,
    b: RolloutBatch,
    object_detect: tuple[np.ndarray, np.ndarray] | None,
    indexes: Indexes,
) -> None:
    """Several objects: each object's detected, missed and unseen steps on its own row, and its p(detect) and
    q(detect) in its row band where ``object_detect`` gives them."""
    names = b.object_names or ()
    if "visible" in names:
        assert b.objects is not None  # object names come with the object rows
        seen = b.objects[0][:, :, names.index("visible")] > 0.5
    else:
        seen = np.ones(b.detected[0].shape, bool)
    for j in range(b.n_objects):
        d = b.detected[0, :, j]
        for kind, rgba, steps_j in (
            ("detected", DETECTED_RGBA, np.flatnonzero(d)),
            ("missed", MISSED_RGBA, np.flatnonzero(~d & seen[:, j])),
            ("unseen", UNSEEN_RGBA, np.flatnonzero(~d & ~seen[:, j])),
        ):
            _markers(
                s,
                f"{E}/detect/object_{j}/{kind}",
                f"{view.object_label(j)} {kind}",
                rgba,
                "circle",
                steps_j,
                np.full(steps_j.size, float(j)),
                indexes,
                size=3.0,
            )
        if object_detect is not None:  # the object's band: 0 at its row, 1 at OBJECT_BAND above it
            p_j, q_j = (np.asarray(a[:, j], dtype=np.float64) for a in object_detect)
            _series(
                s,
                f"{E}/detect/object_{j}/pem",
                f"{view.object_label(j)} p(detect), PEM",
                PEM_PLOT_RGBA,
                j + OBJECT_BAND * p_j,
                indexes,
                width=1.0,
            )
            _series(
                s,
                f"{E}/detect/object_{j}/sampler",
                f"{view.object_label(j)} q(detect), sampler",
                C.rgba(C.BLUE),
                j + OBJECT_BAND * q_j,
                indexes,
                width=1.5,
            )


def _failure_props(
    failure: RolloutsSampled,
    stage_name: str,
    log_p: float,
    n_failures: int,
    misses: np.ndarray,
    n_steps: int,
    parts: LogPParts | None,
) -> dict[str, Any]:
    """The explained failure's properties (``explain/failure``): where it was drawn, its log p (and its parts where
    known), log-weight, robustness, misses."""
    stage, number = failure.stage, int(failure.rollout_numbers[0])
    props: dict = dict(
        stage=stage,
        stage_name=stage_name,
        rollout=number,
        log_p=log_p,
        log_weight=float(failure.log_weight[0]),
        robustness=float(failure.robustness[0]),
        n_failures_compared=n_failures,
        misses=misses,
        n_steps=n_steps,
    )
    if parts is not None:
        props["log_prob_detections"] = parts.detections
        if parts.errors is not None:
            props["log_density_errors"] = parts.errors
    return props


def _chosen_words(
    failure: RolloutsSampled,
    log_p: float,
    parts: LogPParts | None,
    n_failures: int,
    misses: np.ndarray,
    drawing: Any,
    n_steps: int,
) -> str:
    """The summary's paragraph on why this failure was chosen: its log p (in parts where known), robustness,
    log-weight and misses."""
    b = failure.batch
    how = (
        parts.words(2)
        if parts is not None
        else f"log-likelihood {log_p:.2f} nats: the log-probability of its "
        "detections plus the log-density of its measurement errors"
    )
    thing = drawing.object_words if drawing is not None else "the object"
    missed = (
        f"The detector missed {thing} at {misses.size} of {n_steps} steps."
        if b.n_objects == 1
        else f"The detector missed {int((~b.detected[0]).sum())} of {b.detected[0].size} object-steps of its "
        f"{b.n_objects} objects (those it cannot see included)."
    )
    return (
        f"The failing rollout with the largest log p under the PEM ({how}, over the first {n_steps - 1} steps) "
        f"among the {n_failures:,} failing rollouts the run reported; robustness "
        f"{float(failure.robustness[0]):.3g}, importance log-weight {float(failure.log_weight[0]):.2f} nats. " + missed
    )


def _log_drawn(s: rr.RecordingStream, tale: Mapping[str, Any], indexes: Indexes, props: dict) -> list[str]:
    """The drawing object's explanation: its series and markers under ``explain/`` (markers without heights on the
    row under the p(detect) curves), its properties added to ``props``; returns its summary lines."""
    props.update(tale["props"])
    for key, name, role, values in tale["series"]:
        _series(s, f"{E}/{key}", name, ROLE_RGBA[role], values, indexes)
    for key, name, role, marker, steps, values, size in tale["markers"]:
        heights = np.full(np.size(steps), MARKER_ROW) if values is None else values
        _markers(s, f"{E}/{key}", name, ROLE_RGBA[role], marker, steps, heights, indexes, size=size)
    return list(tale["lines"])


def _log_objects(stream: rr.RecordingStream, view: ProblemView, b: RolloutBatch, indexes: Indexes) -> None:
    """Every object of rollout 0 of ``b`` at each step, seen from the ego (``explain/objects``): where it is, where
    it was measured, and where the tracker places it (``tracked``, a box per tracked car) when the rows say."""
    sc = object_scene(view, b)
    x, ahead, det = sc.lateral_m, sc.ahead_m, sc.detected
    t_steps, m = det.shape
    colours = np.where(
        det[..., None],
        np.array(DETECTED_RGBA),
        np.where(sc.seen[..., None], np.array(MISSED_RGBA), np.array(UNSEEN_RGBA)),
    ).astype(np.uint8)
    labels = [str(j) for j in range(m)] * t_steps
    steps = indexes(step=np.arange(t_steps))
    stream.log(
        f"{E}/objects/ego",
        rr.Boxes2D(centers=[[0.0, 2.0]], half_sizes=[[1.0, 2.5]], colors=[C.rgba(C.BLUE)], labels=["ego"]),
        static=True,
    )
    where = np.stack([x, -ahead], axis=-1).reshape(-1, 2)
    stream.send_columns(
        f"{E}/objects/true",
        indexes=steps,
        columns=rr.Points2D.columns(
            positions=where, colors=colours.reshape(-1, 4), radii=np.full(t_steps * m, 1.0)
        ).partition(np.full(t_steps, m)),
    )
    stream.send_columns(
        f"{E}/objects/names",
        indexes=steps,
        columns=rr.Points2D.columns(
            positions=where + [2.5, 0.0],
            colors=np.tile(np.array(AXIS_LABEL_RGBA, np.uint8), (t_steps * m, 1)),
            radii=np.full(t_steps * m, 0.01),
            labels=labels,
        ).partition(np.full(t_steps, m)),
    )
    if sc.tracked is not None:  # where the tracker places each tracked car
        has = np.isfinite(sc.tracked[..., 0])
        n_tracked = has.sum(axis=1)
        if n_tracked.sum():
            est = np.stack([sc.tracked[..., 0], -sc.tracked[..., 1]], -1)
            stream.send_columns(
                f"{E}/objects/tracked",
                indexes=steps,
                columns=rr.Boxes2D.columns(
                    centers=est[has],
                    half_sizes=np.tile([0.9, 2.25], (int(n_tracked.sum()), 1)),
                    colors=np.tile(np.array(C.rgba(C.VIOLET), np.uint8), (int(n_tracked.sum()), 1)),
                ).partition(n_tracked),
            )
    if sc.measured is None:
        return
    lengths = det.sum(axis=1)
    if lengths.sum() == 0:
        return
    measured = np.stack([sc.measured[..., 0], -sc.measured[..., 1]], -1)[det]  # step by step, object by object
    truth = np.stack([x, -ahead], -1)[det]
    stream.send_columns(
        f"{E}/objects/measured",
        indexes=steps,
        columns=rr.Points2D.columns(
            positions=measured,
            colors=np.tile(np.array(C.rgba(C.BLUE), np.uint8), (lengths.sum(), 1)),
            radii=np.full(lengths.sum(), 0.4),
        ).partition(lengths),
    )
    strips = [[a, c] for a, c in zip(truth, measured, strict=False)]
    stream.send_columns(
        f"{E}/objects/error",
        indexes=steps,
        columns=rr.LineStrips2D.columns(
            strips=strips, colors=np.tile(np.array(C.rgba(C.BLUE), np.uint8), (len(strips), 1))
        ).partition(lengths),
    )
