"""Charts with a short title (at most :data:`MAX_TITLE` characters) and their explanation (what is ringed, off
scale, left out; units and abbreviations) in a caption below them, shown and hidden with them."""

from __future__ import annotations

import html
from typing import Any

import viser

MAX_TITLE = 60
"""The longest chart title (characters): a few words, one line of the panel's chart column."""

LOG_W_CAPTION = (
    "log w: the rollout's importance log-weight up to each time, log p - log q summed over its steps (nats): p the "
    "PEM's probability of what the detector did, q the sampler's. mu_hat is the sum of w = exp(log w) over the "
    "failures divided by the number of rollouts: a failure with log w -35 adds e^-35 (6e-16) / N."
)
"""What the *Explain* tab's log-weight chart and its rollout header call ``log w``."""

_STYLE = "font-size:0.78em; color:#555; margin:-4px 6px 6px 6px; line-height:1.3"


def _html(text: str, chart: Any) -> str:
    """The caption's HTML: ``text`` escaped in a ``pemviz-caption`` div naming its chart's element (its uuid: the key
    of the chart among the page's uPlot charts)."""
    if not text:
        return ""
    uuid = html.escape(str(getattr(getattr(chart, "_impl", None), "uuid", "")))
    return f'<div class="pemviz-caption" data-chart="{uuid}" style="{_STYLE}">{html.escape(text)}</div>'


def add_chart(gui: viser.GuiApi, *args: Any, title: str, caption: str = "", visible: bool = True, **kw: Any) -> Any:
    """``gui.add_uplot(*args, title=title, visible=visible, **kw)`` and, right below it, its caption (plain text,
    escaped; an empty caption is not shown). Returns the chart's handle (:func:`set_chart`, :func:`show_chart`)."""
    plot: Any = gui.add_uplot(*args, title=title, visible=visible, **kw)
    plot.caption_text = caption
    plot.caption_handle = gui.add_html(  # right after the chart, whatever is inserted after it later
        _html(caption, plot), visible=visible and bool(caption), order=float(plot.order) + 0.001
    )
    return plot


def set_chart(plot: Any, title: str, caption: str | None = None) -> None:
    """Set the chart's title (at most :data:`MAX_TITLE` characters: the caption is for the rest) and, unless
    ``caption`` is None, its caption text (``''``: none shown; :attr:`caption_text` of the handle)."""
    plot.title = title
    if caption is None:
        return
    plot.caption_text = caption
    handle = getattr(plot, "caption_handle", None)
    if handle is not None:
        handle.content = _html(caption, plot)
        handle.visible = bool(plot.visible) and bool(caption)


def show_chart(plot: Any, visible: bool) -> None:
    """Show or hide the chart with its caption."""
    plot.visible = visible
    handle = getattr(plot, "caption_handle", None)
    if handle is not None:
        handle.visible = visible and bool(getattr(plot, "caption_text", ""))
