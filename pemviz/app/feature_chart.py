"""The *Live* chart of what a state-dependent proposal does to a feature (``method = "state"``): the newest stage's
q(detect) against the PEM's p(detect) over the feature that moved it most
(:func:`pemviz.core.feature_view.stage_feature_curve`). Hidden for a run whose sampler reads no state."""

from __future__ import annotations

import numpy as np
import viser
import viser.uplot as up

from pemviz.app.captions import MAX_TITLE, add_chart, set_chart, show_chart
from pemviz.app.plots import LEGEND, axes
from pemviz.app.runs import PanelRun
from pemviz.core.feature_view import PEM_SERIES, Q_SERIES
from pemviz.sinks.colours import BLACK, css, hex_colour, stage_rgb, stage_span


def feature_plot(gui: viser.GuiApi) -> viser.GuiUplotHandle:
    """The empty feature chart, hidden until a run has a feature curve (:func:`fill_feature_plot`)."""
    x = np.linspace(0.0, 1.0, 2)
    return add_chart(
        gui,
        data=(x, np.full(2, np.nan), np.full(2, np.nan)),
        series=(
            up.Series(label="feature"),
            up.Series(label=Q_SERIES, stroke=hex_colour(BLACK)),
            up.Series(label=PEM_SERIES, stroke=hex_colour(BLACK)),
        ),
        title="q(detect) vs PEM over a feature",
        scales={"x": up.Scale(time=False, auto=True), "y": up.Scale(auto=False, range=(0.0, 1.04))},
        axes=axes("feature", "mean p(detect)"),
        legend=LEGEND,
        height=210,
        visible=False,
    )


def fill_feature_plot(plot: viser.GuiUplotHandle, record: PanelRun | None) -> None:
    """The newest stage's curve of ``record`` (:attr:`PanelRun.feature_curves`): its mean q(detect) (the stage's
    colour) and the PEM's mean p(detect) (black) per bin of the feature (its unit, the mean value of each bin),
    titled with the feature's name, the caption saying the stage, the effect and the rows; hidden without one."""
    curves = record.feature_curves if record is not None else {}
    show_chart(plot, bool(curves))
    if not curves or record is None:
        return
    stage = max(curves)
    kind, curve = curves[stage]
    name = "final batch" if kind == "final" else f"stage {stage}"
    title = f"q(detect) vs PEM over {curve.name}"
    colour = css(stage_rgb(stage, stage_span(record.plan)))
    caption = (
        f"{name}: the feature that moved the proposal's log-odds most from the PEM's, {curve.effect:.2f} nats across "
        f"one standard deviation; mean q(detect) and PEM p(detect) per bin of the {int(curve.n_rows.sum()):,} object "
        "rows the stage drew (a bin per value, or 20 quantile bins)"
    )
    set_chart(plot, title if len(title) <= MAX_TITLE else title[: MAX_TITLE - 3] + "...", caption)
    plot.series = (
        up.Series(label=curve.name),
        up.Series(label=Q_SERIES, stroke=colour, width=2),
        up.Series(label=PEM_SERIES, stroke=hex_colour(BLACK), width=2),
    )
    plot.data = (np.asarray(curve.x), np.asarray(curve.q_detect), np.asarray(curve.p_detect))
    lo, hi = float(curve.x[0]), float(curve.x[-1])
    pad = 0.03 * (hi - lo) if hi > lo else 0.5
    plot.scales = {
        "x": up.Scale(time=False, auto=False, range=(lo - pad, hi + pad)),
        "y": up.Scale(auto=False, range=(0.0, 1.04)),
    }
    plot.axes = axes(curve.name, "mean p(detect)")
