"""The *ODD* tab of the plots panel: after a run over an operating design domain, where p_ODD comes from: per drawn
parameter a chart of log10 p(failure | bin) with its interval, a table of every bin, and the region that carries
most of p_ODD (:class:`pemviz.core.odd.OddMap`)."""

from __future__ import annotations

import html
import math

import numpy as np
import viser
import viser.uplot as up

from pemviz.app.captions import add_chart, set_chart, show_chart
from pemviz.app.html import AMBER, GREY, TABLE_STYLE, VERDICT_COLOURS, box
from pemviz.app.plots import LEGEND, axes
from pemviz.app.runs import PanelRun
from pemviz.core.estimate import format_probability
from pemviz.core.odd import MapBin, OddMap, PairMap, cell_text
from pemviz.sinks import colours as C
from pemviz.sinks.colours import css, hex_colour

MAX_CHARTS = 3
"""Drawn parameters charted (the table lists every one)."""

NO_ODD = (
    "No operating design domain in this run. Give a scenario parameter a distribution instead of a value in the "
    "Experiment tab's folder of scenario parameters (e.g. <code>~uniform(19.5, 21.5)</code>, <code>~normal(12.3, "
    "0.4)</code>, <code>~choice(4, 8)</code>): each rollout then draws its own, the run estimates p over the "
    "ODD, and this tab shows where it comes from."
)


def _log10(x: float) -> float:
    return x / math.log(10) if math.isfinite(x) else math.nan


def bin_points(bins: list[MapBin]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(x, log10 p, log10 low, log10 high)`` of ``bins`` (one parameter's), float64 ``[B]`` each: x the bin's
    middle (a choice's value), nan where a bin has no failure or its interval no such end."""
    x = np.array([(b.lo + b.hi) / 2 for b in bins], dtype=np.float64)
    p = np.array([_log10(b.estimate.log_mu_hat) if b.estimate.n_failures else math.nan for b in bins])
    lo = np.array([_log10(b.estimate.shown_log_ci[0]) for b in bins])
    hi = np.array([_log10(b.estimate.shown_log_ci[1]) for b in bins])
    return x, p, lo, hi


def odd_table_html(m: OddMap) -> str:
    """Every bin of ``m`` as an HTML table, with the region that carries most of p_ODD above it."""
    top = m.top()
    head = f"<b>p over the ODD</b> ({html.escape(m.odd.text())}), from the final stage's {m.rollouts:,} rollouts. " + (
        f"Most of p_ODD: <b>{html.escape(top.label)}</b> ({100 * top.share:.0f} % of it, P(bin) "
        f"{top.probability:.2f})."
        if top is not None
        else "No failure in any bin."
    )
    rows = []
    for b in m.bins:
        e = b.estimate
        colour = VERDICT_COLOURS.get(e.verdict, GREY)
        p = format_probability(e.log_mu_hat) if e.n_failures else "no failure"
        rows.append(
            f"<tr><td style='text-align:left'>{html.escape(b.label)}</td><td>{b.probability:.2f}</td><td>{p}</td>"
            f"<td>{html.escape(e.interval_text())}</td><td style='color:{colour}'>{html.escape(e.verdict)}</td>"
            f"<td>{100 * b.share:.1f} %</td></tr>"
        )
    table = (
        f"{TABLE_STYLE}<table class='pemviz-table' style='font-size:0.8em;margin:0 0.6em'><tr>"
        "<th style='text-align:left'>bin</th><th>P(bin)</th><th>p(failure | bin)</th><th>95 % interval</th>"
        f"<th>verdict</th><th>share</th></tr>{''.join(rows)}</table>"
    )
    return box(head, AMBER) + table


def pair_html(pair: PairMap) -> str:
    """The heat map of the first two parameters as an HTML table: a cell per pair of bins with p(failure | cell)
    (``>=`` a lower bound where its weights back no interval, ``-`` without failure), shaded by log10 p from the
    smallest cell's (light) to the largest's (dark red); the cell that carries most of p_ODD named under it."""
    x, y = pair.names
    grid = pair.log10_p()
    shown = grid[np.isfinite(grid)]
    lo, hi = (float(shown.min()), float(shown.max())) if shown.size else (0.0, 0.0)
    head = "".join(f"<th>{pair.x_edges[a]:.3g}-{pair.x_edges[a + 1]:.3g}</th>" for a in range(len(pair.x_probs)))
    rows = []
    for b, row in enumerate(pair.cells):
        tds = []
        for a, e in enumerate(row):
            v = grid[b, a]
            f = 0.15 + 0.85 * ((v - lo) / (hi - lo) if hi > lo else 1.0) if math.isfinite(v) else 0.0
            tds.append(f"<td style='background:{css(C.RED, f)}'>{html.escape(cell_text(e))}</td>")
        label = f"{pair.y_edges[b]:.3g}-{pair.y_edges[b + 1]:.3g}"
        rows.append(f"<tr><th style='text-align:left'>{label}</th>{''.join(tds)}</tr>")
    top = pair.top()
    said = (
        f"Most of p_ODD in the pair: <b>{html.escape(pair.cell_label(*top))}</b> "
        f"({100 * pair.shares[top[1], top[0]]:.0f} % of it)."
        if top is not None
        else "No failure in any cell."
    )
    return (
        f"<div style='margin:0.6em 0.6em 0.2em;font-size:0.85em'><b>p(failure | cell)</b>: rows {html.escape(y)}, "
        f"columns {html.escape(x)}. {said}</div>"
        f"{TABLE_STYLE}<table class='pemviz-table' style='font-size:0.75em;margin:0 0.6em'>"
        f"<tr><th></th>{head}</tr>{''.join(rows)}</table>"
    )


class OddTab:
    """The *ODD* tab: a note, :data:`MAX_CHARTS` charts (hidden until a run over an ODD fills them) and the table."""

    def __init__(self, client: viser.ClientHandle) -> None:
        self.client = client

    def build(self) -> None:
        """Add the tab's note, charts and table to the open container of ``client.gui``."""
        gui = self.client.gui
        self.note = gui.add_html(box(NO_ODD, GREY))
        self.charts = [
            add_chart(
                gui,
                data=(np.arange(2, dtype=np.float64), np.full(2, np.nan)),
                series=(up.Series(label="parameter"), up.Series(label="p", stroke=hex_colour(C.BLACK))),
                title="log10 p(failure | bin)",
                scales={"x": up.Scale(time=False, auto=True), "y": up.Scale(auto=True)},
                axes=axes("parameter", "log10 p"),
                legend=LEGEND,
                height=220,
                visible=False,
            )
            for _ in range(MAX_CHARTS)
        ]
        self.table = gui.add_html("")

    def fill(self, record: PanelRun | None) -> None:
        """Show ``record``'s map (the newest run's), or the note where it has none (yet)."""
        final = record.final if record is not None else None
        m = final.odd_map if final is not None else None
        if m is None or not m.bins:
            self.note.content = box(NO_ODD, GREY)
            self.note.visible = True
            self.table.content = ""
            for chart in self.charts:
                show_chart(chart, False)
            return
        self.note.visible = False
        self.table.content = odd_table_html(m) + (pair_html(m.pair) if m.pair is not None else "")
        names = list(m.odd.names)
        for i, chart in enumerate(self.charts):
            show_chart(chart, i < len(names))
            if i < len(names):
                self._chart(chart, names[i], [b for b in m.bins if b.name == names[i]])

    @staticmethod
    def _chart(chart: viser.GuiUplotHandle, name: str, bins: list[MapBin]) -> None:
        x, p, lo, hi = bin_points(bins)
        shown = np.concatenate([v[np.isfinite(v)] for v in (p, lo, hi)])
        y_lo, y_hi = (float(shown.min()) - 0.3, float(shown.max()) + 0.3) if shown.size else (-1.0, 0.0)
        pad = 0.5 * float(np.min(np.diff(x))) if x.size > 1 else 0.5
        dot: up.Series_Points = {"show": True, "size": 7}
        set_chart(
            chart,
            f"log10 p(failure | {name} bin)",
            f"the failure probability of each bin of {name} (log10), with its 95 % interval (blue: low end, red: high)",
        )
        chart.series = (
            up.Series(label=name),
            up.Series(label="p", stroke=hex_colour(C.BLACK), width=2, points=dot),
            up.Series(label="95 % low", stroke=hex_colour(C.BLUE), width=1, dash=(4, 3), points={"show": True}),
            up.Series(label="95 % high", stroke=hex_colour(C.RED), width=1, dash=(4, 3), points={"show": True}),
        )
        chart.data = (x, p, lo, hi)
        chart.scales = {
            "x": up.Scale(time=False, auto=False, range=(float(x.min()) - pad, float(x.max()) + pad)),
            "y": up.Scale(auto=False, range=(y_lo, y_hi)),
        }
        chart.axes = axes(name, "log10 p")
