"""The layout of a pemviz recording in rerun's viewer (the blueprint sent with it, :mod:`pemviz.sinks.recording`).

The recording opens on the ``step`` timeline and every tab has content there: **Stages** (what the sampler learned),
**Explain** (the most likely failure) and **Rollouts** (the kept rollouts and the scene's lanes). Logs nothing."""

from __future__ import annotations

from typing import Any

import rerun.blueprint as rrb

from pemviz.core.problem_view import ProblemView, SignalView
from pemviz.sinks import colours as C
from pemviz.sinks.rerun_features import FEATURE_FIG
from pemviz.sinks.rerun_stage_figures import figure, figure_titles
from pemviz.sinks.rerun_views import LANE_SPACING_M, PROPOSAL_FIG, SCENE_PATH, SCENE_X_RANGE_M

TABS = ("stages", "explain", "rollouts")
"""The blueprint's tabs, in order; :func:`default_blueprint` opens the one it is given (``stages`` by default)."""

TIMELINE = {"stages": "step", "explain": "step", "rollouts": "step"}
"""The timeline the viewer opens on with each tab: ``step`` for all three, so that every tab has content as opened;
rerun draws every view on one timeline (a view cannot choose its own: rerun-io/rerun#6828)."""

EXPLAIN_PATH = "explain"
"""Root of the most likely failure's entities (:mod:`pemviz.sinks.rerun_explain`)."""

_NO_LEGEND = rrb.PlotLegend(visible=False)

FEATURE_VIEW_NAME = "q(detect) vs PEM over the feature that moved q most (a state proposal's, per stage)"
"""The name of the Stages tab's feature view (:mod:`pemviz.sinks.rerun_features`; a run of ``method = "state"``)."""


def _signals(view: ProblemView | None) -> tuple[SignalView, ...]:
    """The signals the view draws (none without a view)."""
    return tuple(view.signals) if view is not None else ()


def _has_scene(view: ProblemView | None) -> bool:
    """Whether the problem's drawing object draws its rollouts as a scene seen from above, with a controller and
    contact (:attr:`pemviz.sinks.drawing.RecordingDrawing.draws_scene`)."""
    return view is not None and bool(getattr(view.drawing, "draws_scene", False))


def tab_name(tab: str) -> str:
    """The title of a tab, with its timeline: ``Stages (timeline: stage)``."""
    words = {
        "stages": "Stages (any timeline; on stage, scrub its bars)",
        "explain": "Explain: the most likely failure",
        "rollouts": "Rollouts",
    }[tab]
    return words if tab == "stages" else f"{words} (timeline: {TIMELINE[tab]})"


def _stages_tab(view: ProblemView | None, features: bool = False) -> rrb.Container:
    scene = _has_scene(view)
    several = view is not None and view.objects_xy is not None  # no gap bins: the reference-state curve alone
    series = [figure(key).view(title) for key, title in figure_titles(scene, window=not several)]
    reference = PROPOSAL_FIG.view("Reference-state curve q(detect | d) (other inputs fixed) vs PEM", legend_room=0.34)
    feature = FEATURE_FIG.view(FEATURE_VIEW_NAME, legend_room=0.34)
    proposal = (
        (rrb.Horizontal(feature, reference) if features else reference)
        if several
        else rrb.Horizontal(
            rrb.BarChartView(
                origin="/proposal_marginal/miss",
                plot_legend=_NO_LEGEND,
                name="q(miss) per gap bin over the visited states: mean, 10-90 % (light), PEM (grey)",
            ),
            rrb.Tabs(
                rrb.BarChartView(
                    origin="/proposal_marginal/log_odds",
                    plot_legend=_NO_LEGEND,
                    name="log-odds of a miss (nats) per gap bin: median, 10-90 % (light), PEM (grey)",
                ),
                *([feature] if features else []),
                reference,
            ),
        )
    )
    histograms = rrb.Horizontal(
        rrb.BarChartView(
            origin="/histograms/robustness",
            name="histogram: robustness of the stage's rollouts",
            plot_legend=_NO_LEGEND,
        ),
        rrb.BarChartView(
            origin="/histograms/log_weight", name="histogram: importance log-weight (nats)", plot_legend=_NO_LEGEND
        ),
    )
    return rrb.Vertical(
        proposal, rrb.Grid(*series, grid_columns=4), histograms, row_shares=[1.0, 1.15, 0.6], name=tab_name("stages")
    )


def _scene_view(origin: str, name: str, n_lanes: int) -> rrb.Spatial2DView:
    return rrb.Spatial2DView(
        origin=origin,
        name=name,
        background=C.FIGURE_BACKGROUND,
        visual_bounds=rrb.VisualBounds2D(
            x_range=list(SCENE_X_RANGE_M), y_range=[-0.6 * LANE_SPACING_M, (max(n_lanes, 1) - 0.4) * LANE_SPACING_M]
        ),
    )


def _explain_tab(view: ProblemView | None) -> rrb.Container:
    signals = _signals(view)
    scene = _has_scene(view)
    e = f"/{EXPLAIN_PATH}"
    several = view is not None and view.objects_xy is not None
    detect = (
        rrb.TimeSeriesView(
            origin=f"{e}/detect",
            name="p(detect) of the PEM (grey), q(detect) of the sampler (blue); misses below",
            plot_legend=rrb.PlotLegend(corner="LeftBottom"),
            axis_y=rrb.ScalarAxis(range=(-0.15, 1.08), zoom_lock=True),
        )
        if not several
        else rrb.TimeSeriesView(
            origin=f"{e}/detect",
            name="each object's events, a row per object (0 at the bottom): green detected, orange "
            "missed, grey unseen; above each row its q(detect) of the sampler (blue) and p(detect) of the PEM (grey), "
            "0 to 1",
            plot_legend=_NO_LEGEND,
        )
    )
    replays = ": red recorded; replays: green minimal set detected, violet last saving step"
    traces = [
        rrb.TimeSeriesView(
            origin=f"{e}/{first.column}",
            name=f"{first.name} ({first.unit}){replays if scene else ''}",
            plot_legend=_NO_LEGEND,
        )
        for first in signals[:1]
    ]
    top: list[rrb.View] = [rrb.TextDocumentView(origin=f"{e}/summary", name="What happened")]
    if scene:
        top.append(_scene_view(f"{e}/scene", "Scene of the most likely failure (play on step)", 1))
    elif view is not None and view.objects_xy is not None:
        top.append(
            rrb.Spatial2DView(
                origin=f"{e}/objects",
                name="Every object seen from the ego (ahead is up, metres; play on step): green "
                "detected, orange missed, grey unseen; blue where measured",
                background=C.FIGURE_BACKGROUND,
                visual_bounds=rrb.VisualBounds2D(x_range=[-16.0, 16.0], y_range=[-45.0, 5.0]),
            )
        )
    bottom: list = traces
    if scene:
        bottom.append(
            rrb.Tabs(
                rrb.TimeSeriesView(
                    origin=f"{e}/controller",
                    name="Controller: acceleration (m/s^2), brake commanded, brake applied",
                    plot_legend=rrb.PlotLegend(corner="LeftBottom"),
                ),
                rrb.TimeSeriesView(
                    origin=f"{e}/speed", name="Speeds (m/s)", plot_legend=rrb.PlotLegend(corner="RightTop")
                ),
            )
        )
    return rrb.Vertical(
        rrb.Horizontal(*top, column_shares=[1.3, 1.0][: len(top)]),
        detect,
        rrb.Horizontal(*bottom),
        row_shares=[0.9, 0.8, 1.1],
        name=tab_name("explain"),
    )


def _rollouts_tab(view: ProblemView | None, n_lanes: int) -> rrb.Container:
    signals = _signals(view)
    rest = signals[1:]
    colours = "kept rollouts: red failure, grey safe, yellow least robust, blue most likely, x miss"
    traces = (
        rrb.TimeSeriesView(
            name=f"{signals[0].name}: {signals[0].column} ({signals[0].unit}), {colours}",
            plot_legend=_NO_LEGEND,
            contents=[f"+ /rollouts/{signals[0].column}/**", "+ /rollouts/detected/**", "+ /rollouts/missed/**"],
        )
        if signals
        else rrb.TimeSeriesView(name=colours.capitalize(), contents=["+ /rollouts/**"], plot_legend=_NO_LEGEND)
    )
    others = [
        rrb.TimeSeriesView(
            name=f"{s.name}: {s.column} ({s.unit})", origin=f"/rollouts/{s.column}", plot_legend=_NO_LEGEND
        )
        for s in rest
    ]
    right: list = []
    if others:
        right.append(rrb.Tabs(*others) if len(others) > 1 else others[0])
    if _has_scene(view):
        right.append(_scene_view(f"/{SCENE_PATH}", "Scene: each stage's least robust rollout (play on step)", n_lanes))
    if not right:
        return rrb.Vertical(traces, name=tab_name("rollouts"))
    return rrb.Horizontal(traces, rrb.Vertical(*right), column_shares=[1.4, 1.0], name=tab_name("rollouts"))


def _odd_views(view: ProblemView | None) -> list[Any]:
    """Over an operating design domain: the map's table (``/odd/map``) and, per drawn parameter, log10 p(failure |
    bin) with its 95 % interval's ends over the ``odd_bin`` timeline (``/odd/<name>``); none without an ODD."""
    names = view.odd_names if view is not None else ()
    if not names:
        return []
    plots: list[Any] = [
        rrb.TimeSeriesView(origin=f"/odd/{name}", name=f"log10 p(failure | {name} bin)", plot_legend=_NO_LEGEND)
        for name in names
    ]
    if len(names) > 1:  # the heat map of the first two
        plots.append(rrb.TensorView(origin="/odd/pair", name=f"log10 p(failure | {names[0]}, {names[1]} cell)"))
    return [rrb.Vertical(rrb.TextDocumentView(origin="/odd/map", name="ODD map"), *plots, name="ODD map")]


def default_blueprint(
    n_lanes: int = 12,
    view: ProblemView | None = None,
    tab: str = "stages",
    paused: bool = False,
    features: bool = False,
) -> rrb.Blueprint:
    """The recording's layout: the tabs *Stages*, *Explain* and *Rollouts* with the estimate, the run and the
    failures beside them.

    Args:
        n_lanes: lanes of the rollouts' scene (one per stage); sizes its view.
        view: the problem's view (its signals, thresholds and drawing); None: no signal and no scene are known.
        tab: the tab open at start, one of :data:`TABS`; the time panel shows its timeline (:data:`TIMELINE`).
        paused: start with the time cursor paused (at the timeline's start); else the viewer plays the timeline
            once on opening and stops at its end (the last stage).
        features: the Stages tab shows the feature view of a state-dependent proposal
            (:mod:`pemviz.sinks.rerun_features`), beside or before the reference-state curve.
    Raises:
        ValueError: ``tab`` not one of :data:`TABS`."""
    if tab not in TABS:
        raise ValueError(f"default_blueprint: tab must be one of {TABS}, got {tab!r}")
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Tabs(
                _stages_tab(view, features),
                _explain_tab(view),
                _rollouts_tab(view, n_lanes),
                active_tab=TABS.index(tab),
            ),
            rrb.Vertical(
                rrb.TextDocumentView(origin="/estimate", name="Estimate"),
                rrb.Tabs(
                    rrb.TextDocumentView(origin="/description", name="Run"),
                    rrb.TextDocumentView(origin="/failures", name="Failures by share of p, in groups"),
                    *_odd_views(view),
                    *(
                        [
                            rrb.BarChartView(
                                origin="/final/severity_of_failures",
                                plot_legend=_NO_LEGEND,
                                name="p(severity | failure): share of p per impact speed, no contact first",
                            )
                        ]
                        if _has_scene(view) or view is not None and view.objects_xy is not None
                        else []
                    ),
                ),
                row_shares=[1.0, 1.8],
            ),
            column_shares=[3.6, 1.0],
        ),
        rrb.TimePanel(timeline=TIMELINE[tab], state="collapsed", play_state="paused" if paused else None),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        collapse_panels=True,
    )
