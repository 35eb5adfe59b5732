"""uPlot figures of what the sampler really did and of a rollout's controller (viser's ``add_uplot``).

*Live*: q(detect) of each stage's sampler over the states its rollouts visited, per gap bin, beside the PEM's
(:mod:`pemviz.core.proposal_view`), on a probability and on a log-odds scale, and the 95 % interval and the exact answer
on the log10 mu_hat chart. *Explain*: the controller's brake command, applied brake and acceleration along a
rollout. Colours from :mod:`pemviz.sinks.colours`; every range set from the data that exists, by
:func:`pemviz.app.plots.robust_range`: values far from the rest are drawn at the edge, ringed, and counted in the title.
A gap bin with fewer than :data:`MIN_BIN_STATES` visited states is not joined into its stage's line.
"""

from __future__ import annotations

import html
import math
from typing import Any

import numpy as np
import viser
import viser.uplot as up

from pemviz.app.drawing import LaneExplanation
from pemviz.app.html import GREY as GREY_BOX
from pemviz.app.html import box
from pemviz.methods import plain_method
from pemviz.app.plots import (
    LEGEND,
    _points,
    _ring,
    axes,
    off_scale_series,
    robust_range,
    run_colour,
    run_series,
    stage_values,
)
from pemviz.app.runs import PanelRun
from pemviz.core.proposal_view import ProposalView
from pemviz.engine.events import RolloutsSampled
from pemviz.sinks.colours import (
    BLACK,
    BLUE,
    BRAKE_ZONE,
    CRASH,
    EGO_SPEED,
    GREY,
    MISSED,
    VIOLET,
    css,
    hex_colour,
    stage_rgb,
    stage_span,
)

PROB, LOG_ODDS = "prob", "log_odds"
LOG_ODDS_SPAN = 12.0
"""The log-odds chart shows at most -12..12 nats (odds of 1:160,000); medians beyond are drawn at the edge."""
MIN_BIN_STATES = 20
"""A gap bin with fewer visited states than this is not joined into its stage's line: the standard error of a mean of
values in [0, 1] can reach 0.5 / sqrt(n), over 0.1 below 20 states. The newest stage's such bins are drawn as
hollow rings at their value and counted in the title."""
CROWDED_BIN = 3.0
"""A gap bin holding more than this many times the median bin's states (of the bins with at least
:data:`MIN_BIN_STATES`), most of them standing (:func:`standing_bins`), is ringed in the q(detect) chart and named in
its title with its count."""
CONTROLLER_RULE: dict[str, Any] = {"min_gap": 10.0, "min_pad": 1.0, "at_least": (-4.0, 4.0)}
""":func:`pemviz.app.plots.robust_range` settings of the controller chart (m/s^2): an acceleration more than 10 m/s^2
(and twice the others' spread) from the others is off scale; at least 1 m/s^2 of room each side, -4..4 always shown."""
MU_HAT_RULE: dict[str, Any] = {"min_gap": 3.0, "min_pad": 0.05}
""":func:`pemviz.app.plots.robust_range` settings of the log10 mu_hat chart (log10 probability), as
:data:`pemviz.app.plots.STAGE_RULES`."""


def marginal_plots(gui: viser.GuiApi) -> dict[str, viser.GuiUplotHandle]:
    """The two empty charts of the sampler's q(detect) over visited states: probability and log-odds of a miss, hidden
    until a run has a view to draw (:func:`fill_marginal_plots`)."""
    x = np.linspace(0.0, 13.0, 2)
    none = np.full(2, np.nan)
    x_scale = up.Scale(time=False, auto=False, range=(0.0, 13.0))
    return {
        PROB: gui.add_uplot(
            data=(x, none), series=(up.Series(label="gap (m)"), up.Series(label="PEM", stroke=hex_colour(BLACK))),
            title="q(detect) over the visited states per stage vs the PEM",
            scales={"x": x_scale, "y": up.Scale(auto=False, range=(0.0, 1.04))},
            axes=axes("gap d (m), 0.5 m bins", "mean q(detect)"), legend=LEGEND, height=230, visible=False,
        ),
        LOG_ODDS: gui.add_uplot(
            data=(x, none), series=(up.Series(label="gap (m)"), up.Series(label="PEM", stroke=hex_colour(BLACK))),
            title="log q(miss) / q(detect) over the visited states",
            scales={"x": x_scale, "y": up.Scale(auto=False, range=(-6.0, 2.0))},
            axes=axes("gap d (m), 0.5 m bins", "log-odds (nats)"), legend=LEGEND, height=210, visible=False,
        ),
    }  # fmt: skip


def unchanged_share(values: np.ndarray, edges_m: np.ndarray) -> np.ndarray:
    """Per bin (``edges_m``, metres, as :func:`pemviz.core.proposal_view.proposal_view` bins), the share of the
    visited states ``values`` [N, T] (metres, e.g. the gap) whose value equals the same rollout's one step before:
    both cars at rest (or moving together), one state counted again each step. float64 [B]; nan for an empty bin; a
    first step counts as changed."""
    gap = np.asarray(values, dtype=np.float64)
    edges = np.asarray(edges_m, dtype=np.float64)
    same = np.zeros(gap.shape, bool)
    same[:, 1:] = gap[:, 1:] == gap[:, :-1]
    n_bins = edges.size - 1
    b = np.searchsorted(edges, gap.ravel(), side="right") - 1
    inside = (b >= 0) & (b < n_bins)
    n = np.bincount(b[inside], minlength=n_bins).astype(np.float64)
    k = np.bincount(b[inside], weights=same.ravel()[inside].astype(np.float64), minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, k / n, np.nan)


def standing_bins(n_states: np.ndarray, unchanged_share: np.ndarray) -> np.ndarray:
    """Indices of the bins crowded with standing states: more than :data:`CROWDED_BIN` times the median count of the
    bins with at least :data:`MIN_BIN_STATES` states, more than half of them with the gap unchanged since the step
    before (``unchanged_share``, :func:`unchanged_share`). int, ascending; none without full bins."""
    n = np.asarray(n_states)
    share = np.asarray(unchanged_share, dtype=np.float64)
    full = n[n >= MIN_BIN_STATES]
    if full.size == 0:
        return np.zeros(0, dtype=int)
    return np.flatnonzero((n > CROWDED_BIN * float(np.median(full))) & (np.nan_to_num(share) > 0.5))


def _stage_batch(record: PanelRun, stage: int) -> Any:
    """The rollouts of ``stage`` (the newest :class:`RolloutsSampled` of it that ``record`` kept), None without."""
    with record.lock:
        events = list(record.events)
    return next((e.batch for e in reversed(events) if isinstance(e, RolloutsSampled) and e.stage == stage), None)


def _view_stages(record: PanelRun) -> list[tuple[int, str, ProposalView]]:
    """(stage, name, view) of the stages drawn by a sampler other than the PEM's pretraining, in order."""
    with record.lock:
        views = dict(record.proposal_views)
    out = []
    for stage in sorted(views):
        kind, view = views[stage]
        if kind == "pretrain":
            continue  # pretraining rollouts are the PEM's own: q = p
        out.append((stage, "final batch" if kind == "final" else f"stage {stage}", view))
    return out


def marginal_note(record: PanelRun | None) -> str:
    """Why the q(detect) charts of *Live* are hidden (HTML; empty when ``record`` has a view to draw)."""
    if record is None:
        why = "no run yet"
    elif _view_stages(record):
        return ""
    elif record.view is not None and record.view.thresholds is None and record.view.objects_xy is None:
        why = (f"{html.escape(record.short_label)}: its problem reports neither a gap nor the rows of several objects, "
               "so no detection probability can be binned")  # fmt: skip
    else:
        why = (f"{html.escape(record.short_label)}: no stage drawn by a proposal yet (pretraining draws from the PEM "
               "itself, q = p)")  # fmt: skip
    return box(f"q(detect) over the visited states: {why}.", GREY_BOX)


def fill_marginal_plots(plots: dict[str, viser.GuiUplotHandle], record: PanelRun,
                        note: viser.GuiHtmlHandle | None = None) -> None:  # fmt: skip
    """Each stage's mean q(detect) and median log-odds of a miss (nats) over its visited states, per bin of the view's
    axis (:attr:`pemviz.app.runs.PanelRun.proposal_axis`: e.g. the gap in 0.5 m bins of a scene of one object a
    step, or one car's gap ahead among several in 1 m bins over the states where the camera sees it,
    :func:`pemviz.app.runs.object_proposal_view`),
    the PEM's at the newest stage's states, and the newest stage's 10-90 % spread as a band. Without a view to draw
    both charts are hidden and ``note`` says why (:func:`marginal_note`).

    A bin with fewer than :data:`MIN_BIN_STATES` states is left out of every line (its mean is mostly noise); the
    newest stage's such bins are drawn as hollow rings at their value and the title counts them. The newest stage's
    bins crowded with standing states (:func:`standing_bins`) are ringed in grey on the probability chart and its
    title gives each one's count and share of standing states: their value is real, not noise. For example, the
    6.0-6.5 m bin of the default run's final batch (for example, of the braking scenario) holds 6,048 states, 3.4x its
    neighbours, 77 % of them a car that stopped in time standing behind the stopped object ahead for the rest of the
    episode, where the sampler does not steer and its q(detect) is the PEM's 0.993: the bin's mean q is 0.90 against
    0.47-0.51 beside it (0.56 over its moving states). The log-odds chart's range is
    :func:`pemviz.app.plots.robust_range` of the medians of the bins with enough states, at most -12..12 nats; a
    median beyond is drawn at the edge.
    """
    stages = _view_stages(record)
    if note is not None:
        note.content = marginal_note(record)
    for plot in plots.values():
        plot.visible = bool(stages)
    if not stages:
        return
    cfg = record.config
    axis = record.proposal_axis
    last_stage, last_name, last = stages[-1]
    n_colour = stage_span(record.plan)
    x = last.centres_m
    x_range = (float(last.edges_m[0]), float(last.edges_m[-1]))
    plain_mc = plain_method(cfg.method)
    standing_signal = axis.standing_signal
    whose = "" if standing_signal is not None else f" of {axis.subject}"
    who = "plain Monte Carlo: the rollouts are the PEM's own (q = p)" if plain_mc else (
        f"mean q(miss) {axis.window_name} {last.window_m:g} m {last.q_miss_window:.3g} vs the PEM's "
        f"{last.p_miss_window:.3g} ({last_name})"
    )
    sparse = (last.n_states > 0) & (last.n_states < MIN_BIN_STATES)
    n_sparse = int(sparse.sum())
    few = f"; {n_sparse} bin{'s' * (n_sparse != 1)} of under {MIN_BIN_STATES} states hollow" if n_sparse else ""
    standing = np.zeros(0, dtype=int)
    if standing_signal is not None and np.any(last.n_states > CROWDED_BIN * MIN_BIN_STATES):  # else none is crowded
        batch = _stage_batch(record, last_stage)
        if batch is not None and standing_signal in batch.observation_names:
            share = unchanged_share(batch.signal(standing_signal), last.edges_m)
            standing = standing_bins(last.n_states, share)
    crowd = "" if standing.size == 0 else "; ringed: mostly standing states (the gap unchanged since the step " \
        "before, one state counted each step) " + ", ".join(
            f"{last.edges_m[b]:g}-{last.edges_m[b + 1]:g} m {share[b]:.0%} of {int(last.n_states[b]):,}"
            for b in standing)  # fmt: skip

    def enough(view: ProposalView, values: np.ndarray) -> np.ndarray:
        return np.where(view.n_states >= MIN_BIN_STATES, np.asarray(values, dtype=np.float64), np.nan)

    for key, (mid, lo, hi, p_mid) in {
        PROB: ("q_mean", "q_lo", "q_hi", "p_mean"),
        LOG_ODDS: ("q_log_odds", "q_log_odds_lo", "q_log_odds_hi", "p_log_odds"),
    }.items():
        colour = css(stage_rgb(last_stage, n_colour))
        lines = [enough(last, getattr(last, p_mid))] + [enough(view, getattr(view, mid)) for _, _, view in stages]
        if key == PROB:
            title = f"{record.short_label}: mean q(detect){whose} over the visited states · {who}{few}{crowd}"
            rng = robust_range(np.zeros(0), at_least=(0.0, 1.04))  # probabilities: always 0..1 (tick 1 inside)
        else:
            title = (f"{record.short_label}: median log q(miss)/q(detect){whose} over the visited states "
                     f"(nats){few}")  # fmt: skip
            # the medians of the bins with enough states decide the range (ticks -6 and 2 inside it); a band may
            # leave it, a median beyond is drawn at the edge
            rng = robust_range(np.concatenate(lines), min_pad=0.3, pad_frac=0.06, at_least=(-6.4, 2.4),
                               limits=(-LOG_ODDS_SPAN, LOG_ODDS_SPAN))  # fmt: skip
            title += rng.note("median", ".1f", " nats")
        series: list[Any] = [
            up.Series(label=axis.series_label),
            up.Series(label=f"{last_name} 10 %", stroke=colour, width=1, dash=[3, 3]),
            up.Series(label=f"{last_name} 90 %", stroke=colour, width=1, dash=[3, 3]),
            up.Series(label="PEM", stroke=hex_colour(BLACK), width=2.5),
        ]
        data = [x, enough(last, getattr(last, lo)), enough(last, getattr(last, hi)), rng.drawn(lines[0])]
        for (stage, name, view), line in zip(stages, lines[1:], strict=False):
            width = 2 if view is last else 1.5
            series.append(up.Series(label=name, stroke=css(stage_rgb(stage, n_colour)), width=width))
            data.append(rng.drawn(line))
        if sparse.any():
            series.append(up.Series(label=f"{last_name}, bins under {MIN_BIN_STATES} states", stroke=colour,
                                    points=_ring(stage_rgb(last_stage, n_colour), 8), width=0))  # fmt: skip
            data.append(rng.drawn(np.where(sparse, getattr(last, mid), np.nan)))
        if key == PROB and standing.size:
            mark = np.full(x.size, np.nan)
            mark[standing] = getattr(last, mid)[standing]
            series.append(up.Series(label=f"{last_name}, mostly standing states", stroke=hex_colour(GREY),
                                    points=_ring(GREY, 14), width=0))  # fmt: skip
            data.append(mark)
        extra_series, extra_data = off_scale_series(x, rng, lines)
        plot = plots[key]
        plot.title = title
        plot.series = tuple(series + extra_series)
        plot.data = tuple(np.asarray(d, dtype=np.float64) for d in data + extra_data)
        plot.bands = (up.Band(series=(2, 1), fill=css(stage_rgb(last_stage, n_colour), 0.15)),)
        plot.scales = {"x": up.Scale(time=False, auto=False, range=x_range), "y": up.Scale(auto=False,
                                                                                         range=rng.range)}
        plot.axes = axes(axis.label, "mean q(detect)" if key == PROB else "log-odds (nats)")


def fill_mu_hat_plot(plot: viser.GuiUplotHandle, runs: list[PanelRun]) -> None:
    """The log10 mu_hat chart (log10 probability) with each run's 95 % interval per stage as a band between dashed
    lines and the exact answer as a black line where the run knows it. Drawn after (and over)
    :func:`pemviz.app.plots.fill_stage_plot`'s chart, whose runs and stages it keeps.

    The y range is :func:`pemviz.app.plots.robust_range` (:data:`MU_HAT_RULE`) of the estimates and the interval
    bounds of the stages with at least one failure, widened to the exact answer: a stage without failures has the
    upper bound log10 1 = 0 (the interval says nothing), drawn at the top edge, ringed, and counted in the title.
    """
    if not runs:
        return
    _, shown, x, ys = stage_values("log10_mu_hat", runs)
    n = x.size
    series: list[Any] = [up.Series(label="stage"), *(run_series(r) for r in shown)]
    lines = list(ys)
    matters = [np.isfinite(y) for y in ys]
    bands = []
    ln10 = math.log(10.0)
    for r in runs:
        lo, hi = np.full(n, np.nan), np.full(n, np.nan)
        failed = np.zeros(n, bool)
        with r.lock:
            stages = list(r.stages)
        for s in stages:
            if 0 <= s.stage < n:
                a, b = s.estimate.shown_log_ci  # a bound alone (b = inf: no upper) where no interval is backed
                lo[s.stage], hi[s.stage] = a / ln10, b / ln10
                failed[s.stage] = s.estimate.n_failures > 0
        lo[~np.isfinite(lo)] = np.nan
        hi[~np.isfinite(hi)] = np.nan
        if np.all(np.isnan(hi)):
            continue
        colour = run_colour(r.run_id)
        series += [up.Series(label=f"{r.short_label} 95 % low", stroke=colour, width=1, dash=[4, 3]),
                   up.Series(label=f"{r.short_label} 95 % high", stroke=colour, width=1, dash=[4, 3])]  # fmt: skip
        lines += [lo, hi]
        matters += [failed, failed]
        bands.append(up.Band(series=(len(series) - 1, len(series) - 2), fill=f"{colour}26"))
    exact = runs[-1].exact_log_p
    known = exact is not None and math.isfinite(exact)
    rng = robust_range(np.concatenate(lines), np.concatenate(matters), **MU_HAT_RULE,
                       at_least=(exact / ln10, exact / ln10) if known else None)  # fmt: skip
    data = [x, *(rng.drawn(y) for y in lines)]
    if known:
        series.append(up.Series(label=f"exact answer {exact / ln10:.3f}", stroke=hex_colour(BLACK), width=1.5,
                                dash=[8, 4]))  # fmt: skip
        data.append(np.full(n, exact / ln10))
    extra_series, extra_data = off_scale_series(x, rng, lines)
    plot.title = ("log10 mu_hat per stage, 95 % interval (band)" + (", exact answer (black)" * known)
                  + rng.note("point", ".1f"))  # fmt: skip
    plot.series = tuple(series + extra_series)
    plot.data = tuple(data + extra_data)
    plot.bands = tuple(bands)
    plot.scales = {
        "x": up.Scale(time=False, auto=False, range=(-0.5, float(x[-1]) + 0.5)),
        "y": up.Scale(auto=False, range=rng.range),
    }


def controller_plot(gui: viser.GuiApi, order: float | None = None) -> viser.GuiUplotHandle:
    """The empty controller chart of *Explain*."""
    t = np.linspace(0, 5, 2)
    return gui.add_uplot(
        data=(t, np.full(2, np.nan)), series=(up.Series(label="t (s)"), up.Series(label="acceleration (m/s^2)")),
        title="controller: brake command, brake applied, acceleration (choose a rollout)",
        scales={"x": up.Scale(time=False, auto=False, range=(0.0, 5.0))}, axes=axes("time (s)", "m/s^2"),
        legend=LEGEND, height=170, order=order,
    )  # fmt: skip


def fill_controller_plot(plot: viser.GuiUplotHandle, ex: LaneExplanation, step: int, title: str) -> None:
    """The ego's acceleration (m/s^2), and as rows of dots above it the steps at which the emergency brake was
    commanded (the object detected within the window) and applied (one step later); a marker at ``step``.

    The y range is :func:`pemviz.app.plots.robust_range` of the acceleration (:data:`CONTROLLER_RULE`) over the steps
    before contact (``ex.contact``): a step off it is drawn at the edge, ringed, and the title gives its value and
    time. The one that flattened the chart is the contact step, where the simulator stops the ego within one step
    (for example a = -v / dt = -5.76 m/s / 0.05 s = -115 m/s^2 at 3.10 s in the braking scenario's default crash), a
    collision rather than the controller's doing (at most 27.5 m/s^2 there, drawn at its place).
    """
    c = ex.controller
    t = c.time_s
    a = np.asarray(c.accel_mps2, dtype=np.float64)
    # in contact the simulator stops the ego within one step (a = -v / dt): a collision, not the controller's doing;
    # those steps do not set the range
    contact = np.asarray(ex.contact, bool)
    rng = robust_range(a, ~contact, **CONTROLLER_RULE)
    top, bottom = rng.hi, rng.lo
    row = 0.07 * (top - bottom)  # two rows of dots above the curve, apart at any scale
    command = np.where(c.brake_command, top + 2 * row, np.nan)
    applied = np.where(c.brake_applied, top + row, np.nan)
    drawn = rng.drawn(a)  # the now marker (pemviz.app.plots.move_strip_marker) follows this series: on the chart
    now = np.full(t.size, np.nan)
    now[int(np.clip(step, 0, t.size - 1))] = drawn[int(np.clip(step, 0, t.size - 1))]
    dots = {"width": 0}
    off = np.flatnonzero(rng.below(a) | rng.above(a))
    why = {True: " (contact: the ego stops within one step)", False: ""}
    note = "" if off.size == 0 else (
        f"; {off.size} step{'s' * (off.size != 1)} off scale, drawn at the edge: "
        + ", ".join(f"{a[i]:.1f} m/s^2 at {t[i]:.2f} s{why[bool(contact[i])]}" for i in off[:3])
        + (" ..." if off.size > 3 else "")
    )  # fmt: skip
    plot.title = f"{title}: controller{note}"
    plot.series = (
        up.Series(label="t (s)"),
        up.Series(label="acceleration (m/s^2)", stroke=css(EGO_SPEED), width=2),
        up.Series(label="brake commanded", stroke=css(BRAKE_ZONE), points=_points(BRAKE_ZONE), **dots),
        up.Series(label="brake applied", stroke=css(CRASH), points=_points(CRASH), **dots),
        *([up.Series(label=f"acceleration off scale ({off.size})", stroke=hex_colour(BLACK), points=_ring(BLACK),
                     **dots)] if off.size else []),  # fmt: skip
        up.Series(label="now", stroke=hex_colour(BLACK), points=_points(BLACK, 9), **dots),  # the last series
    )
    ring = np.where(rng.below(a) | rng.above(a), drawn, np.nan)
    plot.data = (t, drawn, command, applied, *([ring] if off.size else []), now)
    plot.scales = {
        "x": up.Scale(time=False, auto=False, range=(0.0, float(t[-1]))),
        "y": up.Scale(auto=False, range=(bottom, top + 3 * row)),
    }


# -- Explain: a rollout of several objects with a story ----------------------------------------------
TRACK_GAP, TRACK_LATERAL, ACC = "track_gap", "track_lateral", "acc"
"""Keys of the charts of *Explain* for a rollout of several objects (:func:`object_plots`)."""
TRACK_RULE: dict[str, Any] = {"min_gap": 10.0, "min_pad": 0.5}
""":func:`pemviz.app.plots.robust_range` settings of the tracker charts (metres): a measurement more than 10 m (and
twice the others' spread) from the rest, a heavy tail of the noise PEM, is drawn at the edge."""


def object_plots(gui: viser.GuiApi, order: float | None = None) -> dict[str, viser.GuiUplotHandle]:
    """The three empty charts of *Explain* for a rollout of several objects, hidden until one whose drawing tells its
    story is shown (:func:`fill_object_plots`): car 0's gap ahead and lateral offset, truth against the tracker's
    estimate, and the ACC's acceleration with the car it follows."""
    t = np.linspace(0, 10, 2)
    none = np.full(2, np.nan)
    x_scale = up.Scale(time=False, auto=False, range=(0.0, 10.0))
    made = {}
    for i, (key, title, y, height) in enumerate((
        (TRACK_GAP, "car 0's gap ahead: truth and the tracker", "gap (m)", 190),
        (TRACK_LATERAL, "car 0's lateral offset: truth and the tracker", "m, right +", 180),
        (ACC, "ACC: acceleration and the car it follows", "m/s^2", 180),
    )):  # fmt: skip
        made[key] = gui.add_uplot(
            data=(t, none), series=(up.Series(label="t (s)"), up.Series(label=y)), title=title, scales={"x": x_scale},
            axes=axes("time (s)", y), legend=LEGEND, height=height, visible=False,
            order=None if order is None else order + 0.01 * i,
        )  # fmt: skip
    return made


def _at(values: np.ndarray, step: int | None) -> np.ndarray:
    """nan everywhere but ``step`` (None: everywhere), where ``values`` holds."""
    out = np.full(np.shape(values), np.nan)
    if step is not None and 0 <= step < out.size:
        out[step] = values[step]
    return out


def fill_object_plots(plots: dict[str, viser.GuiUplotHandle], ox: Any, step: int, title: str) -> None:
    """Draw object 0 of ``ox`` (:class:`pemviz.app.objects_view.ObjectsExplanation` with a story, e.g. the car that
    cuts in) in the charts of :func:`object_plots`, with a marker at ``step`` (the 3D scene's step, the last series of
    each chart):

    - its gap ahead (its rear minus the ego's front bumper, metres) as it truly was (black), where the tracker's
      confirmed track placed it (violet: the true gap plus the track's error along the road), where the camera
      measured it when detected (blue dots: plus the measurement's range error) and the steps it was missed (orange
      dots, on the truth), with the contact line at 0 m (red, dashed) and the failure step (a red dot);
    - its lateral offset from the centre of the ego's lane (metres, to the right) in the same colours, with the lane's
      edges at +-half its width (``ox.lane_width_m``; yellow, dashed): the ACC follows a track whose estimated centre
      lies inside them;
    - the ACC's acceleration at each decision (m/s^2, applied over the next step; IDM clipped to +-6 m/s^2), with two
      rows of dots above it: the steps it followed car 0's track (violet; another car's: grey) and the steps car 0's
      box overlapped the ego's lane (yellow).

    Sources: ``ox``'s positions, detections, measurements, tracks and gaps ahead, and its story (``severity``,
    ``acc``: the ACC's decisions, ``in_lane``: the steps object 0 overlapped the ego's lane),
    e.g. :class:`pemviz.scenarios.cut_in.story.CutInStory`. The y ranges are :func:`pemviz.app.plots.robust_range`'s
    (:data:`TRACK_RULE`, :data:`CONTROLLER_RULE`): a value off them is drawn at the edge and the title counts it.
    """
    st = ox.story
    t = np.asarray(ox.time_s, dtype=np.float64)
    i = int(np.clip(step, 0, t.size - 1))
    fail = st.severity.failure_step
    x_scale = up.Scale(time=False, auto=False, range=(0.0, float(t[-1])))
    dots = {"width": 0}
    det, seen = ox.detected[:, 0], ox.seen[:, 0]
    missed = seen & ~det
    failure_series = [] if fail is None else [
        up.Series(label=f"failure at {fail * st.severity.dt_s:.2f} s", stroke=css(CRASH), points=_points(CRASH, 10),
                  **dots)]  # fmt: skip

    def chart(key: str, what: str, unit_label: str, truth: np.ndarray, track: np.ndarray, measured: np.ndarray,
              levels: list[tuple[str, float, tuple[int, ...]]], at_least: tuple[float, float]) -> None:  # fmt: skip
        values = [truth, track, measured]
        rng = robust_range(np.concatenate(values), **TRACK_RULE,
                           at_least=(min(at_least[0], *(v for _, v, _ in levels)),
                                     max(at_least[1], *(v for _, v, _ in levels))))  # fmt: skip
        drawn = [rng.drawn(v) for v in values]
        extra_series, extra_data = off_scale_series(t, rng, values)
        plot = plots[key]
        plot.title = f"{title}: car 0's {what}, truth and the tracker{rng.note('value', '.1f', ' m')}"
        plot.series = (
            up.Series(label="t (s)"),
            up.Series(label="truth", stroke=hex_colour(BLACK), width=2),
            up.Series(label="measured (detected)", stroke=css(BLUE), points=_points(BLUE, 4), **dots),
            up.Series(label="missed", stroke=css(MISSED), points=_points(MISSED, 5), **dots),
            up.Series(label="tracker (confirmed track)", stroke=css(VIOLET), width=2),  # over the dots
            *(up.Series(label=label, stroke=css(colour), width=1.5, dash=[6, 4]) for label, _, colour in levels),
            *failure_series,
            *extra_series,
            up.Series(label="now", stroke=hex_colour(BLACK), points=_points(BLACK, 9), **dots),  # the last series
        )
        plot.data = (t, drawn[0], drawn[2], np.where(missed, drawn[0], np.nan), drawn[1],
                     *(np.full(t.size, v) for _, v, _ in levels),
                     *([_at(drawn[0], fail)] if failure_series else []), *extra_data, _at(drawn[0], i))  # fmt: skip
        plot.scales = {"x": x_scale, "y": up.Scale(auto=False, range=rng.range)}
        plot.axes = axes("time (s)", unit_label)
        plot.visible = True

    gap = ox.gap_ahead[:, 0]
    nan = np.full(t.size, np.nan)
    along = (ox.tracked[:, 0, 1] - ox.ahead_m[:, 0]) if ox.tracked is not None else nan
    meas_along = (ox.measured[:, 0, 1] - ox.ahead_m[:, 0]) if ox.measured is not None else np.where(det, 0.0, np.nan)
    chart(TRACK_GAP, "gap ahead", "gap (m)", gap, gap + along, gap + meas_along, [("contact 0 m", 0.0, CRASH)],
          (0.0, 5.0))  # fmt: skip
    half = ox.lane_width_m / 2
    chart(TRACK_LATERAL, "lateral offset from the ego's lane centre", "m, right +", ox.lateral_m[:, 0],
          ox.tracked[:, 0, 0] if ox.tracked is not None else nan,
          ox.measured[:, 0, 0] if ox.measured is not None else np.where(det, ox.lateral_m[:, 0], np.nan),
          [(f"ego's lane edge +{half:g} m", half, BRAKE_ZONE), (f"ego's lane edge -{half:g} m", -half, BRAKE_ZONE)],
          (-half, half))  # fmt: skip

    acc = st.acc
    ta, a = acc.time_s, acc.accel_mps2
    rng = robust_range(a, **CONTROLLER_RULE)
    row = 0.07 * (rng.hi - rng.lo)
    follows = np.where(acc.followed == 0, rng.hi + 2 * row, np.nan)
    other = np.where(acc.followed > 0, rng.hi + 2 * row, np.nan)
    in_lane = np.where(st.in_lane[: ta.size], rng.hi + row, np.nan)
    drawn = rng.drawn(a)
    ia = int(np.clip(step, 0, ta.size - 1))
    off = np.flatnonzero(rng.below(a) | rng.above(a))
    note = "" if off.size == 0 else f"; {off.size} step{'s' * (off.size != 1)} off scale, drawn at the edge"
    pairs: list[tuple[Any, np.ndarray]] = [
        (up.Series(label="acceleration (m/s^2)", stroke=css(EGO_SPEED), width=2), drawn),
        (up.Series(label="follows car 0", stroke=css(VIOLET), points=_points(VIOLET), **dots), follows),
    ]
    if np.isfinite(other).any():
        pairs.append((up.Series(label="follows another car", stroke=hex_colour(GREY), points=_points(GREY), **dots),
                      other))  # fmt: skip
    pairs.append((up.Series(label="car 0 in the ego's lane", stroke=css(BRAKE_ZONE), points=_points(BRAKE_ZONE),
                            **dots), in_lane))  # fmt: skip
    if fail is not None and fail < ta.size:
        pairs.append((failure_series[0], _at(drawn, fail)))
    if off.size:
        pairs.append((up.Series(label=f"acceleration off scale ({off.size})", stroke=hex_colour(BLACK),
                                points=_ring(BLACK), **dots), np.where(rng.below(a) | rng.above(a), drawn, np.nan)))
    pairs.append((up.Series(label="now", stroke=hex_colour(BLACK), points=_points(BLACK, 9), **dots),
                  _at(drawn, ia)))  # the last series  # fmt: skip
    plot = plots[ACC]
    plot.title = f"{title}: ACC acceleration (IDM on the followed track){note}"
    plot.series = (up.Series(label="t (s)"), *(series for series, _ in pairs))
    plot.data = (ta, *(values for _, values in pairs))
    plot.scales = {"x": x_scale, "y": up.Scale(auto=False, range=(rng.lo, rng.hi + 3 * row))}
    plot.axes = axes("time (s)", "m/s^2")
    plot.visible = True


def hide_object_plots(plots: dict[str, viser.GuiUplotHandle]) -> None:
    """Hide the charts of *Explain* for a rollout of several objects (another kind of rollout is shown, or none)."""
    for plot in plots.values():
        plot.visible = False
