"""What the rerun recording looks like (:mod:`pemviz.sinks.recording`): colours, figures with axes, the marginal
proposal's bars, a rollout's outcome in words, the run's description and the top-down scene. Everything here draws into
a :class:`rerun.RecordingStream` it is given and keeps no state of a run."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from pemviz.core.problem_view import ProblemView
from pemviz.core.proposal_view import LOG_ODDS_SPAN_NATS, ProposalView
from pemviz.core.rollouts import RolloutBatch
from pemviz.engine.events import RolloutsSampled, RunStarted
from pemviz.plugins import resolve
from pemviz.sinks import colours as C
from pemviz.sinks.drawing import recording_hooks


def _pyarrow_without_pandas() -> None:
    """Let pyarrow settle, before rerun's first conversion, that this process hands it no pandas objects, without
    importing pandas: the import is refused for that one call (a finder that raises ``ImportError``, removed at once);
    pyarrow's paths that need pandas still import it when asked. Nothing changes where pandas is imported already."""
    import sys

    import pyarrow as pa

    class NoPandas:
        @staticmethod
        def find_spec(name: str, path: object = None, target: object = None) -> None:
            if name == "pandas":
                raise ImportError("pandas: not needed to convert numpy arrays")

    if "pandas" in sys.modules:
        return
    finder = NoPandas()
    sys.meta_path.insert(0, finder)
    try:
        pa.array(np.zeros(1, dtype=np.bool_))
    finally:
        sys.meta_path.remove(finder)


_pyarrow_without_pandas()

CRASH_RGBA = C.rgba(C.CRASH, 170)
SAFE_RGBA = C.rgba(C.SAFE, 60)
TAG_RGBA = C.rgba(C.TAGGED)
TAG_CRASH_RGBA = C.rgba(C.CRASH)
LIKELY_RGBA = C.rgba(C.BLUE)
"""The most likely failures of each stage (their own entities, :meth:`pemviz.sinks.recording.RerunSink.featured`)."""
PEM_RGBA = C.rgba(C.ON_DARK)
"""The PEM in the figures drawn on their own dark background (:class:`Figure`)."""
PEM_PLOT_RGBA = C.rgba(C.GREY)
"""The PEM in rerun's own plots (bar charts, time series), whose background follows the viewer's light or dark theme."""
AXIS_RGBA = C.rgba(C.AXIS)
GRID_RGBA = C.rgba(C.GRID, 120)
DETECTED_RGBA = C.rgba(C.DETECTED)
MISSED_RGBA = C.rgba(C.MISSED)
OBJECT_RGBA = C.rgba(C.OBJECT)
OBJECT_CRASH_RGBA = C.rgba(C.CRASH)
BRAKE_RGBA = C.rgba(C.BRAKE_ZONE)
ALL_ROLLOUTS_UP_TO = 500
"""Stages of at most this many rollouts are recorded rollout by rollout; larger ones keep the least-robust
rollouts and a uniform sample (:data:`SAMPLED_ROLLOUTS`)."""
SAMPLED_ROLLOUTS = 100
HISTOGRAM_BINS = 40
LANE_SPACING_M = 3.2
SCENE_X_RANGE_M = (-30.0, 40.0)
"""Top-down scene: lanes ``LANE_SPACING_M`` apart (e.g. cars 2 m wide), x from the lane labels to past where the
objects stop (a lane reaches further where its drawing asks)."""

STAGE_METRICS = (
    ("log10_mu_hat", "log10 mu_hat", C.BLUE),
    ("failure_rate", "failures / N", C.CRASH),
    ("gamma", "threshold gamma", C.VIOLET),
    ("ess", "ESS", C.DETECTED),
    ("khat", "Pareto k-hat", C.MISSED),
    ("nll", "NLL of the failures (nats)", C.NEUTRAL),
)
"""Per-stage values: key under ``stages/``, series name, colour."""


def nice_ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    """Round tick values in [lo, hi]: the step of 1, 2 or 5 x 10^k nearest (in ratio) to (hi - lo) / n."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return np.array([lo])
    raw = (hi - lo) / max(1, n)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 5, 10)), key=lambda st: abs(math.log(st / raw)))
    first = math.ceil(lo / step - 1e-9) * step
    return np.round(np.arange(first, hi + step * 1e-9, step), 10)


@dataclass(frozen=True)
class Figure:
    """A static x-y plot in a 2D view: data in axis units under ``PATH/data``, a frame under ``PATH/axes``.

    A :class:`rerun.Transform3D` on ``PATH/data`` maps (x, y) in axis units to a ``width`` x ``height``
    box with y pointing up (rerun's 2D y axis points down), so the logged points keep their real values."""

    path: str
    x_label: str
    y_label: str
    width: float = 160.0
    height: float = 100.0

    def draw_axes(
        self,
        stream: rr.RecordingStream,
        x_range: tuple[float, float],
        y_range: tuple[float, float],
        x_ticks: np.ndarray | None = None,
        n_y_ticks: int = 5,
        static: bool = True,
    ) -> None:
        """Log the data transform, the frame, grid lines and tick labels for these ranges (about ``n_y_ticks`` round
        values on the y axis): static, or with ``static=False`` on the stream's current time (axes that change)."""
        (x0, x1), (y0, y1) = x_range, y_range
        if y1 <= y0:
            y0, y1 = y0 - 0.5, y1 + 0.5
        sx, sy = self.width / (x1 - x0), self.height / (y1 - y0)
        stream.log(
            f"{self.path}/data",
            rr.Transform3D(translation=[-x0 * sx, y1 * sy, 0.0], scale=[sx, -sy, 1.0]),
            static=static,
        )
        w, h = self.width, self.height
        xt = nice_ticks(x0, x1, 6) if x_ticks is None else np.asarray(x_ticks, dtype=np.float64)
        yt = nice_ticks(y0, y1, n_y_ticks)
        xt = xt[(xt >= x0) & (xt <= x1)]
        yt = yt[(yt >= y0) & (yt <= y1)]
        X = (xt - x0) * sx
        Y = (y1 - yt) * sy
        grid = [[[x, 0.0], [x, h]] for x in X] + [[[0.0, y], [w, y]] for y in Y]
        stream.log(f"{self.path}/axes/grid", rr.LineStrips2D(grid, colors=GRID_RGBA, radii=-0.5), static=True)
        frame: list[list[list[float]]] = [[[0, 0], [w, 0], [w, h], [0, h], [0, 0]]]
        stream.log(f"{self.path}/axes/frame", rr.LineStrips2D(frame, colors=AXIS_RGBA, radii=-1.0), static=static)
        pos = [[x, h + 0.045 * h] for x in X] + [[-0.06 * w, y] for y in Y]
        labels = [f"{v:g}" for v in xt] + [f"{v:g}" for v in yt]
        for text, xy in ((self.x_label, [w / 2, h + 0.13 * h]), (self.y_label, [-0.06 * w, -0.07 * h])):
            if text:  # small figures leave the axis titles to the view's name
                pos.append(xy)
                labels.append(text)
        stream.log(
            f"{self.path}/axes/labels",
            rr.Points2D(pos, radii=-0.01, colors=AXIS_RGBA, labels=labels, show_labels=True),
            static=static,
        )

    def view(self, name: str, legend_room: float = 0.0) -> rrb.Spatial2DView:
        """A 2D view of this figure with bounds that fit the frame, the tick labels, the axis titles and
        ``legend_room`` (a fraction of the width) right of the frame for a legend."""
        w, h = self.width, self.height
        return rrb.Spatial2DView(
            origin=self.path,
            name=name,
            visual_bounds=rrb.VisualBounds2D(
                x_range=[-0.16 * w, (1.04 + legend_room) * w], y_range=[-0.16 * h, 1.24 * h]
            ),
            background=C.FIGURE_BACKGROUND,
        )


PROPOSAL_FIG = Figure("proposal", "gap d (m)", "p(detect | d)")
SCENE_PATH = "scene"


Indexes = Callable[..., list]
"""``indexes(step=array)``: the time columns of a ``send_columns`` (the sink's, with its repetition)."""


def method_markdown(ev: RunStarted) -> str:
    """One sentence on the run's method, its stages and sizes from the run's plan: the method's own words
    (:attr:`pemviz.methods.Method.describe`), else its plan's stages."""
    cfg, plan = ev.config, ev.plan
    record = cfg.method_record
    if record.describe is None:
        stages = ", ".join(f"{s.label} ({s.n_rollouts} rollouts)" for s in plan.stages)
        return f"method **{cfg.method}**: {stages or 'no stage planned'}."
    window = ev.problem.thresholds.labels()[1] if ev.problem.thresholds is not None else "the sampler window"
    return str(resolve(record.describe)(cfg, plan, window))


def intro_markdown(ev: RunStarted) -> str:
    """The head of the recording's description: what the run estimates (from its problem view) and how to read it."""
    view, cfg = ev.problem, ev.config
    method = method_markdown(ev)
    bins = (
        ""
        if view.objects_xy is not None
        else "the sampler's q(miss) over the states the last stage's rollouts "
        "visited, per gap bin, beside the PEM's (grey), as a probability and as log-odds, "
    )
    reading = (
        "**How to read it.** Three tabs; the recording opens on the `step` timeline, where each has content. "
        "*Stages* (0 = pretraining, 1..K = CE stages, K+1 = final batch, as in the console): the per-stage series "
        f"(static figures), {bins}the histograms of robustness and importance log-weight (choose the `stage` "
        "timeline in the time panel below and scrub it to see each stage's) and the proposal's reference-state "
        "curves. *Explain* (`step`): the most likely failure (the failing rollout with the largest log p under the "
        "PEM), its p and q along it, its misses and what would have avoided it. *Rollouts* (`step`): the kept "
        "rollouts of every stage"
    )
    lines = " and ".join(view.thresholds.labels()) if view.thresholds is not None else ""
    colours = "red = failure, yellow = least robust, blue = most likely failures, orange x = misses"
    traces = f" ({view.signals[0].column} with the lines {lines}; {colours})" if lines else f" ({colours})"
    drawing = recording_hooks(view.drawing)
    told = drawing.intro(ev.formula, cfg.metric, method) if drawing is not None else None
    if told is not None:
        head, scene = told
        return f"{head}\n\n{reading}{traces}{scene}\n"
    return (
        f"# pemviz: failure probability of {view.name}\n\n{view.description}. Failure: classic robustness of the "
        f"safety spec `{ev.formula}` below 0; rollouts are ranked by **{cfg.metric}** robustness. Method: {method}\n\n"
        f"{reading}{traces}.\n"
    )


def outcome_values(drawing: object, batch: RolloutBatch, i: int) -> dict | None:
    """Rollout ``i``'s outcome as the recording's properties (:meth:`pemviz.sinks.drawing.RecordingDrawing.
    outcome_values`: ``outcome`` words, ``contact`` and the scenario's numbers), None without a drawing object or
    where it has none."""
    hooks = recording_hooks(drawing)
    values = hooks.outcome_values(batch, i) if hooks is not None else None
    return dict(values) if values is not None else None


def draws_scene(drawing: object) -> bool:
    """Whether the drawing object draws a scene with contact (:attr:`pemviz.sinks.drawing.RecordingDrawing.draws_scene`;
    False for None or a drawing without it)."""
    return bool(getattr(drawing, "draws_scene", False))


def contact_share(drawing: object, batch: RolloutBatch, failed: np.ndarray) -> dict[str, float]:
    """``{"contact_share": s}``: the share of the failing rollouts of ``batch`` (``failed``: bool [N]) that made
    contact (the ``contact`` of :func:`outcome_values`; the drawing object's optional ``contacts(batch, rows)``, bool
    [k] or None, answers for all of them at once), for the recording's per-stage series; ``{}`` where the drawing
    draws no scene, says nothing of contact, or no rollout failed."""
    rows = np.flatnonzero(np.asarray(failed, bool))
    if not draws_scene(drawing) or rows.size == 0:
        return {}
    contacts = getattr(drawing, "contacts", None)  # all rows at once, where the drawing object can
    made = contacts(batch, rows) if contacts is not None else None
    if made is None:
        told = [outcome_values(drawing, batch, int(i)) for i in rows]
        if any(t is None for t in told):
            return {}
        made = [bool(t["contact"]) for t in told if t is not None]  # none is None, as just checked
    return {"contact_share": float(np.mean(made))}


def outcome(drawing: object, batch: RolloutBatch, i: int, failed: bool) -> str:
    """A rollout's outcome in the words the console, the panel and the recording share: the drawing object's
    (:func:`outcome_values`, e.g. ``contact at 3.2 m/s``, ``breach 1.91 m, no contact``, ``safe, min gap 3.41 m``),
    else ``failure`` or ``safe``."""
    values = outcome_values(drawing, batch, i)
    if values is not None:
        return str(values["outcome"])
    return "failure" if failed else "safe"


MARGINAL_PATH = "proposal_marginal"
"""Root of the marginal proposal view: ``miss`` and ``log_odds`` bar charts, the view's numbers (``stats``)."""


def log_marginal_proposal(stream: rr.RecordingStream, pv: ProposalView, rgb: tuple[int, ...]) -> None:
    """One stage's :class:`~pemviz.core.proposal_view.ProposalView` as bars per gap bin, on the current timeline.

    Two charts: ``miss`` (q(miss), mean over the bin's visited states) and ``log_odds`` (the median of log q(miss) /
    q(detect), nats, clipped to :data:`~pemviz.core.proposal_view.LOG_ODDS_SPAN_NATS`): the PEM's (grey) and the
    sampler's (``rgb``) bars, with the sampler's 10-90 % spread behind. ``stats`` holds every array of the view."""
    c, w = pv.centres_m, np.diff(pv.edges_m)
    empty = pv.n_states == 0
    span = LOG_ODDS_SPAN_NATS

    def bars(path: str, values: np.ndarray, x: np.ndarray, width: np.ndarray, colour: Sequence[int]) -> None:
        v = np.where(empty, 0.0, np.nan_to_num(np.asarray(values, dtype=np.float64), nan=0.0))
        stream.log(path, rr.BarChart(v, abscissa=x, widths=width, color=colour))

    scales = {
        "miss": (1.0 - pv.p_mean, 1.0 - pv.q_mean, 1.0 - pv.q_hi, 1.0 - pv.q_lo),
        "log_odds": tuple(
            np.clip(a, -span, span) for a in (pv.p_log_odds, pv.q_log_odds, pv.q_log_odds_lo, pv.q_log_odds_hi)
        ),
    }
    light = C.rgba(rgb, 80)
    for key, (pem, q, q_a, q_b) in scales.items():
        path = f"{MARGINAL_PATH}/{key}"
        bars(f"{path}/a_pem", pem, c - w / 4, w * 0.22, PEM_PLOT_RGBA)
        bars(f"{path}/b_q_quantile_a", q_a, c + w / 4, w * 0.44, light)  # drawn in path order: spread, then q
        bars(f"{path}/c_q_quantile_b", q_b, c + w / 4, w * 0.44, light)
        bars(f"{path}/d_q", q, c + w / 4, w * 0.22, C.rgba(rgb))
    fields = {k: v for k, v in vars(pv).items()}
    stream.log(f"{MARGINAL_PATH}/stats", rr.AnyValues(**fields))


def log_thresholds(
    stream: rr.RecordingStream, view: ProblemView, n_steps: int, indexes: Indexes, path: str | None = None
) -> None:
    """The failure threshold and the sampler window as two lines over ``n_steps`` steps beside the first signal's
    traces (at ``path``, default ``rollouts/<column>/thresholds``); nothing for a problem without thresholds."""
    th = view.thresholds
    if th is None:
        return
    path = path or f"rollouts/{view.signals[0].column}/thresholds"
    stream.log(
        path,
        rr.SeriesLines(colors=[CRASH_RGBA[:3] + (255,), BRAKE_RGBA], widths=[2.0, 2.0], names=list(th.labels())),
        static=True,
    )
    t = np.arange(n_steps)
    levels = np.array([[th.failure, th.window]] * t.size)
    stream.send_columns(path, indexes=indexes(step=t), columns=rr.Scalars.columns(scalars=levels))


def log_scene_lane(
    stream: rr.RecordingStream, path: str, lane: int, ev: RolloutsSampled, i: int, drawing: object, indexes: Indexes
) -> bool:
    """One lane (number ``lane``) of the top-down scene under ``path``: rollout ``i`` of the stage as the drawing
    object draws it (:meth:`pemviz.sinks.drawing.RecordingDrawing.scene_lane`: its objects as boxes, ``path/<name>``,
    and a sight line, ``path/sight``, metres along the road), playable on ``step``, labelled with its stage and
    outcome (:func:`outcome`); returns False (nothing logged) where the drawing draws no lane of it."""
    s, batch = stream, ev.batch
    hooks = recording_hooks(drawing)
    drawn = hooks.scene_lane(batch, i) if hooks is not None else None
    if drawn is None:
        return False
    boxes, sight_x, end_m = drawn
    seen = batch.detected[i, :, 0]
    t = seen.size
    y = lane * LANE_SPACING_M
    ys = np.full(t, y)
    words = outcome(drawing, batch, i, bool(ev.failed[i]))
    label = f"s{ev.stage}: {words}"
    detail = f"stage {ev.stage} ({ev.kind}) rollout {ev.rollout_numbers[i]}: robustness {ev.robustness[i]:.3g}, {words}"
    half = LANE_SPACING_M / 2 - 0.1
    x_end = float(max(end_m, SCENE_X_RANGE_M[1]))
    s.log(
        f"{path}/lane",
        rr.LineStrips2D(
            [[[-4.0, y - half], [x_end, y - half]], [[-4.0, y + half], [x_end, y + half]]],
            colors=GRID_RGBA,
            radii=-0.75,
            labels=[detail, detail],
            show_labels=False,
        ),
        static=True,
    )
    s.log(
        f"{path}/label",
        rr.Points2D(
            [[-16.0, y]],
            radii=-0.01,
            colors=OBJECT_CRASH_RGBA if ev.failed[i] else AXIS_RGBA,
            labels=label,
            show_labels=True,
        ),
        static=True,
    )
    index = indexes(step=np.arange(t))
    det_col = np.where(seen[:, None], np.array(DETECTED_RGBA), np.array(MISSED_RGBA)).astype(np.uint8)
    for name, centre_x, half_size, alarm in boxes:
        colours = (
            det_col
            if alarm is None
            else np.where(np.asarray(alarm, bool)[:, None], np.array(OBJECT_CRASH_RGBA), np.array(OBJECT_RGBA)).astype(
                np.uint8
            )
        )
        s.send_columns(
            f"{path}/{name}",
            indexes=index,
            columns=rr.Boxes2D.columns(
                centers=np.column_stack([centre_x, ys]),
                half_sizes=np.tile(list(half_size), (t, 1)),
                colors=colours,
                radii=np.full(t, -2.0),
            ),
        )
    if sight_x is not None:
        sight = np.stack([np.column_stack([sight_x[0], ys]), np.column_stack([sight_x[1], ys])], axis=1)
        s.send_columns(
            f"{path}/sight",
            indexes=index,
            columns=rr.LineStrips2D.columns(strips=sight, colors=det_col, radii=np.full(t, -1.5)),
        )
    return True
