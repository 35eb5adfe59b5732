"""The *Compare* tab's chart and table: every kept run's final estimate side by side (mu_hat, its 95 % interval, the
exact answer or reference, on a log10 axis), and the settings that differ between the kept runs."""

from __future__ import annotations

import html
import math
from dataclasses import dataclass
from typing import Any, TypedDict

import numpy as np
import viser
import viser.uplot as up

from pemviz.app.captions import add_chart
from pemviz.app.form import setting_value, settings_of
from pemviz.app.html import TABLE_STYLE
from pemviz.app.plots import axes, finite_or_dash, run_colour
from pemviz.app.runs import PanelRun
from pemviz.core.estimate import format_probability
from pemviz.sinks.colours import BLACK, REFERENCE_LINE, hex_colour

TITLE = "log10 mu_hat of each kept run"
CAPTION = (
    "each kept run's log10 mu_hat with its 95 % interval; the exact answer (black) or the plain Monte Carlo reference "
    "(grey, dashed) where its scene has one"
)
"""The chart's caption (:mod:`pemviz.app.captions`): what its marks mean."""
EXACT = "exact"
"""The end of the label of a run's exact answer (a bar across its position where its problem knows it)."""
REFERENCE = "reference (plain Monte Carlo)"
"""The end of the label of a run's plain Monte Carlo reference (a bar, where its problem has no exact answer)."""
CAP_HALF_WIDTH = 0.12
"""Half the width of an interval's caps, in x positions (one run per unit)."""
BAR_HALF_WIDTH = 0.3
"""Half the width of an exact or reference bar, in x positions."""
_OFFSETS = np.array([-BAR_HALF_WIDTH, -CAP_HALF_WIDTH, 0.0, 0.0, CAP_HALF_WIDTH, BAR_HALF_WIDTH])
"""The x offsets drawn at each run's position (bar, caps, the interval's line twice, caps, bar); every series
belongs to one run and is nan at the others' offsets, since uPlot gaps only at null."""
_BAR = slice(0, 6)
_CAP = slice(1, 5)
_BOTTOM, _TOP = 2, 3
_LN10 = math.log(10.0)


@dataclass(frozen=True)
class RunPoint:
    """What the chart draws for one kept run, as log10 of probabilities (finite values, or None: not drawn).

    Attributes:
        record: the run.
        log10_mu: log10 of its final mu_hat; None without a final estimate or with no failure.
        log10_lo, log10_hi: log10 of its 95 % interval's ends; ``log10_lo`` None when the interval reaches 0.
        log10_bound: log10 of the upper bound of a run without failure whose rollouts bound p; None otherwise.
        log10_exact: log10 of the exact answer of the run's problem; None where unknown.
        log10_reference: log10 of the plain Monte Carlo reference, where there is no exact answer.
        bound_only: the run's weights back no interval: ``log10_lo`` is its 95 % lower bound, ``log10_hi`` None.
        note: why nothing, or only a bound, is drawn for this run ("" when its estimate is drawn)."""

    record: PanelRun
    log10_mu: float | None = None
    log10_lo: float | None = None
    log10_hi: float | None = None
    log10_bound: float | None = None
    log10_exact: float | None = None
    log10_reference: float | None = None
    bound_only: bool = False
    note: str = ""


class _Known(TypedDict, total=False):
    """What a run's problem knows of its answer (:func:`run_point`): :attr:`RunPoint.log10_exact`, else
    :attr:`RunPoint.log10_reference`."""

    log10_exact: float | None
    log10_reference: float | None


def _log10(log_p: float | None) -> float | None:
    """log10 of a probability given as a natural log; None for None, -inf, +inf or nan."""
    if log_p is None or not math.isfinite(log_p):
        return None
    return log_p / _LN10


def run_point(record: PanelRun) -> RunPoint:
    """What the chart draws for ``record``: its final estimate and interval, or the bound or note of a run without one,
    and its problem's exact answer or reference."""
    with record.lock:
        final, exact, reference, status = record.final, record.exact_log_p, record.reference, record.status
    known: _Known = {"log10_exact": _log10(exact)}
    if known["log10_exact"] is None and reference is not None:
        known["log10_reference"] = _log10(reference.log_p)
    name = record.short_label
    if final is None:
        return RunPoint(record, note=f"{name}, {status}: no final estimate, not drawn", **known)
    e = final.estimate
    lo, hi = e.log_ci
    if e.n_failures == 0 or e.log_mu_hat == -math.inf:
        bound = _log10(hi) if hi < 0.0 else None
        if bound is None:
            return RunPoint(
                record,
                note=f"{name}: no failure in {e.n} rollouts, mu_hat = 0; under importance sampling "
                "this bounds nothing, not drawn",
                **known,
            )
        note = f"{name}: no failure in {e.n} rollouts, mu_hat = 0: drawn is the bound p < {format_probability(hi, 2)}"
        return RunPoint(record, log10_bound=bound, note=note, **known)
    mu = _log10(e.log_mu_hat)
    if not e.interval_backed:  # the weights back no interval: its lower bound, and a line to the top (no upper end)
        if mu is None:
            return RunPoint(record, note=f"{name}: mu_hat is not a finite number, not drawn", **known)
        note = (
            f"{name} is {e.verdict}: its weights back no interval; drawn is its 95 % lower bound "
            f"p >= {format_probability(e.log_lower_bound, 2)}, with no upper bound"
        )
        return RunPoint(record, log10_mu=mu, log10_lo=_log10(e.log_lower_bound), bound_only=True, note=note, **known)
    if mu is None or _log10(hi) is None or math.isnan(lo):
        return RunPoint(record, note=f"{name}: mu_hat or its interval is not a finite number, not drawn", **known)
    low = _log10(lo)
    note = "" if low is not None else f"{name}: the 95 % interval reaches 0, its line runs off the bottom of the chart"
    return RunPoint(record, log10_mu=mu, log10_lo=low, log10_hi=_log10(hi), note=note, **known)


def estimate_plot(gui: viser.GuiApi) -> viser.GuiUplotHandle:
    """The empty chart of the *Compare* tab (x: kept runs; y: log10 p)."""
    return add_chart(
        gui,
        caption=CAPTION,
        data=(np.array([0.5, 1.5]), np.full(2, np.nan)),
        series=(up.Series(label="run"), up.Series(label="no run yet", stroke=hex_colour(BLACK))),
        title="log10 mu_hat of each kept run (no run yet)",
        scales={"x": up.Scale(time=False, auto=False, range=(0.5, 1.5)), "y": up.Scale(auto=False, range=(-1.0, 0.0))},
        axes=axes("kept run", "log10 p"),
        legend=up.Legend(show=False),
        height=240,
    )


def _y_range(values: list[float]) -> tuple[float, float]:
    """A padded range covering ``values`` (log10 p; finite), at least 1 decade tall; (-1, 0) without values."""
    if not values:
        return (-1.0, 0.0)
    lo, hi = min(values), max(values)
    pad = max(0.25, 0.08 * (hi - lo))
    if hi - lo < 1.0:
        mid = 0.5 * (lo + hi)
        lo, hi = mid - 0.5, mid + 0.5
    return (lo - pad, hi + pad)


def tick_label(p: RunPoint) -> str:
    """The x tick of a run: ``run 3`` and, on a second line, its metric, ``p <`` (a bound) or ``no estimate``."""
    r = p.record
    second = f"({r.config.metric})"
    if p.log10_bound is not None:
        second = "p < bound"
    elif p.log10_mu is None:
        second = "no estimate"
    return f"run {r.run_id}\n{second}"


def fill_estimate_plot(plot: viser.GuiUplotHandle, runs: list[PanelRun]) -> list[str]:
    """Draw ``runs`` (the kept runs, in order) on ``plot``; the notes of the runs drawn only in part or not at all.

    x: run k at position k (1-based, ticks by :func:`tick_label`); y: log10 of a probability. Per run the series of
    its interval's caps and line and its mu_hat dot (or its lower bound and a line to the top where its weights back
    no interval, or its upper bound and a dashed line down where it has no failure), then the exact answer
    (:data:`EXACT`) or reference (:data:`REFERENCE`) as a bar across it; each series is nan away from the offsets
    :data:`_OFFSETS` it draws."""
    if not runs:
        return []
    points = [run_point(r) for r in runs]
    n = len(points)
    x = (np.arange(1, n + 1, dtype=np.float64)[:, None] + _OFFSETS[None, :]).ravel()
    width = _OFFSETS.size

    def column(i: int, where: slice | int, value: float) -> np.ndarray:
        y = np.full(x.size, np.nan, dtype=np.float64)
        y[i * width : (i + 1) * width][where] = value
        return y

    def line(i: int, bottom: float, top: float) -> np.ndarray:
        y = column(i, _BOTTOM, bottom)
        y[i * width + _TOP] = top
        return y

    shown = [
        v
        for p in points
        for v in (p.log10_mu, p.log10_lo, p.log10_hi, p.log10_bound, p.log10_exact, p.log10_reference)
        if v is not None
    ]
    y_lo, y_hi = _y_range(shown)
    no_points: up.Series_Points = {"show": False}
    series: list[up.Series] = [up.Series(label="run")]
    data: list[np.ndarray] = [x]
    for i, p in enumerate(points):
        colour = run_colour(p.record.run_id)
        name = p.record.short_label
        if p.log10_mu is not None and (p.log10_hi is not None or p.bound_only):
            bottom = p.log10_lo if p.log10_lo is not None else y_lo  # an interval reaching 0: to the chart's bottom
            parts: tuple[tuple[str, np.ndarray | None], ...]
            if p.bound_only:  # a lower bound's cap, and a line to the chart's top: no upper bound from this run
                parts = (
                    ("95 % lower bound", column(i, _CAP, bottom) if p.log10_lo is not None else None),
                    ("no upper bound", line(i, bottom, y_hi)),
                )
            else:
                assert p.log10_hi is not None  # not bound_only: the condition above
                parts = (
                    ("95 % low", column(i, _CAP, bottom) if p.log10_lo is not None else None),
                    ("95 % high", column(i, _CAP, p.log10_hi)),
                    ("95 % interval", line(i, bottom, p.log10_hi)),
                )
            for label, values in parts:
                if values is not None:
                    series.append(up.Series(label=f"{name} {label}", stroke=colour, width=2, points=no_points))
                    data.append(values)
            series.append(
                up.Series(
                    label=f"{name} mu_hat",
                    stroke=colour,
                    width=0,
                    points={"show": True, "size": 11, "fill": colour, "stroke": colour},
                )
            )
            data.append(column(i, _BOTTOM, p.log10_mu))
        elif p.log10_bound is not None:
            series += [
                up.Series(label=f"{name} upper bound", stroke=colour, width=2, dash=(4, 3), points=no_points),
                up.Series(label=f"{name} below the bound", stroke=colour, width=1.5, dash=(4, 3), points=no_points),
            ]
            data += [column(i, _CAP, p.log10_bound), line(i, y_lo, p.log10_bound)]
    for i, p in enumerate(points):
        answers = (
            (EXACT, p.log10_exact, hex_colour(BLACK), None),
            (REFERENCE, p.log10_reference, hex_colour(REFERENCE_LINE), (6, 3)),
        )
        for label, value, stroke, dash in answers:
            if value is not None:
                extra: up.Series = {"dash": dash} if dash else {}
                series.append(
                    up.Series(
                        label=f"{p.record.short_label} {label}", stroke=stroke, width=2.5, points=no_points, **extra
                    )
                )
                data.append(column(i, _BAR, value))
    if len(series) == 1:  # nothing to draw yet: uPlot needs a y series
        series.append(up.Series(label="no estimate yet", stroke=hex_colour(BLACK)))
        data.append(np.full(x.size, np.nan, dtype=np.float64))
    drawn = any(p.log10_mu is not None or p.log10_bound is not None for p in points)
    plot.title = TITLE if drawn else "log10 mu_hat of each kept run (no final estimate yet)"
    plot.series = tuple(series)
    plot.data = tuple(data)
    x_axis, y_axis = axes("kept run", "log10 p")
    x_axis = up.Axis(
        **{**x_axis, "size": 48},
        splits=tuple(float(k) for k in range(1, n + 1)),
        values=tuple(tick_label(p) for p in points),
    )
    plot.axes = (x_axis, y_axis)
    # uPlot's auto-range breaks on nan: give both ranges explicitly
    plot.scales = {
        "x": up.Scale(time=False, auto=False, range=(0.5, n + 0.5)),
        "y": up.Scale(auto=False, range=(y_lo, y_hi)),
    }
    return [p.note for p in points if p.note]


RESULT_ROWS = ("mu_hat", "95 % interval", "failures", "ESS", "verdict", "status")
"""The result rows of the table, above the settings."""


def result_cells(record: PanelRun) -> list[str]:
    """The :data:`RESULT_ROWS` of ``record`` as text ("-" without a final estimate)."""
    fin = record.final.estimate if record.final is not None else None
    if fin is None:
        return ["-"] * (len(RESULT_ROWS) - 1) + [record.status]
    return [
        format_probability(fin.log_mu_hat),
        fin.interval_text(),
        f"{fin.n_failures}/{fin.n}",
        finite_or_dash(fin.ess, ".1f"),
        fin.verdict,
        record.status,
    ]


def result_table(runs: list[PanelRun], rows: tuple[str, ...] = RESULT_ROWS) -> tuple[str, str]:
    """HTML of a table of ``runs``, a column each: its head (each run's number in its colour) and the result ``rows``
    (some of :data:`RESULT_ROWS`, :func:`result_cells`)."""
    head = "".join(
        f'<th style="color:{run_colour(r.run_id)}">run {r.run_id}{" (pinned)" if r.pinned else ""}</th>' for r in runs
    )
    cells = [result_cells(r) for r in runs]
    body = "".join(
        f'<tr><th style="text-align:left">{label}</th>'
        + "".join(f"<td>{html.escape(c[RESULT_ROWS.index(label)])}</td>" for c in cells)
        + "</tr>"
        for label in rows
    )
    return head, body


def differing_settings(runs: list[PanelRun]) -> tuple[list[tuple[str, list[Any]]], int]:
    """``(label, [value per run])`` of each setting whose values differ between ``runs`` (:func:`settings_of`'s order,
    a method of one's own's settings included), and how many settings are the same in every run."""
    rows = settings_of([r.config for r in runs])
    differ = [(label, values) for _, label, values in rows if len({repr(v) for v in values}) > 1]
    return differ, len(rows) - len(differ)


def answer_lines(runs: list[PanelRun]) -> list[str]:
    """What the chart's bars are: ``black bars: the exact answer 1.984e-15 (runs 1, 2)``, one line per answer, and the
    same for plain Monte Carlo references (grey, dashed)."""
    by_answer: dict[str, list[str]] = {}
    for r in runs:
        with r.lock:
            exact, reference = r.exact_log_p, r.reference
        if exact is not None and math.isfinite(exact):
            key = f"black bar: the exact answer {format_probability(exact)}"
        elif reference is not None:
            key = f"grey dashed bar: the plain Monte Carlo reference {reference.text()}"
        else:
            continue
        by_answer.setdefault(key, []).append(str(r.run_id))
    return [f"{key} (run{'s' * (len(ids) > 1)} {', '.join(ids)})" for key, ids in by_answer.items()]


def compare_html(runs: list[PanelRun], notes: list[str] | None = None) -> str:
    """The *Compare* tab's text under its chart: ``notes`` (runs drawn in part or not at all), the runs' labels in
    their colours, and a table of the result rows and the settings that differ between ``runs``."""
    if not runs:
        return ""
    head, body = result_table(runs)
    differ, same = differing_settings(runs)
    for label, values in differ:
        body += (
            f'<tr style="font-weight:bold"><th style="text-align:left">{html.escape(label)}</th>'
            + "".join(f"<td>{html.escape(setting_value(v))}</td>" for v in values)
            + "</tr>"
        )
    if len(runs) < 2:
        hidden = f"one run kept: its {same} settings are listed under Runs"
    elif differ:
        which = "the 1 setting that differs" if len(differ) == 1 else f"the {len(differ)} settings that differ"
        hidden = f"only {which} between the runs; {same} identical settings hidden (all under Runs)"
    else:
        hidden = f"the runs have the same settings: all {same} hidden (listed under Runs)"
    table = (
        TABLE_STYLE + '<table class="pemviz-table" style="width:100%; font-size:0.75em; white-space:nowrap">'
        f'<tr><th style="text-align:left">setting</th>{head}</tr>{body}</table>'
    )
    lines = [*answer_lines(runs), *(notes or ())]
    note_html = "".join(f'<div style="font-size:0.75em; color:#555">{html.escape(n)}</div>' for n in lines)
    labels = "".join(
        f'<div style="color:{run_colour(r.run_id)}; font-size:0.8em">{html.escape(r.label)}</div>' for r in runs
    )
    return (
        f'<div style="margin:0 0.6em 0.5em; overflow-x:auto">{note_html}{labels}{table}'
        f'<div style="font-size:0.75em; color:#777">{html.escape(hidden)}</div></div>'
    )
