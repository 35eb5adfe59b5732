"""uPlot figures of the panel (viser's ``add_uplot``): proposal curves, per-stage values, the strip chart.

Every figure names its axes, keeps its legend to the series' names (no live values, so no ``--``
placeholders), leaves room for long tick labels (``-14.75``) and sets its ranges from the data that
exists, never from what a run planned. Colours come from :mod:`pemviz.sinks.colours`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
import viser
import viser.uplot as up

from pemviz.app.explain import Explanation
from pemviz.app.runs import PanelRun, Trajectory
from pemviz.sinks import colours as C
from pemviz.sinks.colours import (
    BRAKE_ZONE,
    CRASH,
    DETECTED,
    EGO_SPEED,
    LEAD_SPEED,
    LOG_WEIGHT,
    MISSED,
    PROPOSAL,
    css,
    hex_colour,
    stage_rgb,
)

if TYPE_CHECKING:
    from pemviz.core.problems import Thresholds

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


def run_colour(run_id: int) -> str:
    return RUN_COLOURS[(run_id - 1) % len(RUN_COLOURS)]


def axes(x_label: str, y_label: str) -> tuple[up.Axis, up.Axis]:
    """An x and a y axis with titles; the y axis wide enough for ``-14.75``."""
    return (up.Axis(label=x_label, size=36), up.Axis(label=y_label, size=62, gap=4))


def y_range(key: str, series: list[np.ndarray]) -> tuple[float, float]:
    """A padded y range covering the finite values of ``series`` ((0, 1) for rates or without values)."""
    if key == "failure_rate":
        return (-0.05, 1.05)
    values = np.concatenate([np.asarray(s, dtype=np.float64).ravel() for s in series]) if series else np.zeros(0)
    values = values[np.isfinite(values)]
    if values.size == 0:
        return (-0.05, 1.05)
    lo, hi = float(values.min()), float(values.max())
    pad = 0.08 * (hi - lo) if hi > lo else max(0.5, 0.1 * abs(lo))
    return (lo - pad, hi + pad)


def curve_plot(gui: viser.GuiApi, title: str, height: int = 230) -> viser.GuiUplotHandle:
    """An empty q(detect | gap) plot: gap 0..13 m, probability 0..1 (the top tick 1 included)."""
    return gui.add_uplot(
        data=(np.linspace(0, 13, 2), np.full(2, np.nan)),
        series=(up.Series(label="gap (m)"), up.Series(label="PEM", stroke=hex_colour(C.BLACK))),
        title=title,
        scales={"x": up.Scale(time=False, auto=False, range=(0.0, 13.0)), "y": up.Scale(auto=False, range=(0.0, 1.04))},
        axes=axes("gap d (m)", "p(detect | d)"),
        legend=LEGEND,
        height=height,
    )


def fill_curve_plot(plot: viser.GuiUplotHandle, record: PanelRun, title: str) -> None:
    """The PEM and the proposal after each stage (blue early, orange late) of ``record``."""
    with record.lock:
        grid, pem = record.curve_grid_m, record.pem_curve
        stages = [s for s in record.stages if not np.all(np.isnan(s.proposal_curve)) and s.kind != "final"]
    if grid.size == 0:
        return
    n_colour = max(1, record.plan.n_ce if record.plan is not None else 1)  # blue (stage 0) to orange (stage K)
    series = [up.Series(label="gap (m)"), up.Series(label="PEM", stroke=hex_colour(C.BLACK), width=2)]
    data = [grid, pem]
    for s in stages:  # the final batch samples from the last stage's proposal: the same curve
        name = "pretraining" if s.kind == "pretrain" else f"stage {s.stage}"  # short: uPlot's legend is narrow
        series.append(up.Series(label=name, stroke=css(stage_rgb(s.stage, n_colour)), width=1.5))
        data.append(np.asarray(s.proposal_curve, dtype=np.float64))
    plot.title = title
    plot.series = tuple(series)
    plot.data = tuple(data)


def stage_plot(gui: viser.GuiApi, title: str, y_label: str) -> viser.GuiUplotHandle:
    return gui.add_uplot(
        data=(np.arange(2, dtype=np.float64), np.full(2, np.nan)),
        series=(up.Series(label="stage"), up.Series(label="no run yet", stroke=hex_colour(C.GREY))),
        title=title,
        scales={"x": up.Scale(time=False, auto=False, range=(-0.5, 1.5)), "y": up.Scale(auto=False, range=(-0.05, 1.05))},
        axes=axes("stage (0 pretraining, K+1 final batch)", y_label),
        legend=LEGEND,
        height=150,
    )


def fill_stage_plot(plot: viser.GuiUplotHandle, key: str, runs: list[PanelRun]) -> None:
    """One series per run over the stages finished so far (x from 0 to the last finished stage).

    ``gamma`` has a unit that depends on the metric (metres for classic, none for AGM): only runs with the
    newest run's metric are drawn, and the title says the unit and how many runs are left out.
    """
    if not runs:
        return
    title = dict((k, t) for k, t, _ in STAGE_PLOTS)[key]
    shown = runs
    if key == "gamma":
        metric = runs[-1].config.metric
        shown = [r for r in runs if r.config.metric == metric]
        left_out = len(runs) - len(shown)
        title = f"gamma per stage, {metric} ({GAMMA_UNITS.get(metric, 'unitless')})" + (
            f"; {left_out} run{'s' * (left_out != 1)} of another metric not shown" if left_out else ""
        )
    values = [r.stage_series(key) for r in shown]
    last = max([max(v) for v in values if v] + [1])
    x = np.arange(last + 1, dtype=np.float64)
    series: list[Any] = [up.Series(label="stage")]
    data = [x]
    for r, v in zip(shown, values):
        y = np.full(x.size, np.nan)
        for stage, value in v.items():
            y[stage] = value
        colour = run_colour(r.run_id)
        series.append(
            up.Series(label=r.short_label, stroke=colour, width=2, points={"show": True, "size": 5, "fill": colour})
        )
        data.append(y)
    plot.title = title
    plot.series = tuple(series)
    plot.data = tuple(data)
    # uPlot's auto-range breaks on NaN (stages without a value): give both ranges explicitly
    plot.scales = {
        "x": up.Scale(time=False, auto=False, range=(-0.5, last + 0.5)),
        "y": up.Scale(auto=False, range=y_range(key, data[1:])),
    }


# -- the strip chart of one rollout ---------------------------------------------------------------


def strip_plots(gui: viser.GuiApi) -> dict[str, viser.GuiUplotHandle]:
    """The three strip charts of *Explain*: gap and speeds, p / q of detect, cumulative log-weight."""
    t = np.linspace(0, 5, 2)
    none = np.full(2, np.nan)
    x_scale = up.Scale(time=False, auto=False, range=(0.0, 5.0))
    return {
        "gap": gui.add_uplot(
            data=(t, none), series=(up.Series(label="t (s)"), up.Series(label="gap (m)")),
            title="gap and speeds (choose a rollout)", scales={"x": x_scale}, axes=axes("time (s)", "m, m/s"),
            legend=LEGEND, height=185,
        ),
        "detect": gui.add_uplot(
            data=(t, none), series=(up.Series(label="t (s)"), up.Series(label="p(detect)")),
            title="p(detect) under the PEM and q(detect) of the sampler",
            scales={"x": x_scale, "y": up.Scale(auto=False, range=(-0.1, 1.1))},
            axes=axes("time (s)", "probability"), legend=LEGEND, height=200,
        ),
        "weight": gui.add_uplot(
            data=(t, none), series=(up.Series(label="t (s)"), up.Series(label="log w")),
            title="cumulative importance log-weight", scales={"x": x_scale}, axes=axes("time (s)", "nats"),
            legend=LEGEND, height=170,
        ),
    }  # fmt: skip


def _points(colour: tuple[int, int, int], size: float = 6) -> dict[str, Any]:
    return {"show": True, "size": size, "fill": css(colour), "stroke": css(colour)}


def fill_strip_plots(
    plots: dict[str, viser.GuiUplotHandle], traj: Trajectory, ex: Explanation, step: int, title: str,
    thresholds: Thresholds | None,
) -> None:  # fmt: skip
    """Draw ``traj`` with a marker at ``step`` (the 3D scene's step) in each strip chart, with the problem's failure
    threshold and sampler window (:attr:`pemviz.core.problems.ProblemView.thresholds`; None: no such lines)."""
    t = ex.time_s
    now = np.full(t.size, np.nan)
    now_i = int(np.clip(step, 0, t.size - 1))
    no_line = {"width": 0}

    def marker(values: np.ndarray) -> np.ndarray:
        m = now.copy()
        m[now_i] = values[now_i]
        return m

    # detections as a row of dots just above 1 and misses just below 0, clear of the probability curves
    det = np.where(traj.detected, 1.05, np.nan)
    miss = np.where(traj.detected, np.nan, -0.05)
    decisive = np.full(t.size, np.nan)
    decisive[ex.decisive] = -0.05
    minimal = np.full(t.size, np.nan)
    minimal[ex.counterfactual.minimal_set] = -0.05
    t_max = float(t[-1])
    x_scale = up.Scale(time=False, auto=False, range=(0.0, t_max))
    gap_hi = float(np.nanmax(np.concatenate([traj.gap_m, traj.ego_speed_mps, traj.lead_speed_mps, [12.0]])))
    plots["gap"].title = f"{title}: gap and speeds"
    plots["gap"].series = (
        up.Series(label="t (s)"),
        up.Series(label="gap (m)", stroke=hex_colour(C.BLACK), width=2),
        up.Series(label="ego speed (m/s)", stroke=css(EGO_SPEED), width=1.5),
        up.Series(label="lead speed (m/s)", stroke=css(LEAD_SPEED), width=1.5),
        *(up.Series(label=label, stroke=css(colour), width=1.5, dash=[6, 4])
          for label, colour in zip(thresholds.labels() if thresholds else (), (CRASH, BRAKE_ZONE))),
        up.Series(label="now", stroke=hex_colour(C.BLACK), points=_points(C.BLACK, 9), **no_line),
    )
    levels = (thresholds.failure, thresholds.window) if thresholds else ()
    plots["gap"].data = (
        t, traj.gap_m, traj.ego_speed_mps, traj.lead_speed_mps, *(np.full(t.size, v) for v in levels),
        marker(traj.gap_m),
    )  # fmt: skip
    plots["gap"].scales = {"x": x_scale, "y": up.Scale(auto=False, range=(min(0.0, float(np.min(traj.gap_m))), gap_hi * 1.05))}

    plots["detect"].series = (
        up.Series(label="t (s)"),
        up.Series(label="p(detect) PEM", stroke=hex_colour(C.BLACK), width=2),
        up.Series(label="q(detect) sampler", stroke=css(PROPOSAL), width=2),
        up.Series(label="detected", stroke=css(DETECTED), points=_points(DETECTED, 5), **no_line),
        up.Series(label="missed", stroke=css(MISSED), points=_points(MISSED, 5), **no_line),
        up.Series(label="decisive miss", stroke=css(CRASH), points=_points(CRASH, 10), **no_line),
        up.Series(label="minimal miss set", stroke=hex_colour(C.BLACK),
                  points={"show": True, "size": 13, "fill": "transparent", "stroke": hex_colour(C.BLACK), "width": 1.5},
                  **no_line),
        up.Series(label="now", stroke=hex_colour(C.BLACK), points=_points(C.BLACK, 9), **no_line),
    )
    plots["detect"].data = (t, ex.p_detect, ex.q_detect, det, miss, decisive, minimal, marker(ex.p_detect))
    plots["detect"].scales = {"x": x_scale, "y": up.Scale(auto=False, range=(-0.1, 1.1))}

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
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)
