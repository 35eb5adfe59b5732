"""uPlot figures of what the sampler really did and of a rollout's controller (viser's ``add_uplot``).

*Live*: q(detect) of each stage's sampler over the states its rollouts visited, per gap bin, beside the PEM's
(:mod:`pemviz.core.proposal_view`), on a probability and on a log-odds scale, and the 95 % interval and the exact answer
on the log10 mu_hat chart. *Explain*: the controller's brake command, applied brake and acceleration along a
rollout. Colours from :mod:`pemviz.sinks.colours`; every range set from the data that exists.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import viser
import viser.uplot as up

from pemviz.app.explain import Explanation
from pemviz.app.plots import LEGEND, _points, axes, run_colour
from pemviz.app.runs import PanelRun
from pemviz.core.proposal_view import ProposalView
from pemviz.sinks.colours import BLACK, BRAKE_ZONE, CRASH, EGO_SPEED, css, hex_colour, stage_rgb

PROB, LOG_ODDS = "prob", "log_odds"
LOG_ODDS_SPAN = 12.0
"""The log-odds chart shows at most -12..12 nats (odds of 1:160,000); values beyond leave the chart."""


def marginal_plots(gui: viser.GuiApi) -> dict[str, viser.GuiUplotHandle]:
    """The two empty charts of the sampler's q(detect) over visited states: probability and log-odds of a miss."""
    x = np.linspace(0.0, 13.0, 2)
    none = np.full(2, np.nan)
    x_scale = up.Scale(time=False, auto=False, range=(0.0, 13.0))
    return {
        PROB: gui.add_uplot(
            data=(x, none), series=(up.Series(label="gap (m)"), up.Series(label="PEM", stroke=hex_colour(BLACK))),
            title="q(detect) over the visited states per stage vs the PEM",
            scales={"x": x_scale, "y": up.Scale(auto=False, range=(0.0, 1.04))},
            axes=axes("gap d (m), 0.5 m bins", "mean q(detect)"), legend=LEGEND, height=230,
        ),
        LOG_ODDS: gui.add_uplot(
            data=(x, none), series=(up.Series(label="gap (m)"), up.Series(label="PEM", stroke=hex_colour(BLACK))),
            title="log q(miss) / q(detect) over the visited states",
            scales={"x": x_scale, "y": up.Scale(auto=False, range=(-6.0, 2.0))},
            axes=axes("gap d (m), 0.5 m bins", "log-odds (nats)"), legend=LEGEND, height=210,
        ),
    }  # fmt: skip


def _padded(values: list[np.ndarray], lo: float = -math.inf, hi: float = math.inf) -> tuple[float, float]:
    v = np.concatenate([np.ravel(a) for a in values]) if values else np.zeros(0)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return (-1.0, 1.0)
    a, b = float(v.min()), float(v.max())
    pad = max(0.3, 0.06 * (b - a))
    return (max(lo, a - pad), min(hi, b + pad))


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


def fill_marginal_plots(plots: dict[str, viser.GuiUplotHandle], record: PanelRun) -> None:
    """Each stage's mean q(detect) and median log-odds of a miss over its visited states, per gap bin, the PEM's at
    the newest stage's states, and the newest stage's 10-90 % spread as a band."""
    stages = _view_stages(record)
    if not stages:
        return
    cfg = record.config
    last_stage, last_name, last = stages[-1]
    n_colour = max(1, cfg.n_stages + 1 if cfg.method == "adaptive" else 1)
    x = last.centres_m
    plain_mc = cfg.method == "mc"
    who = "plain Monte Carlo: the rollouts are the PEM's own (q = p)" if plain_mc else (
        f"mean q(miss) below {last.window_m:g} m {last.q_miss_window:.3g} vs the PEM's {last.p_miss_window:.3g} "
        f"({last_name})"
    )
    for key, (mid, lo, hi, p_mid) in {
        PROB: ("q_mean", "q_lo", "q_hi", "p_mean"),
        LOG_ODDS: ("q_log_odds", "q_log_odds_lo", "q_log_odds_hi", "p_log_odds"),
    }.items():
        colour = css(stage_rgb(last_stage, n_colour))
        series: list[Any] = [
            up.Series(label="gap (m)"),
            up.Series(label=f"{last_name} 10 %", stroke=colour, width=1, dash=[3, 3]),
            up.Series(label=f"{last_name} 90 %", stroke=colour, width=1, dash=[3, 3]),
            up.Series(label="PEM", stroke=hex_colour(BLACK), width=2.5),
        ]
        data = [x, getattr(last, lo), getattr(last, hi), getattr(last, p_mid)]
        for stage, name, view in stages:
            width = 2 if view is last else 1.5
            series.append(up.Series(label=name, stroke=css(stage_rgb(stage, n_colour)), width=width))
            data.append(getattr(view, mid))
        plot = plots[key]
        if key == PROB:
            plot.title = f"{record.short_label}: mean q(detect) over the visited states · {who}"
            y = (0.0, 1.04)
        else:
            plot.title = f"{record.short_label}: median log q(miss)/q(detect) over the visited states (nats)"
            mids = [getattr(v, mid) for _, _, v in stages] + [getattr(last, p_mid)]
            lo_, hi_ = _padded(mids, -LOG_ODDS_SPAN, LOG_ODDS_SPAN)
            y = (min(lo_, -6.4), max(hi_, 2.4))  # the medians decide the range (ticks -6 and 2 inside it); a band or
            # a spike may leave it
        plot.series = tuple(series)
        plot.data = tuple(np.asarray(d, dtype=np.float64) for d in data)
        plot.bands = (up.Band(series=(2, 1), fill=css(stage_rgb(last_stage, n_colour), 0.15)),)
        plot.scales = {"x": up.Scale(time=False, auto=False, range=(0.0, 13.0)), "y": up.Scale(auto=False, range=y)}


def fill_mu_hat_plot(plot: viser.GuiUplotHandle, runs: list[PanelRun]) -> None:
    """Add to the log10 mu_hat chart (already filled by :func:`pemviz.app.plots.fill_stage_plot`) each run's 95 %
    interval per stage as a band between dashed lines and the exact answer as a black line where the run knows it."""
    data = list(plot.data)
    series = list(plot.series)
    if not runs or len(data) < 2:
        return
    x = np.asarray(data[0], dtype=np.float64)
    n = x.size
    values = [np.asarray(d, dtype=np.float64) for d in data[1:]]
    bands = []
    ln10 = math.log(10.0)
    for r in runs:
        lo, hi = np.full(n, np.nan), np.full(n, np.nan)
        with r.lock:
            stages = list(r.stages)
        for s in stages:
            if 0 <= s.stage < n:
                a, b = s.estimate.log_ci
                lo[s.stage], hi[s.stage] = a / ln10, b / ln10
        lo[~np.isfinite(lo)] = np.nan
        hi[~np.isfinite(hi)] = np.nan
        if np.all(np.isnan(hi)):
            continue
        colour = run_colour(r.run_id)
        series += [up.Series(label=f"{r.short_label} 95 % low", stroke=colour, width=1, dash=[4, 3]),
                   up.Series(label=f"{r.short_label} 95 % high", stroke=colour, width=1, dash=[4, 3])]  # fmt: skip
        data += [lo, hi]
        values += [lo, hi]
        bands.append(up.Band(series=(len(series) - 1, len(series) - 2), fill=f"{colour}26"))
    exact = runs[-1].exact_log_p
    if exact is not None and math.isfinite(exact):
        series.append(up.Series(label=f"exact {exact / ln10:.3f}", stroke=hex_colour(BLACK), width=1.5, dash=[8, 4]))
        data.append(np.full(n, exact / ln10))
        values.append(data[-1])
    plot.title = "log10 mu_hat per stage, 95 % interval (band)" + (", exact answer (black)" * (exact is not None))
    plot.series = tuple(series)
    plot.data = tuple(data)
    plot.bands = tuple(bands)
    plot.scales = {"x": plot.scales["x"], "y": up.Scale(auto=False, range=_padded(values))}


def controller_plot(gui: viser.GuiApi, order: float | None = None) -> viser.GuiUplotHandle:
    """The empty controller chart of *Explain*."""
    t = np.linspace(0, 5, 2)
    return gui.add_uplot(
        data=(t, np.full(2, np.nan)), series=(up.Series(label="t (s)"), up.Series(label="acceleration (m/s^2)")),
        title="controller: brake command, brake applied, acceleration (choose a rollout)",
        scales={"x": up.Scale(time=False, auto=False, range=(0.0, 5.0))}, axes=axes("time (s)", "m/s^2"),
        legend=LEGEND, height=170, order=order,
    )  # fmt: skip


def fill_controller_plot(plot: viser.GuiUplotHandle, ex: Explanation, step: int, title: str) -> None:
    """The ego's acceleration, and as rows of dots above it the steps at which the emergency brake was commanded
    (the lead detected within the braking distance) and applied (one step later); a marker at ``step``."""
    c = ex.controller
    t = c.time_s
    a = c.accel_mps2
    top = max(4.0, float(np.max(a)) + 1.0)
    bottom = min(-4.0, float(np.min(a)) - 1.0)
    row = 0.07 * (top - bottom)  # two rows of dots above the curve, apart at any scale
    command = np.where(c.brake_command, top + 2 * row, np.nan)
    applied = np.where(c.brake_applied, top + row, np.nan)
    now = np.full(t.size, np.nan)
    now[int(np.clip(step, 0, t.size - 1))] = a[int(np.clip(step, 0, t.size - 1))]
    dots = {"width": 0}
    plot.title = f"{title}: controller"
    plot.series = (
        up.Series(label="t (s)"),
        up.Series(label="acceleration (m/s^2)", stroke=css(EGO_SPEED), width=2),
        up.Series(label="brake commanded", stroke=css(BRAKE_ZONE), points=_points(BRAKE_ZONE), **dots),
        up.Series(label="brake applied", stroke=css(CRASH), points=_points(CRASH), **dots),
        up.Series(label="now", stroke=hex_colour(BLACK), points=_points(BLACK, 9), **dots),
    )
    plot.data = (t, a, command, applied, now)
    plot.scales = {
        "x": up.Scale(time=False, auto=False, range=(0.0, float(t[-1]))),
        "y": up.Scale(auto=False, range=(bottom, top + 3 * row)),
    }


