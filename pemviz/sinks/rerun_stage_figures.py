"""The per-stage series of a recording as static figures (:class:`pemviz.sinks.rerun_views.Figure`, re-logged after
each stage), visible on every timeline: rerun draws every view on the one chosen timeline, so series over ``stage``
would be blank on ``step``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import rerun as rr

from pemviz.engine.events import RolloutsSampled
from pemviz.sinks import colours as C
from pemviz.sinks.rerun_views import CRASH_RGBA, HISTOGRAM_BINS, PEM_PLOT_RGBA, STAGE_METRICS, Figure

EXTRA_SERIES = (
    ("miss_in_window", "mean miss in the window: q (blue), PEM (grey)", C.PROPOSAL),
    ("contact_share", "share of the stage's failures with contact", C.CRASH),
)
"""Series beyond :data:`pemviz.sinks.rerun_views.STAGE_METRICS`: key, title, colour."""

EMPTY = {
    "khat": "no k-hat yet: it needs 25 failures in a stage to fit the weights' tail",
    "nll": "no NLL yet: no failure so far",
    "log10_mu_hat": "no estimate yet",
    "gamma": "no threshold yet",
}
"""What a figure says while its series has no finite value."""

FIGURE_ROOT = "stage_figures"
"""Root of the figures' entities: ``stage_figures/<key>/{data,axes}``."""


def figure(key: str) -> Figure:
    """The figure of series ``key`` over the stages (its titles go in the view's name), as wide as the views."""
    return Figure(f"{FIGURE_ROOT}/{key}", "", "", width=240.0, height=100.0)


def stage_ticks(last_stage: int) -> np.ndarray:
    """Stages to label on the x axis: every one up to 8 stages, else every 2nd, 5th, 10th, ... (about 6 labels)."""
    step = next(k for k in (1, 2, 5, 10, 20, 50, 100, 10**9) if (last_stage + 1) / k <= 8)
    return np.arange(0, last_stage + 1, step)


def figure_titles(scene: bool, window: bool = True) -> list[tuple[str, str]]:
    """(key, title) of every figure, in the Stages tab's order; ``contact_share`` only for a scene with contact,
    ``miss_in_window`` only with a sampler window over one object's gap (``window``)."""
    titles = {
        "log10_mu_hat": "log10 mu_hat per stage: 95 % interval (bars), exact or reference (line)",
        "nll": "NLL of the failures (nats)",
    }
    out = [(key, titles.get(key, name)) for key, name, _ in STAGE_METRICS]
    out += [
        (key, title)
        for key, title, _ in EXTRA_SERIES
        if (scene or key != "contact_share") and (window or key != "miss_in_window")
    ]
    return out


def _range(values: list[float]) -> tuple[float, float]:
    v = np.asarray([x for x in values if math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return (0.0, 1.0)
    lo, hi = float(v.min()), float(v.max())
    pad = 0.08 * (hi - lo) if hi > lo else max(0.5, 0.1 * abs(lo))
    return (lo - pad, hi + pad)


@dataclass
class StageFigures:
    """The figures of one recording: call :meth:`add` after each stage with its values.

    Args:
        stream: the recording.
        last_stage: the plan's last stage (the x axis runs from 0 to it; it grows if a run adds stages).
        known_log10: log10 of the exact answer, or of the reference, drawn across log10 mu_hat; None: none known.
        scene: the problem has a scene with contact (its share of contact is drawn)."""

    stream: rr.RecordingStream
    last_stage: int
    known_log10: float | None = None
    scene: bool = True
    series: dict[str, dict[int, float]] = field(default_factory=dict)

    def add(self, stage: int, values: dict[str, float]) -> None:
        """Record stage ``stage``'s values (keys as the ``stages/<key>`` series of the recording,
        ``log10_mu_hat/ci_low`` and ``/ci_high`` included; non-finite ones are left out) and re-log every figure."""
        for key, value in values.items():
            if math.isfinite(value):
                self.series.setdefault(key, {})[stage] = float(value)
        self.last_stage = max(self.last_stage, stage)
        for key, _ in figure_titles(self.scene):
            self._draw(key)

    def _points(self, key: str) -> np.ndarray:
        s = self.series.get(key, {})
        return np.array(sorted(s.items()), dtype=np.float64).reshape(-1, 2)

    def _draw(self, key: str) -> None:
        fig, s = figure(key), self.stream
        parts = {"miss_in_window": ("miss_in_window/q", "miss_in_window/pem")}.get(key, (key,))
        curves = [(part, self._points(part)) for part in parts]
        if all(c.size == 0 for _, c in curves):  # the axes and a note in place of an empty view
            fig.draw_axes(
                s, (-0.5, self.last_stage + 0.5), (0.0, 1.0), x_ticks=stage_ticks(self.last_stage), n_y_ticks=3
            )
            s.log(
                f"{fig.path}/data/note",
                rr.Points2D(
                    [[self.last_stage / 2, 0.5]],
                    radii=-0.01,
                    labels=[EMPTY.get(key, "no finite value yet")],
                    colors=C.rgba(C.ON_DARK),
                    show_labels=True,
                ),
                static=True,
            )
            return
        s.log(f"{fig.path}/data/note", rr.Clear(recursive=False), static=True)
        ys = [float(y) for _, c in curves for y in c[:, 1]]
        bars = np.zeros((0, 3))
        if key == "log10_mu_hat":
            lo, hi = self.series.get("log10_mu_hat/ci_low", {}), self.series.get("log10_mu_hat/ci_high", {})
            failed = {k for k, v in self.series.get("failure_rate", {}).items() if v > 0}
            bars = np.array([(k, lo[k], hi[k]) for k in sorted(lo) if k in hi], dtype=np.float64).reshape(-1, 3)
            ys = [y for k, y in self.series.get(key, {}).items() if k in failed] or ys
            ys += [v for b in bars if b[0] in failed for v in b[1:]]
            if self.known_log10 is not None:
                ys.append(self.known_log10)
        if key in ("failure_rate", "contact_share", "miss_in_window"):
            y_range = (-0.04, 1.04)
        else:
            y_range = _range(ys)
        fig.draw_axes(s, (-0.5, self.last_stage + 0.5), y_range, x_ticks=stage_ticks(self.last_stage), n_y_ticks=3)
        y0, y1 = y_range
        colours = {k: rgb for k, _, rgb in (*STAGE_METRICS, *EXTRA_SERIES)}
        for part, c in curves:
            rgb = C.GREY if part.endswith("/pem") else colours.get(part.split("/")[0], C.BLUE)
            c = c.copy()
            c[:, 1] = np.clip(c[:, 1], y0, y1)  # a value off the range is drawn at its edge
            name = part.replace("/", "_")
            s.log(f"{fig.path}/data/{name}/line", rr.LineStrips2D([c], colors=C.rgba(rgb), radii=-1.5), static=True)
            s.log(f"{fig.path}/data/{name}/points", rr.Points2D(c, colors=C.rgba(rgb), radii=-3.0), static=True)
        if bars.size:
            segs = [[[k, max(a, y0)], [k, min(b, y1)]] for k, a, b in bars]
            s.log(
                f"{fig.path}/data/interval", rr.LineStrips2D(segs, colors=C.rgba(C.INTERVAL), radii=-1.0), static=True
            )
        if key == "log10_mu_hat" and self.known_log10 is not None:
            k = min(max(self.known_log10, y0), y1)
            line = [[[-0.5, k], [self.last_stage + 0.5, k]]]
            s.log(f"{fig.path}/data/known", rr.LineStrips2D(line, colors=C.rgba(C.DETECTED), radii=-1.0), static=True)


def log_series_styles(s: rr.RecordingStream, scene: bool) -> None:
    """Static styling of the per-stage scalars ``stages/<series>`` on the ``stage`` timeline (names, colours,
    markers), for a time-series view a user builds over them; ``scene``: the contact share is one of them."""
    for key, name, rgb in STAGE_METRICS:
        s.log(
            f"stages/{key}",
            rr.SeriesLines(colors=[C.rgba(rgb)], names=[name], widths=[2.0]),
            rr.SeriesPoints(colors=[C.rgba(rgb)], names=[name], marker_sizes=[3.0]),
            static=True,
        )
    for key, name, rgb in (
        ("ci_low", "95 % interval, low", C.INTERVAL),
        ("ci_high", "95 % interval, high", C.INTERVAL),
        ("exact", "exact answer", C.DETECTED),
    ):
        s.log(
            f"stages/log10_mu_hat/{key}", rr.SeriesLines(colors=[C.rgba(rgb)], names=[name], widths=[1.0]), static=True
        )
    for key, name, rgba in (
        ("miss_in_window/q", "mean q(miss) of the sampler", C.rgba(C.PROPOSAL)),
        ("miss_in_window/pem", "mean p(miss) of the PEM", PEM_PLOT_RGBA),
        ("contact_share", "share of failures with contact", C.rgba(C.CRASH)),
    ):
        if key == "contact_share" and not scene:
            continue
        s.log(
            f"stages/{key}",
            rr.SeriesLines(colors=[rgba], names=[name], widths=[2.0]),
            rr.SeriesPoints(colors=[rgba], names=[name], marker_sizes=[3.0]),
            static=True,
        )


def log_histograms(s: rr.RecordingStream, ev: RolloutsSampled, bins: int = HISTOGRAM_BINS) -> None:
    """Histograms of every rollout's robustness and log-weight at the stage of ``ev`` (:class:`rerun.BarChart` on
    ``stage``, and on ``step`` 0 so that ``step`` shows the last stage's)."""
    every = ev.n_total is not None  # a streamed stage: the sample's rows, every rollout's numbers
    for key, values in (
        ("robustness", ev.stage_robustness if every else ev.robustness),
        ("log_weight", ev.stage_log_weight if every else ev.log_weight),
    ):
        v = np.asarray(values, dtype=np.float64)
        v = v[np.isfinite(v)]
        if v.size == 0:
            continue
        counts, edges = np.histogram(v, bins=bins if np.ptp(v) > 0 else 1)
        colour = CRASH_RGBA[:3] + (255,) if key == "robustness" else C.rgba(C.LOG_WEIGHT)
        s.set_time("step", sequence=0)
        s.log(
            f"histograms/{key}",
            rr.BarChart(
                counts.astype(np.float64), abscissa=(edges[:-1] + edges[1:]) / 2, widths=np.diff(edges), color=colour
            ),
        )
        s.disable_timeline("step")
