"""uPlot figures of the panel (viser's ``add_uplot``): proposal curves, per-stage values, the strip chart. Every
figure names its axes, keeps its legend to the series' names and sets its ranges from the data that exists; values
far from the rest are drawn at the edge, ringed and counted in the caption (:func:`robust_range`,
:mod:`pemviz.app.captions`). Colours come from :mod:`pemviz.sinks.colours`."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np
import viser
import viser.uplot as up

from pemviz.app.captions import LOG_W_CAPTION, add_chart, set_chart
from pemviz.app.drawing import LaneExplanation
from pemviz.app.runs import PanelRun
from pemviz.scenarios.panel_data import CurveAxis, Series
from pemviz.sinks import colours as C
from pemviz.sinks.colours import (
    BRAKE_ZONE,
    CRASH,
    DETECTED,
    EGO_SPEED,
    LOG_WEIGHT,
    MISSED,
    OBJECT_SPEED,
    PROPOSAL,
    css,
    hex_colour,
    stage_rgb,
)

if TYPE_CHECKING:
    from pemviz.core.problem_view import Thresholds

RUN_COLOURS = tuple(hex_colour(c) for c in C.RUN_COLOURS)
"""Series colour of a run: its number modulo 6 (:data:`pemviz.sinks.colours.RUN_COLOURS`)."""

STAGE_PLOTS = (
    ("gamma", "threshold gamma per stage", "gamma"),
    ("failure_rate", "failures / N per stage", "failures / N"),
    ("log10_mu_hat", "log10 mu_hat per stage", "log10 mu_hat"),
    ("nll", "NLL of the failures per stage", "NLL (nats)"),
)
GAMMA_UNITS = {"classic": "m", "agm": "unitless", "smooth-cumulative": "m"}
LEGEND = up.Legend(show=True, live=False)
SERIES_STYLE: dict[str, up.Series] = {
    "main": {"stroke": hex_colour(C.BLACK), "width": 2},
    "ego": {"stroke": css(EGO_SPEED), "width": 1.5},
    "object": {"stroke": css(OBJECT_SPEED), "width": 1.5},
}
"""The strip chart's line of each :attr:`pemviz.scenarios.panel_data.Series.role`: colour and width."""


def run_colour(run_id: int) -> str:
    """Series colour of run number ``run_id`` (from 1; :data:`RUN_COLOURS`, cycling)."""
    return RUN_COLOURS[(run_id - 1) % len(RUN_COLOURS)]


def axes(x_label: str, y_label: str) -> tuple[up.Axis, up.Axis]:
    """An x and a y axis with titles; the y axis wide enough for ``-14.75``."""
    return (up.Axis(label=x_label, size=36), up.Axis(label=y_label, size=62, gap=4))


@dataclass(frozen=True)
class AxisRange:
    """A chart's y range and the values it leaves off scale (:func:`robust_range`).

    Attributes:
        lo, hi: the range, in the chart's unit (lo < hi).
        n_below, n_above: finite values below ``lo`` / above ``hi``: off scale, drawn at that edge.
        lowest, highest: the smallest and largest finite value of all (nan without one), to name an off-scale
            extreme."""

    lo: float
    hi: float
    n_below: int = 0
    n_above: int = 0
    lowest: float = math.nan
    highest: float = math.nan

    @property
    def range(self) -> tuple[float, float]:
        return (self.lo, self.hi)

    @property
    def n_off(self) -> int:
        """Values off scale, both edges."""
        return self.n_below + self.n_above

    def drawn(self, values: np.ndarray) -> np.ndarray:
        """Where ``values`` are drawn, float64 of their shape: a value inside the range at its place, one below or
        above it at that edge (clamped), nan and +-inf (no value) as nan."""
        v = np.asarray(values, dtype=np.float64)
        return np.where(np.isfinite(v), np.clip(v, self.lo, self.hi), np.nan)

    def below(self, values: np.ndarray) -> np.ndarray:
        """bool of ``values``' shape: finite and below ``lo`` (drawn at the bottom edge)."""
        v = np.asarray(values, dtype=np.float64)
        return np.isfinite(v) & (v < self.lo)

    def above(self, values: np.ndarray) -> np.ndarray:
        """bool of ``values``' shape: finite and above ``hi`` (drawn at the top edge)."""
        v = np.asarray(values, dtype=np.float64)
        return np.isfinite(v) & (v > self.hi)

    def note(self, what: str = "point", spec: str = ".1f", unit: str = "") -> str:
        """``'; 2 points off scale, drawn at the edge (lowest -40.0)'`` for a title; ``''`` when none is."""
        if not self.n_off:
            return ""
        ends = ([f"lowest {self.lowest:{spec}}{unit}"] if self.n_below else []) + (
            [f"highest {self.highest:{spec}}{unit}"] if self.n_above else []
        )
        return f"; {self.n_off} {what}{'s' * (self.n_off != 1)} off scale, drawn at the edge ({', '.join(ends)})"


def robust_range(
    values: np.ndarray,
    matters: np.ndarray | None = None,
    *,
    min_gap: float = math.inf,
    factor: float = 2.0,
    pad_frac: float = 0.08,
    min_pad: float = 0.0,
    at_least: tuple[float, float] | None = None,
    limits: tuple[float, float] = (-math.inf, math.inf),
    empty: tuple[float, float] = (-0.05, 1.05),
) -> AxisRange:
    """The y range of a chart fitted to the values that matter, and what it leaves off scale (the chart's unit).

    From the median of the finite ``values`` where ``matters`` (all without it), take in the nearest remaining
    candidate one at a time; once more than half are in, stop at the first whose gap to those taken is wider than
    both ``min_gap`` and ``factor`` times their span (``min_gap = inf``: take all). The range is their [min, max]
    padded by max(``pad_frac`` * span, ``min_pad``), widened to ``at_least`` and cut to ``limits``. Values outside
    it are drawn at the nearer edge (:meth:`AxisRange.drawn`) and counted (:meth:`AxisRange.note`). Without any
    candidate: ``at_least`` or ``empty``."""
    v = np.asarray(values, dtype=np.float64).ravel()
    ok = np.isfinite(v)
    finite = v[ok]
    c = np.sort(v[ok & (np.ones(v.size, bool) if matters is None else np.asarray(matters, bool).ravel())])
    if c.size == 0 and at_least is None:
        lo, hi = empty
    elif c.size == 0:  # only at_least to cover; one value of it (an exact answer before any failure) padded as in 3
        assert at_least is not None  # the branch above takes no candidate and no at_least
        lo, hi = float(at_least[0]), float(at_least[1])
        if not hi > lo:
            pad = min_pad if min_pad > 0.0 else max(0.5, 0.1 * abs(lo))
            lo, hi = lo - pad, hi + pad
    else:
        i = j = (c.size - 1) // 2  # the taken candidates are c[i..j]
        while i > 0 or j < c.size - 1:
            down = c[i] - c[i - 1] if i > 0 else math.inf
            up_ = c[j + 1] - c[j] if j < c.size - 1 else math.inf
            gap = min(down, up_)
            if j - i + 1 > c.size / 2 and gap > min_gap and gap > factor * (c[j] - c[i]):
                break
            i, j = (i - 1, j) if down <= up_ else (i, j + 1)
        lo, hi = float(c[i]), float(c[j])
        pad = max(pad_frac * (hi - lo), min_pad)
        if pad <= 0.0:
            pad = max(0.5, 0.1 * abs(lo))
        lo, hi = lo - pad, hi + pad
        if at_least is not None:
            lo, hi = min(lo, at_least[0]), max(hi, at_least[1])
    lo, hi = max(lo, limits[0]), min(hi, limits[1])
    if not hi > lo:  # never a range without width (uPlot cannot draw one): values cut to a single limit
        lo, hi = (lo - 0.5, lo + 0.5) if math.isfinite(lo) else empty
    return AxisRange(
        float(lo),
        float(hi),
        int(np.sum(finite < lo)),
        int(np.sum(finite > hi)),
        float(finite.min()) if finite.size else math.nan,
        float(finite.max()) if finite.size else math.nan,
    )


class RangeRules(TypedDict, total=False):
    """Settings of :func:`robust_range` kept by name (:data:`STAGE_RULES`)."""

    min_gap: float
    factor: float
    pad_frac: float
    min_pad: float


STAGE_RULES: dict[str, RangeRules] = {"log10_mu_hat": {"min_gap": 3.0, "min_pad": 0.05}, "gamma": {}, "nll": {}}
""":func:`robust_range` settings of the per-stage charts. log10 mu_hat: a stage more than 3 orders of magnitude (and
twice the others' spread) from the others is off scale, at least 0.05 (log10 probability) of room each side;
gamma and NLL keep every value (their fall over the stages is what they show)."""


def stage_range(key: str, series: list[np.ndarray], matters: list[np.ndarray] | None = None) -> AxisRange:
    """The y range of a per-stage chart (:data:`STAGE_PLOTS`) over the runs' ``series``: failures / N is always
    -0.05..1.05; the others follow :func:`robust_range` with :data:`STAGE_RULES`."""
    if key == "failure_rate":
        return AxisRange(-0.05, 1.05)
    flat = [np.asarray(s, dtype=np.float64).ravel() for s in series]
    values = np.concatenate(flat) if flat else np.zeros(0)
    mask = None if matters is None else np.concatenate([np.asarray(m, bool).ravel() for m in matters])
    return robust_range(values, mask, **STAGE_RULES.get(key, {}))


def y_range(key: str, series: list[np.ndarray]) -> tuple[float, float]:
    """(lo, hi) of :func:`stage_range` ((-0.05, 1.05) for rates or without values)."""
    return stage_range(key, series).range


def off_scale_series(x: np.ndarray, rng: AxisRange, ys: list[np.ndarray]) -> tuple[list[Any], list[np.ndarray]]:
    """Black rings at the bottom / top edge where any of ``ys`` (each [x.size]) is below / above ``rng``: the
    series and data to append to a chart (none for an edge with nothing off scale). The labels say how many."""
    series: list[Any] = []
    data: list[np.ndarray] = []
    for edge, side, name in ((rng.lo, rng.below, "below"), (rng.hi, rng.above, "above")):
        hits = np.zeros(np.shape(x), bool)
        n = 0
        for y in ys:
            m = side(y)
            hits |= m
            n += int(m.sum())
        if n:
            series.append(
                up.Series(
                    label=f"{n} {name} the scale (at the edge)",
                    stroke=hex_colour(C.BLACK),
                    points=_ring(C.BLACK),
                    width=0,
                )
            )
            data.append(np.where(hits, edge, np.nan))
    return series, data


def curve_plot(gui: viser.GuiApi, title: str, height: int = 230, visible: bool = True) -> viser.GuiUplotHandle:
    """An empty q(detect | gap) plot: gap 0..13 m, probability 0..1 (the top tick 1 included)."""
    return add_chart(
        gui,
        data=(np.linspace(0, 13, 2), np.full(2, np.nan)),
        series=(up.Series(label="gap (m)"), up.Series(label="PEM", stroke=hex_colour(C.BLACK))),
        title=title,
        scales={"x": up.Scale(time=False, auto=False, range=(0.0, 13.0)), "y": up.Scale(auto=False, range=(0.0, 1.04))},
        axes=axes("gap d (m)", "p(detect | d)"),
        legend=LEGEND,
        height=height,
        visible=visible,
    )


DEFAULT_CURVE_AXIS = CurveAxis("gap (m)", "gap d (m)", "p(detect | d)")
"""The x axis of a proposal's reference-state curve where the problem's drawing gives none
(:meth:`pemviz.app.drawing.PanelDrawing.curve_axis`): the distance to the object ahead (metres)."""


def fill_curve_plot(plot: viser.GuiUplotHandle, record: PanelRun, title: str, caption: str = "") -> None:
    """The PEM and the proposal after each stage (blue early, orange late) of ``record``, over the run's curve grid
    (metres, e.g. 0-13 m of gap in the braking scenario, 0-50 m of range in the cut-in), its axis the drawing's
    (:meth:`pemviz.app.drawing.PanelDrawing.curve_axis`, else :data:`DEFAULT_CURVE_AXIS`)."""
    with record.lock:
        grid, pem = record.curve_grid_m, record.pem_curve
        stages = [s for s in record.stages if not np.all(np.isnan(s.proposal_curve)) and s.kind != "final"]
    if grid.size == 0:
        return
    hook = getattr(record.view.drawing if record.view is not None else None, "curve_axis", None)
    axis = hook() if callable(hook) else DEFAULT_CURVE_AXIS
    n_colour = C.stage_span(record.plan)  # blue (stage 0) to orange (the last stage)
    series = [up.Series(label=axis.series_label), up.Series(label="PEM", stroke=hex_colour(C.BLACK), width=2)]
    data = [grid, pem]
    for s in stages:  # the final batch samples from the last stage's proposal: the same curve
        name = "pretraining" if s.kind == "pretrain" else f"stage {s.stage}"  # short: uPlot's legend is narrow
        series.append(up.Series(label=name, stroke=css(stage_rgb(s.stage, n_colour)), width=1.5))
        data.append(np.asarray(s.proposal_curve, dtype=np.float64))
    set_chart(plot, title, caption)
    plot.series = tuple(series)
    plot.data = tuple(data)
    plot.scales = {
        "x": up.Scale(time=False, auto=False, range=(float(np.min(grid)), float(np.max(grid)))),
        "y": up.Scale(auto=False, range=(0.0, 1.04)),
    }
    plot.axes = axes(axis.label, axis.y_label)


def stage_plot(gui: viser.GuiApi, title: str, y_label: str) -> viser.GuiUplotHandle:
    """An empty per-stage chart titled ``title`` (y axis ``y_label``, 0 to 1 until a run fills it), added to ``gui``."""
    return add_chart(
        gui,
        data=(np.arange(2, dtype=np.float64), np.full(2, np.nan)),
        series=(up.Series(label="stage"), up.Series(label="no run yet", stroke=hex_colour(C.GREY))),
        title=title,
        scales={
            "x": up.Scale(time=False, auto=False, range=(-0.5, 1.5)),
            "y": up.Scale(auto=False, range=(-0.05, 1.05)),
        },
        axes=axes("stage (0 pretraining, K+1 final batch)", y_label),
        legend=LEGEND,
        height=150,
    )


def stage_values(key: str, runs: list[PanelRun]) -> tuple[str, str, list[PanelRun], np.ndarray, list[np.ndarray]]:
    """(title, caption, the runs drawn, stages 0..last float64, each drawn run's value per stage float64 [stages],
    nan where it has none) of a per-stage chart (:data:`STAGE_PLOTS`). ``gamma`` draws only the newest run's metric."""
    title, caption = dict((k, t) for k, t, _ in STAGE_PLOTS)[key], ""
    shown = runs
    if key == "gamma" and runs:
        metric = runs[-1].config.metric
        shown = [r for r in runs if r.config.metric == metric]
        left_out = len(runs) - len(shown)
        title = f"gamma per stage, {metric} ({GAMMA_UNITS.get(metric, 'unitless')})"
        caption = "gamma: the robustness level each stage's elite rollouts reached (the stage's threshold)" + (
            f"; {left_out} run{'s' * (left_out != 1)} of another metric not shown" if left_out else ""
        )
    values = [r.stage_series(key) for r in shown]
    last = max([max(v) for v in values if v] + [1])
    x = np.arange(last + 1, dtype=np.float64)
    ys = []
    for v in values:
        y = np.full(x.size, np.nan)
        for stage, value in v.items():
            y[stage] = value
        ys.append(y)
    return title, caption, shown, x, ys


def run_series(r: PanelRun) -> up.Series:
    """A run's line with dots, in its colour, labelled with its short label."""
    colour = run_colour(r.run_id)
    return up.Series(label=r.short_label, stroke=colour, width=2, points={"show": True, "size": 5, "fill": colour})


def fill_stage_plot(plot: viser.GuiUplotHandle, key: str, runs: list[PanelRun]) -> None:
    """One series per run over the stages finished so far. ``gamma``'s unit depends on the metric, so only runs with
    the newest run's metric are drawn (the caption counts the others); the y range is :func:`stage_range`'s."""
    if not runs:
        return
    title, caption, shown, x, ys = stage_values(key, runs)
    rng = stage_range(key, ys)
    extra_series, extra_data = off_scale_series(x, rng, ys)
    set_chart(plot, title, (caption + rng.note()).removeprefix("; "))
    plot.series = (up.Series(label="stage"), *(run_series(r) for r in shown), *extra_series)
    plot.data = (x, *(rng.drawn(y) for y in ys), *extra_data)
    # uPlot's auto-range breaks on NaN (stages without a value): give both ranges explicitly
    plot.scales = {
        "x": up.Scale(time=False, auto=False, range=(-0.5, float(x[-1]) + 0.5)),
        "y": up.Scale(auto=False, range=rng.range),
    }


# -- the strip chart of one rollout ---------------------------------------------------------------


def strip_plots(gui: viser.GuiApi, title: str = "distance and speeds") -> dict[str, viser.GuiUplotHandle]:
    """The three strip charts of *Explain*: the rollout's distance and speeds (``title``, e.g. the idle scene's
    :attr:`pemviz.scenarios.panel_data.LaneScene.strip_title`), p / q of detect, cumulative log-weight."""
    t = np.linspace(0, 5, 2)
    none = np.full(2, np.nan)
    x_scale = up.Scale(time=False, auto=False, range=(0.0, 5.0))
    probability = up.Scale(auto=False, range=(-0.1, 1.1))
    detect_caption = (
        "p(detect): the PEM's probability of detecting the object at each step; q(detect): the sampler's, which drew "
        "the rollout; dots: detected (top) and missed (bottom) steps"
    )
    charts = (  # key, series label, title, caption, y scale, unit, height
        ("gap", "gap (m)", f"{title} (choose a rollout)", "", None, "m, m/s", 185),
        ("detect", "p(detect)", "p(detect) and q(detect)", detect_caption, probability, "probability", 200),
        ("weight", "log w", "importance log-weight log w (nats)", LOG_W_CAPTION, None, "nats", 170),
    )
    return {
        key: add_chart(
            gui,
            data=(t, none),
            series=(up.Series(label="t (s)"), up.Series(label=label)),
            title=chart_title,
            caption=caption,
            scales={"x": x_scale} if y is None else {"x": x_scale, "y": y},
            axes=axes("time (s)", unit),
            legend=LEGEND,
            height=height,
        )
        for key, label, chart_title, caption, y, unit, height in charts
    }


def _points(colour: tuple[int, int, int], size: float = 6) -> up.Series_Points:
    return {"show": True, "size": size, "fill": css(colour), "stroke": css(colour)}


def _ring(colour: tuple[int, int, int], size: float = 11) -> up.Series_Points:
    """Hollow points: a value drawn at the edge of its chart (off scale) or a bin of too few states."""
    return {"show": True, "size": size, "fill": "transparent", "stroke": css(colour), "width": 1.5}


def _fill_detect_chart(
    plot: viser.GuiUplotHandle,
    ex: LaneExplanation,
    detected: np.ndarray,
    x_scale: up.Scale,
    marker: Callable[[np.ndarray], np.ndarray],
) -> None:
    """The p(detect) strip chart of :func:`fill_strip_plots`: the PEM's and the sampler's p(detect), the detections
    and misses, the decisive misses and the minimal miss set, and the ``marker`` of the scene's step."""
    t = ex.time_s
    no_line: up.Series = {"width": 0}
    # detections as a row of dots just above 1 and misses just below 0, clear of the probability curves
    det = np.where(detected, 1.05, np.nan)
    miss = np.where(detected, np.nan, -0.05)
    decisive = np.full(t.size, np.nan)
    decisive[ex.decisive] = -0.05
    minimal = np.full(t.size, np.nan)
    minimal[ex.counterfactual.minimal_set] = -0.05
    plot.series = (
        up.Series(label="t (s)"),
        up.Series(label="p(detect) PEM", stroke=hex_colour(C.BLACK), width=2),
        up.Series(label="q(detect) sampler", stroke=css(PROPOSAL), width=2),
        up.Series(label="detected", stroke=css(DETECTED), points=_points(DETECTED, 5), **no_line),
        up.Series(label="missed", stroke=css(MISSED), points=_points(MISSED, 5), **no_line),
        up.Series(label="decisive miss", stroke=css(CRASH), points=_points(CRASH, 10), **no_line),
        up.Series(
            label="minimal miss set",
            stroke=hex_colour(C.BLACK),
            points={"show": True, "size": 13, "fill": "transparent", "stroke": hex_colour(C.BLACK), "width": 1.5},
            **no_line,
        ),
        up.Series(label="now", stroke=hex_colour(C.BLACK), points=_points(C.BLACK, 9), **no_line),
    )
    plot.data = (t, ex.p_detect, ex.q_detect, det, miss, decisive, minimal, marker(ex.p_detect))
    plot.scales = {"x": x_scale, "y": up.Scale(auto=False, range=(-0.1, 1.1))}


def fill_strip_plots(
    plots: dict[str, viser.GuiUplotHandle],
    lines: tuple[Series, ...],
    detected: np.ndarray,
    ex: LaneExplanation,
    step: int,
    title: str,
    thresholds: Thresholds | None,
    what: str = "distance and speeds",
) -> None:
    """Draw a rollout with a marker at ``step`` in each strip chart, with the problem's failure threshold and sampler
    window (None: no such lines).

    Args:
        plots: the strip charts by name (:func:`strip_plots`).
        lines: the first chart's lines (:meth:`pemviz.app.drawing.LanePanel.strip_series`), the ``main`` one first;
            float64 [T] each.
        detected: bool [T] the detections taken.
        ex: the rollout explained (:meth:`pemviz.app.drawing.LanePanel.lane_explanation`).
        step: the step marked.
        title: the rollout's name.
        thresholds: the problem's failure threshold and sampler window, or None.
        what: the first chart's title."""
    t = ex.time_s
    now = np.full(t.size, np.nan)
    now_i = int(np.clip(step, 0, t.size - 1))
    no_line: up.Series = {"width": 0}

    def marker(values: np.ndarray) -> np.ndarray:
        m = now.copy()
        m[now_i] = values[now_i]
        return m

    t_max = float(t[-1])
    x_scale = up.Scale(time=False, auto=False, range=(0.0, t_max))
    values = [np.asarray(s.values, dtype=np.float64) for s in lines]
    main = values[0]
    gap_hi = float(np.nanmax(np.concatenate([*values, [12.0]])))
    set_chart(plots["gap"], what, title)
    plots["gap"].series = (
        up.Series(label="t (s)"),
        *(up.Series(label=s.label, **SERIES_STYLE[s.role]) for s in lines),
        *(
            up.Series(label=label, stroke=css(colour), width=1.5, dash=(6, 4))
            for label, colour in zip(thresholds.labels() if thresholds else (), (CRASH, BRAKE_ZONE), strict=False)
        ),
        up.Series(label="now", stroke=hex_colour(C.BLACK), points=_points(C.BLACK, 9), **no_line),
    )
    levels = (thresholds.failure, thresholds.window) if thresholds else ()
    plots["gap"].data = (t, *values, *(np.full(t.size, v) for v in levels), marker(main))
    gap_lo = min(0.0, float(np.min(main)))
    plots["gap"].scales = {"x": x_scale, "y": up.Scale(auto=False, range=(gap_lo, gap_hi * 1.05))}

    _fill_detect_chart(plots["detect"], ex, detected, x_scale, marker)

    lw = ex.cum_log_weight
    finite = lw[np.isfinite(lw)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    pad = max(0.5, 0.06 * (hi - lo))
    plots["weight"].series = (
        up.Series(label="t (s)"),
        up.Series(label="cumulative log p - log q (nats)", stroke=css(LOG_WEIGHT), width=2),
        up.Series(label="now", stroke=hex_colour(C.BLACK), points=_points(C.BLACK, 9), **no_line),
    )
    plots["weight"].data = (t, lw, marker(lw))
    plots["weight"].scales = {"x": x_scale, "y": up.Scale(auto=False, range=(lo - pad, hi + pad))}


def move_strip_marker(plots: dict[str, viser.GuiUplotHandle], step: int) -> None:
    """Move the ``now`` marker of each strip chart to ``step`` (the last series of each plot)."""
    for plot in plots.values():
        data = plot.data
        if len(data) < 3 or data[0].size < 2:
            continue
        i = int(np.clip(step, 0, data[0].size - 1))
        # the marker follows the first data series
        m = np.full(data[0].size, np.nan)
        m[i] = data[1][i]
        plot.data = (*data[:-1], m)


def finite_or_dash(x: float | None, spec: str) -> str:
    """``x`` formatted with ``spec`` (e.g. ``".1f"``), or ``-`` where it is None or not finite."""
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)
