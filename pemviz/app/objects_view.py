"""*Explain a failure* for a scene of several objects (e.g. the cut-in): every object at every step, detected,
missed or unseen, where each detected one was measured inside the noise PEM's error ellipse, and which errors
decided the failure (:func:`pemviz.core.counterfactuals.counterfactuals`). Plain functions of a rollout returning
HTML with inline SVG; no viser."""

from __future__ import annotations

import html
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from pemviz.app.drawing import objects_panel
from pemviz.core.counterfactuals import MISS, Counterfactuals, counterfactuals
from pemviz.core.problem_view import object_scene
from pemviz.sinks import colours as C
from pemviz.sinks.colours import hex_colour

if TYPE_CHECKING:
    from pemviz.core.problems import Problem

GREEN, ORANGE, UNSEEN, BLUE, RED, EGO, TRACK = (
    hex_colour(c) for c in (C.DETECTED, C.MISSED, C.IDLE, C.BLUE, C.RED, C.OBJECT, C.VIOLET)
)
BACKGROUND, LANE, TEXT, AXIS_TEXT, ON_EGO, NOW = (
    hex_colour(c) for c in (C.SKETCH_BACKGROUND, C.SKETCH_LANE, C.DARK, C.GREY, C.ON_DARK, C.BLACK)
)
AHEAD_M = (-25.0, 75.0)
"""The stretch of road the bird's-eye view shows, from behind the ego to ahead of it (metres)."""
LATERAL_M = 9.0
"""The bird's-eye view shows this far to either side of the ego (metres)."""
CAR_LENGTH_M, CAR_WIDTH_M = 4.5, 1.8
ELLIPSE_SCALES = 2.0
DEFAULT_DT_S, DEFAULT_LANE_M = 0.1, 4.0
"""Seconds per step and a lane's width (metres) where neither the problem nor its drawing gives them."""
"""The error ellipse's half-axes, in the noise PEM's scales of each component."""


@dataclass(frozen=True)
class ObjectsExplanation:
    """A rollout of a scene of several objects, object by object, and which of its perception errors decided it.

    Attributes:
        lateral_m, ahead_m: float64 [T, M] each object's true position seen from the ego (metres: right, ahead).
        detected, seen: bool [T, M] detected; visible to the camera at all.
        measured: float64 [T, M, 2] where each detected object was measured (lateral, ahead; NaN where not), or
            None.
        ellipse: float64 [T, M, 2, 2] the noise PEM's (centre offset, half-axis) along lateral and ahead (metres),
            or None.
        tracked: float64 [T, M, 2] the tracker's confirmed positions (NaN where none), or None: no tracker.
        followed: bool [T, M] the car the controller followed at the step.
        counterfactuals: every single intervention of a failing rollout (None: it did not fail, or cannot replay).
        names: the objects' names.
        failed: the rollout failed.
        time_s: float64 [T] the time of each step (seconds).
        gap_ahead: float64 [T, M] each object's gap ahead (metres; negative beside or behind), or None.
        story: what happened, in words, and the severity (:meth:`~pemviz.app.drawing.ObjectsPanel.objects_story`),
            or None.
        lane_width_m: a lane's width (metres)."""

    lateral_m: np.ndarray
    ahead_m: np.ndarray
    detected: np.ndarray
    seen: np.ndarray
    measured: np.ndarray | None
    ellipse: np.ndarray | None
    tracked: np.ndarray | None
    followed: np.ndarray
    counterfactuals: Counterfactuals | None
    names: tuple[str, ...]
    failed: bool
    time_s: np.ndarray | None = None
    gap_ahead: np.ndarray | None = None
    story: Any | None = None
    lane_width_m: float = 4.0

    @property
    def n_steps(self) -> int:
        return int(self.detected.shape[0])

    def decisive_at(self, step: int) -> set[tuple[int, str]]:
        """(object, kind) of the decisive interventions at ``step``."""
        cf = self.counterfactuals
        return set() if cf is None else {(i.obj, i.kind) for i in cf.decisive if i.step == step}


def explain_objects(problem: Problem | None, view, batch, failed: bool) -> ObjectsExplanation:
    """The :class:`ObjectsExplanation` of rollout 0 of ``batch`` (a batch of one rollout with object rows); times in
    the problem's ``dt_s`` (else the drawing's, else 0.1 s).

    Args:
        problem: the run's :class:`pemviz.core.problems.Problem` (error ellipses, counterfactual replays); None:
            neither.
        view: its :class:`pemviz.core.problem_view.ProblemView` (its drawing, an
            :class:`pemviz.app.drawing.ObjectsPanel`, tells the story).
        batch: one rollout, ``objects`` [1, T, M, G] named by ``object_names``.
        failed: whether the rollout failed (only a failure is explained by counterfactuals).

    Raises:
        ValueError: the view has no object positions (``objects_xy``) or the batch no object rows."""
    sc = object_scene(view, batch)
    ellipse = None
    target = getattr(problem, "target", None)
    if sc.measured is not None and target is not None and hasattr(target, "noise_params"):
        rows = batch.objects[0]
        ix, iz = view.noise_xy
        loc, log_scale = target.noise_params(rows.reshape(-1, rows.shape[-1]))
        shape = sc.detected.shape
        loc, scale = np.asarray(loc).reshape(*shape, -1), np.exp(log_scale).reshape(*shape, -1)
        ellipse = np.stack(
            [np.stack([loc[..., ix], scale[..., ix]], -1), np.stack([loc[..., iz], scale[..., iz]], -1)], -2
        )
    cf = None
    if failed and problem is not None and getattr(problem, "branch", None) is not None:
        cf = counterfactuals(problem, batch, 0)
    names = tuple(view.object_label(j) for j in range(sc.detected.shape[1]))
    drawing = objects_panel(getattr(view, "drawing", None))
    scene = drawing.panel_scene() if drawing is not None else None
    dt_s = getattr(problem, "dt_s", None) or (drawing.dt_s if drawing is not None else DEFAULT_DT_S)
    object_names = tuple(batch.object_names or ())
    column = scene.distance_column if scene is not None else ""
    gap = batch.objects[0][:, :, object_names.index(column)].astype(np.float64) if column in object_names else None
    story = drawing.objects_story(batch, names) if drawing is not None else None
    return ObjectsExplanation(
        sc.lateral_m,
        sc.ahead_m,
        sc.detected,
        sc.seen,
        sc.measured,
        ellipse,
        sc.tracked,
        sc.followed,
        cf,
        names,
        bool(failed),
        np.arange(sc.detected.shape[0]) * float(dt_s),
        gap,
        story,
        scene.lane_width_m if scene is not None else DEFAULT_LANE_M,
    )


@dataclass(frozen=True)
class RobustnessOutcome:
    """The outcome of a rollout of a problem without a drawing's outcome: failed or not, by its classic robustness
    (the safety formula's margin, e.g. metres)."""

    robustness: float
    failed: bool

    @property
    def short(self) -> str:
        return f"{'failed' if self.failed else 'safe'}, robustness {self.robustness:+.3g}"

    @property
    def rank(self) -> float:
        """Sort key, larger = worse."""
        return -self.robustness


def state_colour(detected: bool, seen: bool) -> str:
    """An object's colour at a step: green detected, orange missed (visible to the camera), grey unseen."""
    return GREEN if detected else (ORANGE if seen else UNSEEN)


def _road_svg(
    lane_width_m: float, px: Callable[[float, float], tuple[float, float]], width: int, height: int
) -> list[str]:
    """The road of :func:`birds_eye_svg`: the lines of three lanes, the ego's in the middle (dashed between lanes),
    and the distance ahead every 25 m (``px``: metres ahead and to the right -> pixels)."""
    parts = []
    for k in (-1.5, -0.5, 0.5, 1.5):
        y = px(0.0, k * lane_width_m)[1]
        dash = "" if abs(k) > 1 else ' stroke-dasharray="6 6"'
        parts.append(f'<line x1="0" y1="{y:.1f}" x2="{width}" y2="{y:.1f}" stroke="{LANE}"{dash}/>')
    for metres in range(0, int(AHEAD_M[1]) + 1, 25):
        x = px(float(metres), 0.0)[0]
        parts.append(
            f'<text x="{x:.1f}" y="{height - 3}" font-size="9" fill="{AXIS_TEXT}" text-anchor="middle">'
            f"{metres} m</text>"
        )
    return parts


def birds_eye_svg(ox: ObjectsExplanation, step: int, width: int = 430, height: int = 170) -> str:
    """The scene at ``step`` from above: the ego, each object where it truly is (green detected, orange missed, grey
    unseen; red outline where its error was decisive), a detected one's measurement inside the noise PEM's ellipse
    (:data:`ELLIPSE_SCALES`), and the tracker's boxes (the followed one marked "ACC follows"). The road runs to the
    right."""
    t = int(np.clip(step, 0, ox.n_steps - 1))
    lo, hi = AHEAD_M
    sx = width / (hi - lo)
    sy = (height - 20) / (2 * LATERAL_M)

    def px(ahead: float, lateral: float) -> tuple[float, float]:
        return (ahead - lo) * sx, 10 + (lateral + LATERAL_M) * sy

    parts = [
        (
            f'<svg class="pemviz-birds-eye" xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
            f'style="background:{BACKGROUND};border-radius:4px">'
        )
    ]
    parts += _road_svg(ox.lane_width_m, px, width, height)

    def car(ahead: float, lateral: float, fill: str, stroke: str = "none", width_px: float = 0.0) -> str:
        x, y = px(ahead - CAR_LENGTH_M / 2, lateral - CAR_WIDTH_M / 2)
        return (
            f'<rect x="{x:.1f}" y="{y:.1f}" width="{CAR_LENGTH_M * sx:.1f}" height="{CAR_WIDTH_M * sy:.1f}" '
            f'rx="2" fill="{fill}" stroke="{stroke}" stroke-width="{width_px}"/>'
        )

    parts.append(car(0.0, 0.0, EGO))
    ex, ey = px(0.0, 0.0)
    parts.append(f'<text x="{ex:.1f}" y="{ey + 3:.1f}" font-size="9" fill="{ON_EGO}" text-anchor="middle">ego</text>')
    decisive = ox.decisive_at(t)
    for j in range(ox.detected.shape[1]):
        a, lat = float(ox.ahead_m[t, j]), float(ox.lateral_m[t, j])
        if not (np.isfinite(a) and np.isfinite(lat)) or not (lo <= a <= hi and abs(lat) <= LATERAL_M):
            continue
        det, seen = bool(ox.detected[t, j]), bool(ox.seen[t, j])
        hit = any(obj == j for obj, _ in decisive)
        parts.append(car(a, lat, state_colour(det, seen), RED if hit else TEXT, 3.0 if hit else 0.5))
        x, y = px(a, lat)
        parts.append(
            f'<text x="{x:.1f}" y="{y - CAR_WIDTH_M * sy / 2 - 3:.1f}" font-size="10" fill="{TEXT}" '
            f'text-anchor="middle">{j}</text>'
        )
        if det and ox.ellipse is not None:
            (c_lat, r_lat), (c_ahead, r_ahead) = ox.ellipse[t, j]
            cx, cy = px(a + c_ahead, lat + c_lat)
            parts.append(
                f'<ellipse cx="{cx:.1f}" cy="{cy:.1f}" rx="{ELLIPSE_SCALES * r_ahead * sx:.1f}" '
                f'ry="{ELLIPSE_SCALES * r_lat * sy:.1f}" fill="none" stroke="{BLUE}" '
                f'stroke-dasharray="3 2"/>'
            )
        if ox.tracked is not None and np.all(np.isfinite(ox.tracked[t, j])):  # the tracker's estimate, dashed
            tx, ty = px(float(ox.tracked[t, j, 1]) - CAR_LENGTH_M / 2, float(ox.tracked[t, j, 0]) - CAR_WIDTH_M / 2)
            follow = bool(ox.followed[t, j])
            parts.append(
                f'<rect class="pemviz-track" x="{tx:.1f}" y="{ty:.1f}" width="{CAR_LENGTH_M * sx:.1f}" '
                f'height="{CAR_WIDTH_M * sy:.1f}" rx="2" fill="none" stroke="{TRACK}" '
                f'stroke-width="{2.0 if follow else 1.2}" stroke-dasharray="4 2"/>'
            )
            if follow:
                parts.append(
                    f'<text x="{tx + CAR_LENGTH_M * sx / 2:.1f}" y="{ty + CAR_WIDTH_M * sy + 10:.1f}" '
                    f'font-size="9" fill="{TRACK}" text-anchor="middle">ACC follows</text>'
                )
        if det and ox.measured is not None and np.all(np.isfinite(ox.measured[t, j])):
            mx, my = px(float(ox.measured[t, j, 1]), float(ox.measured[t, j, 0]))
            parts.append(
                f'<line x1="{x:.1f}" y1="{y:.1f}" x2="{mx:.1f}" y2="{my:.1f}" stroke="{BLUE}"/>'
                f'<circle cx="{mx:.1f}" cy="{my:.1f}" r="3" fill="{BLUE}"/>'
            )
    parts.append("</svg>")
    return "".join(parts)


def label_width(names: tuple[str, ...]) -> int:
    """The pixels the charts' label column takes: room for the longest object label at 10 px type (34 px at least,
    ``car 0``'s), at most 110."""
    return int(min(max(34, 6 * max((len(n) for n in names), default=0) + 4), 110))


def raster_svg(ox: ObjectsExplanation, step: int, width: int = 430) -> str:
    """Every object's events, a row per object and a column per step: green detected, orange missed, grey unseen;
    a red bar under a decisive miss or error; a black line at ``step`` and a red one at the failure."""
    t_steps, m = ox.detected.shape
    left, cell_h = label_width(ox.names), 13
    cw = (width - left - 4) / t_steps
    height = m * cell_h + 22
    parts = [f'<svg class="pemviz-raster" xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}">']
    for j in range(m):
        y = 2 + j * cell_h
        parts.append(f'<text x="0" y="{y + cell_h - 3}" font-size="10" fill="{TEXT}">{html.escape(ox.names[j])}</text>')
        for t in range(t_steps):
            colour = state_colour(bool(ox.detected[t, j]), bool(ox.seen[t, j]))
            parts.append(
                f'<rect x="{left + t * cw:.2f}" y="{y}" width="{max(cw - 0.3, 0.5):.2f}" '
                f'height="{cell_h - 3}" fill="{colour}"/>'
            )
    cf = ox.counterfactuals
    if cf is not None:
        for i in cf.decisive:
            x, y = left + i.step * cw, 2 + i.obj * cell_h + cell_h - 3
            parts.append(
                f'<rect x="{x:.2f}" y="{y}" width="{max(cw, 2):.2f}" height="3" fill="{RED}">'
                f"<title>decisive: {html.escape(ox.names[i.obj])} {i.kind} at step {i.step}</title></rect>"
            )
        fx = left + cf.failure_step * cw
        parts.append(f'<line x1="{fx:.1f}" y1="0" x2="{fx:.1f}" y2="{m * cell_h + 2}" stroke="{RED}"/>')
    sx = left + (int(step) + 0.5) * cw
    parts.append(f'<line x1="{sx:.1f}" y1="0" x2="{sx:.1f}" y2="{m * cell_h + 2}" stroke="{NOW}" stroke-width="1.5"/>')
    for t in range(0, t_steps, 20):
        parts.append(f'<text x="{left + t * cw:.1f}" y="{height - 4}" font-size="9" fill="{AXIS_TEXT}">{t}</text>')
    parts.append("</svg>")
    return "".join(parts)


def detect_svg(names: tuple[str, ...], p: np.ndarray, q: np.ndarray, step: int, width: int = 430) -> str:
    """Each object's proposal along the rollout, a band per object in the order of :func:`raster_svg`: q(detect) of the
    sampler (blue) and p(detect) of the PEM (grey, dashed) at each step, a black line at ``step``.

    Args:
        names: the M objects' labels.
        p: float64 [T, M] each object's p(detect) under the PEM
            (:func:`pemviz.core.proposal_view.object_detect_probabilities`).
        q: float64 [T, M] each object's q(detect) under the sampler that drew the rollout.
        step: the step marked.
        width: the picture's width (pixels)."""
    t_steps, m = p.shape
    left, band = label_width(names), 22
    cw = (width - left - 4) / t_steps
    height = m * band + 4
    parts = [f'<svg class="pemviz-detect" xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}">']
    x = left + (np.arange(t_steps) + 0.5) * cw
    for j in range(m):
        foot = 2 + (j + 1) * band - 3
        parts.append(
            f'<text x="0" y="{foot - 4}" font-size="10" fill="{TEXT}">{html.escape(names[j])}</text>'
            f'<line x1="{left}" y1="{foot}" x2="{width - 4}" y2="{foot}" stroke="{LANE}"/>'
        )
        for values, colour, dash in ((p[:, j], AXIS_TEXT, ' stroke-dasharray="3,2"'), (q[:, j], BLUE, "")):
            y = foot - (band - 5) * np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0)
            points = " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(x, y, strict=False))
            parts.append(f'<polyline points="{points}" fill="none" stroke="{colour}" stroke-width="1.2"{dash}/>')
    sx = left + (int(step) + 0.5) * cw
    parts.append(f'<line x1="{sx:.1f}" y1="0" x2="{sx:.1f}" y2="{height}" stroke="{NOW}" stroke-width="1.5"/>' "</svg>")
    return "".join(parts)


def decisive_table(ox: ObjectsExplanation) -> str:
    """The decisive interventions, one row each: object, step, what was undone, the replay's robustness."""
    cf = ox.counterfactuals
    if cf is None or not cf.decisive:
        return ""
    rows = "".join(
        f"<tr><td>{html.escape(ox.names[i.obj])}</td><td>{i.step}</td><td style='text-align:left'>"
        + (
            "missed: flipped to an exact detection"
            if i.kind == MISS
            else "mislocated by " + ", ".join(f"{e:+.2f} m" for e in i.error) + ": error set to zero"
        )
        + f"</td><td>{i.robustness:+.3f}</td></tr>"
        for i in cf.decisive[:12]
    )
    more = f"<div>... and {len(cf.decisive) - 12} more</div>" if len(cf.decisive) > 12 else ""
    return (
        '<table class="pemviz-table" style="width:100%;font-size:0.95em"><tr><th>object</th><th>step</th>'
        f"<th>undone alone</th><th>robustness after</th></tr>{rows}</table>{more}"
    )


def story_html(ox: ObjectsExplanation) -> str:
    """*What happened* to the objects and the ego, in words, and the **severity** (e.g. the minimum clearance in
    metres, the closing speed in m/s at contact), as HTML lines (the story's ``severity.short`` and ``text``); empty
    without a story."""
    st = ox.story
    if st is None:
        return ""
    return f"<b>Severity</b>: {html.escape(st.severity.short)}<br><b>What happened</b>: {html.escape(st.text)}"


def objects_summary(ox: ObjectsExplanation) -> str:
    """One line: which objects' errors were decisive, or why there is nothing to say."""
    cf = ox.counterfactuals
    if not ox.failed:
        return "no failure: nothing to explain (the safety formula held)"
    if cf is None:
        return "the problem cannot replay its rollouts: no counterfactual"
    return cf.summary(ox.names)


def state_counts(ox: ObjectsExplanation, step: int) -> str:
    """``step 17: 3 detected, 1 missed, 1 unseen``."""
    t = int(np.clip(step, 0, ox.n_steps - 1))
    d, s = ox.detected[t], ox.seen[t]
    return f"step {t}: {int(d.sum())} detected, {int((~d & s).sum())} missed, {int((~s).sum())} unseen"
