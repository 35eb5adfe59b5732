"""One browser client's panel: its own form, runs, Stop, plots, rollout explanation and 3D scene, built in that
client's own ``client.gui`` / ``client.scene``, so two tabs never share a form, a run or a Stop button
(docs/panel.md)."""

from __future__ import annotations

import threading
from typing import Any, ClassVar

import viser

from pemviz.app.experiment_tab import ExperimentTab
from pemviz.app.explain_tab import ExplainTab
from pemviz.app.host import PanelHost
from pemviz.app.plots_panel import PlotsPanel
from pemviz.app.rollouts_tab import RolloutsTab
from pemviz.app.run_control import RunControl
from pemviz.app.runs_tab import RunsTab
from pemviz.app.scene_view import SceneView
from pemviz.sinks import colours as C

__all__ = ["PanelHost", "Session"]


class Session:
    """The panel of one browser client: builds and wires its parts (:attr:`control`, :attr:`form`,
    :attr:`rollouts_tab`, :attr:`runs_tab`, :attr:`scene`, :attr:`explain`, :attr:`plots_panel`), each owning its
    state and GUI handles."""

    def __init__(self, app: PanelHost, client: viser.ClientHandle) -> None:
        self.app = app
        self.client = client
        self.drawing = app.drawing
        """The drawing object of the lane scene built first (:attr:`pemviz.app.panel.PanelApp.drawing`); the 3D view
        then draws the idle scene of the scenario chosen under *Experiment* (:meth:`SceneView.choose_scenario`)."""
        self.lock = threading.RLock()
        """One lock for every part: GUI callbacks run in a thread pool, the run in a worker thread."""
        self.explain = ExplainTab(client, self.drawing.panel_scene().strip_title)
        self.scene = SceneView(client, self.drawing, self.lock, self.explain)
        self.rollouts_tab = RolloutsTab(client, self.lock, self.scene)
        self.plots_panel = PlotsPanel(client, self.explain)
        self.runs_tab = RunsTab(client, app, self.lock, self.rollouts_tab, self.plots_panel)
        self.form = ExperimentTab(client, app)
        self.control = RunControl(
            client,
            app,
            self.lock,
            form=self.form,
            runs_tab=self.runs_tab,
            rollouts_tab=self.rollouts_tab,
            scene=self.scene,
            explain=self.explain,
            plots_panel=self.plots_panel,
        )
        self._build_gui()
        self.scene.build_scene()
        self.scene.choose_scenario(self.form.choices["scenario"].value)  # its idle scene
        self.control.validate()
        self.fields, self.choices, self.preset = self.form.fields, self.form.choices, self.form.preset
        self.run_choice, self.result_html = self.runs_tab.run_choice, self.control.result_html
        self.rollout_dropdown, self.rollout_order = self.rollouts_tab.rollout_dropdown, self.rollouts_tab.rollout_order
        self.step_slider, self.scene_html = self.scene.step_slider, self.scene.scene_html
        self.explain_html = self.explain.explain_html

    def _build_gui(self) -> None:
        gui = self.client.gui
        gui.configure_theme(control_width="large", show_share_button=False, brand_color=C.BLUE)
        gui.set_panel_label("pemviz")
        gui.add_markdown(
            "**pemviz**: the failure probability of a PEM-driven scenario (one car ahead of the ego, or several around "
            "it) by adaptive importance sampling (Innes & Ramamoorthy 2022). Set the experiment, press **Run**; this "
            "tab has its own runs."
        )
        self.control.build()
        tabs = gui.add_tab_group()
        with tabs.add_tab("Experiment", viser.Icon.SETTINGS):
            self.form.build(on_change=self.control.validate, on_scenario=self.scene.choose_scenario)
        with tabs.add_tab("Rollouts", viser.Icon.CAR):
            self.rollouts_tab.build()
            self.scene.build_controls()
        with tabs.add_tab("Runs", viser.Icon.CHART_LINE):
            self.runs_tab.build()
        self.tabs = tabs
        self.plots_panel.build()
        gui.main_panel.dock_right()

    # == what the server, the tests and the benchmarks call ============================================
    def stop_run(self) -> None:
        """Set this session's cancel token (the engine stops at its next check)."""
        self.control.stop_run()

    def wait_for_run(self, timeout: float | None = None) -> bool:
        """Wait up to ``timeout`` seconds for the run's worker; whether none is left running."""
        return self.control.wait_for_run(timeout)

    def close(self) -> None:
        """The client left: stop its run."""
        self.control.close()

    def tick(self) -> None:
        """Refresh the status line of a running run (:meth:`RunControl.tick`)."""
        self.control.tick()

    def play_tick(self) -> None:
        """Advance the playback by one step (:meth:`SceneView.play_tick`)."""
        self.scene.play_tick()

    # == the parts' state, read through the session ===================================================
    READ: ClassVar[dict[str, str]] = {
        **dict.fromkeys(("running", "record", "last_stop_latency_s"), "control"),
        **dict.fromkeys(("runs", "last_export"), "runs_tab"),
        **dict.fromkeys(("listed", "_rollout_labels"), "rollouts_tab"),
        **dict.fromkeys(("shown", "shown_record", "shown_step"), "scene"),
        **dict.fromkeys(("explanation", "objects_ex"), "explain"),
    }
    """The parts' state the session reads through, by name: ``session.record`` is ``session.control.record`` (the run
    the live plots show), ``session.shown`` ``session.scene.shown`` (the rollout shown), and so on."""

    def __getattr__(self, name: str) -> Any:
        part = Session.READ.get(name)
        if part is None:
            raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")
        return getattr(getattr(self, part), name)
