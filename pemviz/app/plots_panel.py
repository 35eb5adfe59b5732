"""The plots panel (left) of a :class:`pemviz.app.session.Session`: *Live*, *Explain*
(:class:`pemviz.app.explain_tab.ExplainTab`), *Compare* and *ODD* (:class:`pemviz.app.odd_tab.OddTab`)."""

from __future__ import annotations

import viser

from pemviz.app import charts, compare, feature_chart, plots
from pemviz.app.captions import show_chart
from pemviz.app.explain_tab import ExplainTab
from pemviz.app.odd_tab import OddTab
from pemviz.app.runs import PanelRun
from pemviz.core.estimate import format_probability


class PlotsPanel:
    """The plots panel: owns the panel, its *Live* and *Compare* charts and HTML and its *ODD* tab; its *Explain* tab
    is the :class:`pemviz.app.explain_tab.ExplainTab` it is given."""

    def __init__(self, client: viser.ClientHandle, explain: ExplainTab) -> None:
        self.client, self.explain = client, explain
        self.odd = OddTab(client)

    def build(self) -> None:
        """Add the panel, docked left, with its three tabs to ``client.gui``."""
        gui = self.client.gui
        panel = gui.add_panel()
        with panel.add_tab("Live", viser.Icon.CHART_LINE):
            self.marginal_note = gui.add_html(charts.marginal_note(None))  # why the q(detect) charts are hidden
            self.marginal_plots = charts.marginal_plots(gui)
            self.feature_plot = feature_chart.feature_plot(gui)  # a state proposal's q(detect) over a feature
            self.stage_plots = {key: plots.stage_plot(gui, title, y) for key, title, y in plots.STAGE_PLOTS}
        with panel.add_tab("Explain", viser.Icon.ZOOM_QUESTION):
            self.explain.build()
        with panel.add_tab("Compare", viser.Icon.A_B):
            self.compare_estimates = compare.estimate_plot(gui)
            self.compare_html = gui.add_html("")
            self.compare_html_ref = gui.add_html(
                '<div style="margin:0 0.6em; font-size:0.8em; color:#555">Reference-state curves: q(detect | gap) with '
                "the proposal's other inputs (speeds, pending brake) held at the start state; in a scene of several "
                "objects, q(detect | range) of car 0 straight ahead in the ego's lane. The Live tab shows what each "
                "sampler did over the states its rollouts visited. One chart per kept run.</div>"
            )
            self.compare_plots = [
                plots.curve_plot(gui, f"slot {i + 1}: no run yet", height=190, visible=False) for i in range(4)
            ]
        with panel.add_tab("ODD", viser.Icon.MAP):
            self.odd.build()
        self.panel = panel
        panel.dock_left()
        panel.set_width(460)

    def fill(self, runs: list[PanelRun], record: PanelRun | None) -> None:
        """Redraw *Live* for ``record`` (the newest run) and ``runs`` (the kept ones) and *Compare*'s proposal curves
        of ``runs``."""
        with self.client.atomic():
            if record is not None:
                charts.fill_marginal_plots(self.marginal_plots, record, self.marginal_note)
            feature_chart.fill_feature_plot(self.feature_plot, record)
            for i, plot in enumerate(self.compare_plots):
                show_chart(plot, i < len(runs) and runs[i].curve_grid_m.size > 0)  # a slot without a run is hidden
                if i < len(runs):
                    r = runs[i]
                    fin = r.final.estimate if r.final is not None else None
                    mu = f", mu_hat {format_probability(fin.log_mu_hat)}" if fin is not None else ""
                    ref = (
                        "the proposal's reference-state q(detect) after each stage"
                        if r.config.adaptive.reads_state
                        else ""
                    )
                    plots.fill_curve_plot(plot, r, f"{r.short_label}{mu}", ref)
            self.odd.fill(record)
            for key, plot in self.stage_plots.items():
                plots.fill_stage_plot(plot, key, runs)
                if key == "log10_mu_hat":
                    charts.fill_mu_hat_plot(plot, runs)

    def fill_compare(self, runs: list[PanelRun]) -> None:
        """Redraw *Compare*'s estimates and settings of the kept ``runs``."""
        notes = compare.fill_estimate_plot(self.compare_estimates, runs)
        self.compare_html.content = compare.compare_html(runs, notes)
