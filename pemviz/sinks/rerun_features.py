"""The recording's view of what a state-dependent proposal does to a feature: per stage, q(detect) of the stage's
proposal against the PEM's over the feature that moved q most (:func:`pemviz.core.feature_view.stage_feature_curve`),
under ``feature/``."""

from __future__ import annotations

from typing import Any

import numpy as np
import rerun as rr

from pemviz.core.feature_view import PEM_SERIES, Q_SERIES, FeatureCurve, stage_feature_curve
from pemviz.sinks.rerun_views import AXIS_RGBA, PEM_RGBA, Figure

FEATURE_PATH = "feature"
"""Root of the feature view's entities."""

FEATURE_FIG = Figure(FEATURE_PATH, "", "p(detect)")
"""The feature view's figure: its x axis title is the stage's feature (logged with its axes)."""


def feature_title(curve: FeatureCurve, stage: int) -> str:
    """The figure's title for ``stage``'s curve: the feature's name and its effect (nats)."""
    return f"stage {stage}: {curve.name} moves logit q by {curve.effect:.2f} nats / sd"


def log_feature_curve(stream: rr.RecordingStream, curve: FeatureCurve, stage: int, colour: tuple[int, ...]) -> None:
    """``curve`` as ``stage``'s feature view (module docstring), on ``stage`` and on ``step`` 0."""
    stream.set_time("stage", sequence=stage)
    stream.set_time("step", sequence=0)  # on step, the last stage's curve (each stage's on stage)
    lo, hi = float(curve.x[0]), float(curve.x[-1])
    if hi <= lo:  # one bin: a unit span around it
        lo, hi = lo - 0.5, hi + 0.5
    pad = 0.03 * (hi - lo)
    FEATURE_FIG.draw_axes(stream, (lo - pad, hi + pad), (0.0, 1.0), static=False)
    w, h = FEATURE_FIG.width, FEATURE_FIG.height
    stream.log(
        f"{FEATURE_PATH}/axes/title",
        rr.Points2D(
            [[w / 2, h + 0.13 * h], [w / 2, -0.08 * h]],
            radii=-0.01,
            colors=AXIS_RGBA,
            labels=[curve.name, feature_title(curve, stage)],
            show_labels=True,
        ),
    )
    stream.log(
        f"{FEATURE_PATH}/axes/legend",
        rr.Points2D(
            [[1.12 * w, 0.4 * h], [1.12 * w, 0.52 * h]],
            radii=-3.0,
            colors=[colour, PEM_RGBA],
            labels=[Q_SERIES, PEM_SERIES],
            show_labels=True,
        ),
    )
    for name, label, values, rgba, radius in (
        ("q_detect", Q_SERIES, curve.q_detect, colour, -3.0),
        ("pem", PEM_SERIES, curve.p_detect, PEM_RGBA, -2.0),
    ):
        points = np.column_stack([curve.x, values])
        strip = rr.LineStrips2D([points], colors=rgba, radii=radius, labels=[label], show_labels=False)  # legend
        stream.log(f"{FEATURE_PATH}/data/{name}", strip)
        stream.log(f"{FEATURE_PATH}/data/{name}/bins", rr.Points2D(points, colors=rgba, radii=radius * 1.5))
    stream.log(
        f"{FEATURE_PATH}/stats",
        rr.AnyValues(
            feature=curve.name,
            effect_nats=curve.effect,
            x=curve.x,
            q_detect=curve.q_detect,
            p_detect=curve.p_detect,
            n_rows=curve.n_rows.astype(np.int64),
        ),
    )
    stream.disable_timeline("step")


def log_stage_features(stream: rr.RecordingStream, event: Any, problem: Any, colour: tuple[int, ...]) -> bool:
    """The feature view of the stage of ``event`` (a :class:`pemviz.engine.events.RolloutsSampled`, heard while its
    sampler is the one that drew it) under ``problem`` (its PEM and its features' replay); returns whether it logged
    one (none: no problem, a sampler that reads no state, e.g. a pretraining stage, or no feature moved q)."""
    if problem is None:
        return False
    curve = stage_feature_curve(event.batch, event.sampler, problem.target, getattr(problem, "features", None))
    if curve is None:
        return False
    log_feature_curve(stream, curve, event.stage, colour)
    return True
