"""The *Runs* tab of a :class:`pemviz.app.session.Session`: kept runs, the run chosen for *Rollouts* and *Explain*,
pin and export."""

from __future__ import annotations

import dataclasses
import html

import viser

from pemviz.app import compare, plots
from pemviz.app.html import GREEN, RED, TABLE_STYLE, box, display_path
from pemviz.app.form import setting_name, setting_value
from pemviz.app.runs import PanelRun
from pemviz.config import ExperimentConfig
from pemviz.core.estimate import format_probability


class RunsTab:
    """The *Runs* tab's part of a session (a mixin of :class:`pemviz.app.session.Session`)."""

    def _refresh_runs(self) -> None:
        with self.lock:
            runs = list(self.runs)
        if not runs:
            return
        names = [f.name for f in dataclasses.fields(ExperimentConfig)]
        head = "".join(
            f'<th style="color:{plots.run_colour(r.run_id)}">run {r.run_id}{" (pinned)" if r.pinned else ""}</th>'
            for r in runs
        )

        def result(r: PanelRun) -> list[str]:
            fin = r.final.estimate if r.final is not None else None
            return [
                format_probability(fin.log_mu_hat) if fin else "-",
                f"{fin.n_failures}/{fin.n}" if fin else "-",
                fin.verdict if fin else "-",
                r.status,
            ]

        rows = [("mu_hat", "failures", "verdict", "status")]
        cells = [result(r) for r in runs]
        body = "".join(
            f'<tr><th style="text-align:left">{label}</th>' + "".join(f"<td>{html.escape(c[i])}</td>" for c in cells)
            + "</tr>"
            for i, label in enumerate(rows[0])
        )  # fmt: skip
        defaults = ExperimentConfig()
        for name in names:
            values = [getattr(r.config, name) for r in runs]
            differs = any(v != getattr(defaults, name) for v in values) or len({repr(v) for v in values}) > 1
            style = "font-weight:bold" if differs else "color:#777"
            body += (
                f'<tr style="{style}"><th style="text-align:left">{html.escape(setting_name(name))}</th>'
                + "".join(f"<td>{html.escape(setting_value(v))}</td>" for v in values)
                + "</tr>"
            )
        table = (
            TABLE_STYLE + '<table class="pemviz-table" style="width:100%; font-size:0.75em; white-space:nowrap">'
            f'<tr><th style="text-align:left">setting</th>{head}</tr>{body}</table>'
        )
        block = (
            '<div style="margin:0 0.6em 0.5em; overflow-x:auto">'
            + "".join(f'<div style="color:{plots.run_colour(r.run_id)}; font-size:0.8em">{html.escape(r.label)}</div>'
                      for r in runs)
            + table + "<div style='font-size:0.75em;color:#777'>bold: differs from the defaults or between runs</div>"
            "</div>"
        )  # fmt: skip
        with self.client.atomic():
            self.runs_html.content = block
            notes = compare.fill_estimate_plot(self.compare_estimates, runs)
            self.compare_html.content = compare.compare_html(runs, notes)
            options = tuple(r.label for r in runs)
            current = self.run_choice.value
            self.run_choice.options = options
            if current not in options:
                self.run_choice.value = options[-1]
            self._on_run_choice()

    def chosen_run(self) -> PanelRun | None:
        for r in self.runs:
            if r.label == self.run_choice.value:
                return r
        return None

    def _on_run_choice(self) -> None:
        r = self.chosen_run()
        self.pin_button.disabled = r is None
        self.export_button.disabled = r is None or not r.events
        if r is not None:
            self.pin_button.label = "Unpin" if r.pinned else "Pin"
            self.export_name.value = f"run{r.run_id}-{r.config.metric}"
            self._list_run(r)

    def _list_run(self, record: PanelRun) -> None:
        """Rollouts and Explain follow ``record`` (the run chosen under Runs): its rollouts, and its most likely
        failure explained once it has ended."""
        with self.lock:
            if record is self.listed:
                return
            self.listed = record
            self._set_rollouts(record)
            if record.done:
                self._show_default_rollout(record)
                if self.shown_record is not record:
                    self._clear_scene(f"{record.short_label} ({record.status}) has no rollout to show")
            else:
                self._clear_scene(f"{record.short_label} is going: its rollouts appear in the Rollouts tab")

    def _toggle_pin(self) -> None:
        r = self.chosen_run()
        if r is not None:
            self.set_pinned(r.run_id, not r.pinned)

    def _on_export(self, event: viser.GuiEvent) -> None:
        r = self.chosen_run()
        try:
            if r is None:
                raise ValueError("no run chosen")
            path = self.export(r.run_id, self.export_name.value)
        except (ValueError, OSError) as exc:
            self.export_html.content = box(f"<b>Export refused.</b> {html.escape(str(exc))}", RED)
            return
        shown = display_path(path)
        size_kb = path.stat().st_size / 1024
        self.export_html.content = box(
            f"Saved {html.escape(r.short_label)} to <b>{html.escape(shown)}</b> ({size_kb:.0f} KB). Open it with "
            f"<code>rerun {html.escape(shown)}</code>; the download link is in this tab's notification.",
            GREEN,
        )
        self.client.send_file_download(path.name, path.read_bytes(), save_immediately=False)

    # == rollouts, explanation and the 3D scene =======================================================
