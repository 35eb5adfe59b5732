"""uPlot figures of what the sampler really did, the charts of *Live*: q(detect) of each stage's sampler per gap bin
beside the PEM's (:mod:`pemviz.core.proposal_view`), and the log10 mu_hat chart with its interval and the exact answer.
"""

from __future__ import annotations

import html
import math
from typing import Any

import numpy as np
import viser
import viser.uplot as up

from pemviz.app.captions import add_chart, set_chart, show_chart
from pemviz.app.html import GREY as GREY_BOX
from pemviz.app.html import box
from pemviz.app.plots import LEGEND, _ring, axes, off_scale_series, robust_range, run_colour, run_series, stage_values
from pemviz.app.runs import PanelRun
from pemviz.core.proposal_view import ProposalView
from pemviz.engine.events import RolloutsSampled
from pemviz.sinks.colours import BLACK, GREY, css, hex_colour, stage_rgb, stage_span

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
MU_HAT_RULE: dict[str, Any] = {"min_gap": 3.0, "min_pad": 0.05}
""":func:`pemviz.app.plots.robust_range` settings of the log10 mu_hat chart (log10 probability), as
:data:`pemviz.app.plots.STAGE_RULES`."""


def marginal_plots(gui: viser.GuiApi) -> dict[str, viser.GuiUplotHandle]:
    """The two empty charts of the sampler's q(detect) over visited states: probability and log-odds of a miss, hidden
    until a run has a view to draw (:func:`fill_marginal_plots`)."""
    x = np.linspace(0.0, 13.0, 2)
    x_scale = up.Scale(time=False, auto=False, range=(0.0, 13.0))
    return {
        key: add_chart(
            gui,
            data=(x, np.full(2, np.nan)),
            series=(up.Series(label="gap (m)"), up.Series(label="PEM", stroke=hex_colour(BLACK))),
            title=title,
            scales={"x": x_scale, "y": up.Scale(auto=False, range=y_range)},
            axes=axes("gap d (m), 0.5 m bins", y_label),
            legend=LEGEND,
            height=height,
            visible=False,
        )
        for key, title, y_range, y_label, height in (
            (PROB, "mean q(detect) vs the PEM", (0.0, 1.04), "mean q(detect)", 230),
            (LOG_ODDS, "median log q(miss)/q(detect) (nats)", (-6.0, 2.0), "log-odds (nats)", 210),
        )
    }


def unchanged_share(values: np.ndarray, edges_m: np.ndarray) -> np.ndarray:
    """Per bin (``edges_m``, metres), the share of the visited states ``values`` [N, T] equal to the same rollout's
    one step before (cars at rest, one state counted again each step): float64 [B], nan for an empty bin."""
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
    """(stage, name, view) of the stages drawn by a sampler other than the PEM's pretraining, in order. Each name is
    the chart's legend entry, so no two are alike: ``stage 3``, ``final batch``; a run whose stages ran once more (a
    retry) has two final batches, each named with its stage (``final batch (stage 4)``, ``final batch (stage 9)``)."""
    with record.lock:
        views = dict(record.proposal_views)
    drawn = [(stage, *views[stage]) for stage in sorted(views) if views[stage][0] != "pretrain"]  # pretraining: q = p
    n_final = sum(kind == "final" for _, kind, _ in drawn)

    def name(stage: int, kind: str) -> str:
        if kind != "final":
            return f"stage {stage}"
        return "final batch" if n_final == 1 else f"final batch (stage {stage})"

    return [(stage, name(stage, kind), view) for stage, kind, view in drawn]


def marginal_note(record: PanelRun | None) -> str:
    """Why the q(detect) charts of *Live* are hidden (HTML; empty when ``record`` has a view to draw)."""
    if record is None:
        why = "no run yet"
    elif _view_stages(record):
        return ""
    elif any(r.kind == "ce" for r in record.stages) or (
        record.view is not None and record.view.thresholds is None and record.view.objects_xy is None
    ):
        drew = "its stages drew from a proposal, but " if any(r.kind == "ce" for r in record.stages) else ""
        why = (
            f"{html.escape(record.short_label)}: {drew}its scene gives no axis to bin q(detect) by (its drawing's "
            "proposal_axis, or a detection window on a scene of one object a step)"
        )
    else:
        why = (
            f"{html.escape(record.short_label)}: no stage drawn by a proposal yet (pretraining draws from the PEM "
            "itself, q = p)"
        )
    return box(f"q(detect) over the visited states: {why}.", GREY_BOX)


def fill_marginal_plots(
    plots: dict[str, viser.GuiUplotHandle], record: PanelRun, note: viser.GuiHtmlHandle | None = None
) -> None:
    """Each stage's mean q(detect) and median log-odds of a miss (nats) over its visited states, per bin of the view's
    axis, the PEM's at the newest stage's states, and the newest stage's 10-90 % spread as a band; without a view both
    charts are hidden and ``note`` says why. Bins with fewer than :data:`MIN_BIN_STATES` states are left out of the
    lines; bins crowded with standing states (:func:`standing_bins`) are ringed in grey. The log-odds range is at most
    -12..12 nats."""
    stages = _view_stages(record)
    if note is not None:
        note.content = marginal_note(record)
    for plot in plots.values():
        show_chart(plot, bool(stages))
    if not stages:
        return
    cfg = record.config
    axis = record.proposal_axis
    last_stage, last_name, last = stages[-1]
    n_colour = stage_span(record.plan)
    x = last.centres_m
    x_range = (float(last.edges_m[0]), float(last.edges_m[-1]))
    plain_mc = cfg.method_record.plain
    standing_signal = axis.standing_signal
    whose = "" if standing_signal is not None else f" of {axis.subject}"
    who = (
        "plain Monte Carlo: the rollouts are the PEM's own (q = p)"
        if plain_mc
        else (
            f"mean q(miss) {axis.window_name} {last.window_m:g} m {last.q_miss_window:.3g} vs the PEM's "
            f"{last.p_miss_window:.3g} ({last_name})"
        )
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
    crowd = (
        ""
        if standing.size == 0
        else "; ringed: mostly standing states (the gap unchanged since the step "
        "before, one state counted each step) "
        + ", ".join(
            f"{last.edges_m[b]:g}-{last.edges_m[b + 1]:g} m {share[b]:.0%} of {int(last.n_states[b]):,}"
            for b in standing
        )
    )

    def enough(view: ProposalView, values: np.ndarray) -> np.ndarray:
        return np.where(view.n_states >= MIN_BIN_STATES, np.asarray(values, dtype=np.float64), np.nan)

    for key, (mid, lo, hi, p_mid) in {
        PROB: ("q_mean", "q_lo", "q_hi", "p_mean"),
        LOG_ODDS: ("q_log_odds", "q_log_odds_lo", "q_log_odds_hi", "p_log_odds"),
    }.items():
        colour = css(stage_rgb(last_stage, n_colour))
        lines = [enough(last, getattr(last, p_mid))] + [enough(view, getattr(view, mid)) for _, _, view in stages]
        if key == PROB:
            title = "mean q(detect) vs the PEM"
            caption = f"{record.short_label}: mean q(detect){whose} over the visited states · {who}{few}{crowd}"
            rng = robust_range(np.zeros(0), at_least=(0.0, 1.04))  # probabilities: always 0..1 (tick 1 inside)
        else:
            title = "median log q(miss)/q(detect) (nats)"
            caption = (
                f"{record.short_label}: the median log-odds of a miss{whose} over the visited states, in nats{few}"
            )
            # the medians of the bins with enough states decide the range (ticks -6 and 2 inside it); a band may
            # leave it, a median beyond is drawn at the edge
            rng = robust_range(
                np.concatenate(lines),
                min_pad=0.3,
                pad_frac=0.06,
                at_least=(-6.4, 2.4),
                limits=(-LOG_ODDS_SPAN, LOG_ODDS_SPAN),
            )
            caption += rng.note("median", ".1f", " nats")
        series: list[Any] = [
            up.Series(label=axis.series_label),
            up.Series(label=f"{last_name} 10 %", stroke=colour, width=1, dash=(3, 3)),
            up.Series(label=f"{last_name} 90 %", stroke=colour, width=1, dash=(3, 3)),
            up.Series(label="PEM", stroke=hex_colour(BLACK), width=2.5),
        ]
        data = [x, enough(last, getattr(last, lo)), enough(last, getattr(last, hi)), rng.drawn(lines[0])]
        for (stage, name, view), line in zip(stages, lines[1:], strict=False):
            width = 2 if view is last else 1.5
            series.append(up.Series(label=name, stroke=css(stage_rgb(stage, n_colour)), width=width))
            data.append(rng.drawn(line))
        if sparse.any():
            series.append(
                up.Series(
                    label=f"{last_name}, bins under {MIN_BIN_STATES} states",
                    stroke=colour,
                    points=_ring(stage_rgb(last_stage, n_colour), 8),
                    width=0,
                )
            )
            data.append(rng.drawn(np.where(sparse, getattr(last, mid), np.nan)))
        if key == PROB and standing.size:
            mark = np.full(x.size, np.nan)
            mark[standing] = getattr(last, mid)[standing]
            series.append(
                up.Series(
                    label=f"{last_name}, mostly standing states",
                    stroke=hex_colour(GREY),
                    points=_ring(GREY, 14),
                    width=0,
                )
            )
            data.append(mark)
        extra_series, extra_data = off_scale_series(x, rng, lines)
        plot = plots[key]
        set_chart(plot, title, caption)
        plot.series = tuple(series + extra_series)
        plot.data = tuple(np.asarray(d, dtype=np.float64) for d in data + extra_data)
        plot.bands = (up.Band(series=(2, 1), fill=css(stage_rgb(last_stage, n_colour), 0.15)),)
        plot.scales = {"x": up.Scale(time=False, auto=False, range=x_range), "y": up.Scale(auto=False, range=rng.range)}
        plot.axes = axes(axis.label, "mean q(detect)" if key == PROB else "log-odds (nats)")


def fill_mu_hat_plot(plot: viser.GuiUplotHandle, runs: list[PanelRun]) -> None:
    """The log10 mu_hat chart with each run's 95 % interval per stage as a band and the exact answer as a black line.
    The y range is :func:`pemviz.app.plots.robust_range` (:data:`MU_HAT_RULE`) of the stages with a failure, widened
    to the exact answer; a stage without failures is drawn at the top edge, ringed and counted."""
    if not runs:
        return
    _, _, shown, x, ys = stage_values("log10_mu_hat", runs)
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
        series += [
            up.Series(label=f"{r.short_label} 95 % low", stroke=colour, width=1, dash=(4, 3)),
            up.Series(label=f"{r.short_label} 95 % high", stroke=colour, width=1, dash=(4, 3)),
        ]
        lines += [lo, hi]
        matters += [failed, failed]
        bands.append(up.Band(series=(len(series) - 1, len(series) - 2), fill=f"{colour}26"))
    exact = runs[-1].exact_log_p
    known = exact is not None and math.isfinite(exact)
    exact10 = exact / ln10 if exact is not None else math.nan  # log10 of the exact answer, drawn where known
    rng = robust_range(
        np.concatenate(lines), np.concatenate(matters), **MU_HAT_RULE, at_least=(exact10, exact10) if known else None
    )
    data = [x, *(rng.drawn(y) for y in lines)]
    if known:
        series.append(up.Series(label=f"exact answer {exact10:.3f}", stroke=hex_colour(BLACK), width=1.5, dash=(8, 4)))
        data.append(np.full(n, exact10))
    extra_series, extra_data = off_scale_series(x, rng, lines)
    set_chart(
        plot,
        "log10 mu_hat per stage",
        "log10 of each stage's mu_hat; band: its 95 % interval (a bound alone where no interval is backed)"
        + ("; black: the exact answer" * known)
        + rng.note("point", ".1f"),
    )
    plot.series = tuple(series + extra_series)
    plot.data = tuple(data + extra_data)
    plot.bands = tuple(bands)
    plot.scales = {
        "x": up.Scale(time=False, auto=False, range=(-0.5, float(x[-1]) + 0.5)),
        "y": up.Scale(auto=False, range=rng.range),
    }
