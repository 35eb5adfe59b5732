"""The *Runs* tab of a :class:`pemviz.app.session.Session`: kept runs, the run chosen for *Rollouts* and *Explain*,
pin and export."""

from __future__ import annotations

import html
import threading
from pathlib import Path

import viser

from pemviz.app import plots
from pemviz.app._viser_compat import set_value
from pemviz.app.compare import result_table
from pemviz.app.form import NOT_HELD, default_settings, setting_value, settings_of
from pemviz.app.host import PanelHost
from pemviz.app.html import GREEN, GREY, RED, TABLE_STYLE, box, display_path
from pemviz.app.plots_panel import PlotsPanel
from pemviz.app.rollouts_tab import RolloutsTab
from pemviz.app.runs import PanelRun, export_path, export_run, keep_runs


class RunsTab:
    """The *Runs* tab: owns the kept runs (:attr:`runs`, oldest first), its table, the run chosen (which *Rollouts*
    lists, through the :class:`pemviz.app.rollouts_tab.RolloutsTab` it is given), pin / unpin and the export of a
    run; refreshing it refreshes the *Compare* tab's estimates (:class:`pemviz.app.plots_panel.PlotsPanel`)."""

    def __init__(
        self,
        client: viser.ClientHandle,
        app: PanelHost,
        lock: threading.RLock,
        rollouts_tab: RolloutsTab,
        plots_panel: PlotsPanel,
    ) -> None:
        self.client, self.app, self.lock, self.rollouts_tab = client, app, lock, rollouts_tab
        self.plots_panel = plots_panel
        self.runs: list[PanelRun] = []
        """The kept runs (at most 4; :func:`pemviz.app.runs.keep_runs`)."""
        self.last_export: Path | None = None

    def build(self) -> None:
        """Add the table, the run chosen, Pin and the export to the tab open in ``client.gui``."""
        gui = self.client.gui
        self.runs_html = gui.add_html(box("No runs yet.", GREY))
        gui.add_markdown(
            "Up to 4 runs are kept; a new run drops stopped runs first, then the oldest finished one; pinned runs stay."
        )
        self.run_choice = gui.add_dropdown(
            "kept run", ("(no run yet)",), initial_value="(no run yet)", hint="the run to pin or export"
        )
        self.pin_button = gui.add_button("Pin", icon=viser.Icon.PIN, disabled=True)
        with gui.add_folder("export to rerun (.rrd)"):
            self.export_name = gui.add_text("export name", "run")
            self.export_button = gui.add_button("Export chosen run", icon=viser.Icon.DOWNLOAD, disabled=True)
            self.export_html = gui.add_html("")
        self.run_choice.on_update(lambda _: self._on_run_choice())
        self.pin_button.on_click(lambda _: self._toggle_pin())
        self.export_button.on_click(self._on_export)

    def keep(self, record: PanelRun) -> None:
        """Keep a new run (dropping the runs :func:`pemviz.app.runs.keep_runs` drops) and choose it."""
        self.runs = keep_runs(self.runs, record)
        with self.client.atomic():
            self.run_choice.options = tuple(r.label for r in self.runs)
            set_value(self.run_choice, record.label)

    def kept_run(self, run_id: int) -> PanelRun:
        for r in self.runs:
            if r.run_id == run_id:
                return r
        raise ValueError(f"run {run_id} is not kept in this tab")

    def set_pinned(self, run_id: int, pinned: bool) -> None:
        self.kept_run(run_id).pinned = pinned
        self.refresh()

    def export(self, run_id: int, name: str) -> Path:
        """Write a kept run to ``recordings_dir / <sanitised name>.rrd``.

        Raises:
            ValueError: the run is not kept or has no events, or an unusable name."""
        record = self.kept_run(run_id)
        if not record.events:
            raise ValueError(f"{record.short_label} has nothing to export yet")
        path = export_path(self.app.recordings_dir, name)
        export_run(record, path)
        self.last_export = path
        return path

    def refresh(self) -> None:
        """Redraw the table of kept runs, the *Compare* tab's estimates and the list of runs to choose from."""
        with self.lock:
            runs = list(self.runs)
        if not runs:
            return
        head, body = result_table(runs, ("mu_hat", "failures", "verdict", "status"))
        defaults = [default_settings(r.config) for r in runs]
        for name, label, values in settings_of([r.config for r in runs]):
            away = (v != d.get(name, NOT_HELD) for v, d in zip(values, defaults, strict=True))
            differs = len({repr(v) for v in values}) > 1 or any(away)
            style = "font-weight:bold" if differs else "color:#777"
            body += (
                f'<tr style="{style}"><th style="text-align:left">{html.escape(label)}</th>'
                + "".join(f"<td>{html.escape(setting_value(v))}</td>" for v in values)
                + "</tr>"
            )
        table = (
            TABLE_STYLE + '<table class="pemviz-table" style="width:100%; font-size:0.75em; white-space:nowrap">'
            f'<tr><th style="text-align:left">setting</th>{head}</tr>{body}</table>'
        )
        block = (
            '<div style="margin:0 0.6em 0.5em; overflow-x:auto">'
            + "".join(
                f'<div style="color:{plots.run_colour(r.run_id)}; font-size:0.8em">{html.escape(r.label)}</div>'
                for r in runs
            )
            + table
            + "<div style='font-size:0.75em;color:#777'>bold: differs from the defaults or between runs</div>"
            "</div>"
        )
        with self.client.atomic():
            self.runs_html.content = block
            self.plots_panel.fill_compare(runs)
            options = tuple(r.label for r in runs)
            current = self.run_choice.value
            self.run_choice.options = options
            if current not in options:
                set_value(self.run_choice, options[-1])
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
            set_value(self.export_name, f"run{r.run_id}-{r.config.metric}")
            self.rollouts_tab.list_run(r)

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
