"""Run control of a :class:`pemviz.app.session.Session`: Run / Stop, the cost, the status line, the progress bars and
the form's errors; the experiment runs in a worker thread, its events reach the panel through a :class:`RunListener`."""

from __future__ import annotations

import html
import math
import threading
import time

import viser

from pemviz.app._viser_compat import set_value
from pemviz.app.experiment_tab import ExperimentTab
from pemviz.app.explain_tab import ExplainTab
from pemviz.app.form import FormResult, run_cost
from pemviz.app.host import PanelHost
from pemviz.app.html import AMBER, BLUE, GREEN, GREY, RED, accuracy_html, box
from pemviz.app.plots_panel import PlotsPanel
from pemviz.app.rollouts_tab import RolloutsTab
from pemviz.app.runs import PanelRun
from pemviz.app.runs_tab import RunsTab
from pemviz.app.scene_view import SceneView
from pemviz.engine import experiment
from pemviz.engine.cost import LOAD_WORDS, range_text
from pemviz.engine.events import FinalEstimate, RolloutsSampled, RunFinished, RunStarted, StageFinished, StageStarted
from pemviz.engine.resources import torch_threads
from pemviz.scenarios.registry import problem_for
from pemviz.sinks import Sink


class RunControl:
    """Starting, stopping and following a run: owns the buttons and lines above the tabs, the newest run
    (:attr:`record`), its worker thread and cancel token; the run's events refresh the tabs (:class:`RunListener`)."""

    def __init__(
        self,
        client: viser.ClientHandle,
        app: PanelHost,
        lock: threading.RLock,
        *,
        form: ExperimentTab,
        runs_tab: RunsTab,
        rollouts_tab: RolloutsTab,
        scene: SceneView,
        explain: ExplainTab,
        plots_panel: PlotsPanel,
    ) -> None:
        self.client, self.app, self.lock = client, app, lock
        self.form, self.runs_tab, self.rollouts_tab, self.scene = form, runs_tab, rollouts_tab, scene
        self.explain, self.plots_panel = explain, plots_panel
        self.record: PanelRun | None = None
        """The run the live plots, status and rollouts show: the newest."""
        self._worker: threading.Thread | None = None
        self._cancel = threading.Event()
        self._stop_requested_at: float | None = None
        self.last_stop_latency_s: float | None = None
        """Seconds from Stop to the worker's end, for the last stopped run."""
        self.closed = False

    def build(self) -> None:
        """Add Run, Stop, the cost, Run anyway, the status line, the progress bars, the accuracy and the form's errors
        to ``client.gui``."""
        gui = self.client.gui
        self.run_button = gui.add_button("Run", color="green", icon=viser.Icon.PLAYER_PLAY)
        self.stop_button = gui.add_button("Stop", color="red", icon=viser.Icon.PLAYER_STOP, disabled=True)
        self.cost_html = gui.add_html("")
        self.confirm_button = gui.add_button("Run anyway", color="orange", visible=False)
        self.status_html = gui.add_html(box("idle", GREY))
        self.run_progress = gui.add_progress_bar(0.0, color="blue")
        self.stage_progress = gui.add_progress_bar(0.0, color="teal", animated=False)
        self.result_html = gui.add_html("")
        self.error_html = gui.add_html("")

        def run(_: object) -> None:
            self.start_run()

        def run_anyway(_: object) -> None:
            self.start_run(confirmed=True)

        self.run_button.on_click(run)
        self.confirm_button.on_click(run_anyway)
        self.stop_button.on_click(lambda _: self.stop_run())

    @property
    def running(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    def start_run(self, confirmed: bool = False) -> str | None:
        """Start a run with the form's values; returns why it was refused instead.

        A run whose cost is above the limits (:meth:`pemviz.engine.cost.RunCost.needs_confirm`) starts only
        ``confirmed`` (the *Run anyway* button)."""
        with self.lock:
            if self.running:
                return "a run is going: press Stop first"
            form = self.form.read_form()
            self._show_form(form)
            if not form.ok:
                return "invalid settings: " + "; ".join(form.errors.values())
            cfg = form.config
            assert cfg is not None  # form.ok
            cost = run_cost(cfg)
            if cost.needs_confirm and not confirmed:
                self.cost_html.content = box(
                    f"<b>This run is large:</b> {html.escape(cost.text())}. Press <b>Run anyway</b> to start it.", AMBER
                )
                self.confirm_button.visible = True
                return "confirm the cost first"
            self.confirm_button.visible = False
            self.form.echo()
            record = PanelRun(self.app.next_run_id(), cfg)
            self.record = record
            self.rollouts_tab.listed = record  # before Runs chooses it, so that choosing it lists nothing twice
            self.runs_tab.keep(record)
            self._cancel = threading.Event()
            self._stop_requested_at = None
            self._worker = threading.Thread(
                target=self._work, args=(record, self._cancel), name=f"pemviz-run-{record.run_id}", daemon=True
            )
            self._set_running_ui(True)
            self.status(f"{record.label}: starting ...")
            self.result_html.content = ""
            self.scene.clear(f"{record.short_label} is going: its rollouts appear in the Rollouts tab")
            self.rollouts_tab.set_rollouts(record)
            self.refresh_plots()
            self.runs_tab.refresh()
            self._worker.start()
        return None

    def stop_run(self) -> None:
        """Set this session's cancel token (the engine stops at its next check)."""
        with self.lock:
            if not self.running:
                return
            self._stop_requested_at = time.perf_counter()
            self._cancel.set()
            self.stop_button.disabled = True
            self.status("stopping ...")

    def wait_for_run(self, timeout: float | None = None) -> bool:
        worker = self._worker
        if worker is None:
            return True
        worker.join(timeout)
        return not worker.is_alive()

    def close(self) -> None:
        """The client left: stop its run."""
        self.closed = True
        self._cancel.set()

    def validate(self) -> None:
        """Check the form and show what it says (each field's error, the cost, whether Run can start)."""
        # read and show under the lock: callbacks run in a thread pool, and the last one must win
        with self.lock:
            self._show_form(self.form.read_form())

    def _show_form(self, form: FormResult) -> None:
        with self.lock:
            with self.client.atomic():
                self.form.show_errors(form)
                general = form.errors.get("", "")
                n_bad = len(form.errors)
                self.error_html.content = (
                    box(
                        f"<b>{n_bad} setting{'s' * (n_bad != 1)} to fix before Run.</b> "
                        + html.escape(general or "See the red lines under the fields (Experiment tab)."),
                        RED,
                    )
                    if n_bad
                    else ""
                )
                if not self.running:
                    self.run_button.disabled = not form.ok
                self.confirm_button.visible = False
                if form.ok:
                    assert form.config is not None  # form.ok
                    cost = run_cost(form.config)
                    colour = AMBER if cost.needs_confirm else GREY
                    self.cost_html.content = box(f"Cost: {html.escape(cost.text())}", colour)
                else:
                    self.cost_html.content = ""

    def _work(self, record: PanelRun, cancel: threading.Event) -> None:
        self.app.wait_warm()
        try:
            with torch_threads(1):
                problem = problem_for(record.config)
                record.problem = problem
                record.clock.pilot = experiment.scene_pilot(problem)  # prices the run's time left
                experiment.Experiment(record.config, [RunListener(self, record)], cancel, problem=problem).run()
        except Exception as exc:  # a bad PEM file, a simulator error: show it, keep serving
            record.fail(f"{type(exc).__name__}: {exc}")
            self.status(f"{record.label} failed: {record.message}", RED)
        finally:
            with self.lock:
                if self._stop_requested_at is not None:
                    self.last_stop_latency_s = time.perf_counter() - self._stop_requested_at
                self._set_running_ui(False)
                if record.status in ("cancelled", "failed"):
                    self.rollouts_tab.after_run(record)
                if record.status == "cancelled":
                    latency = self.last_stop_latency_s
                    self.status(
                        f"{record.short_label}: stopped after {len(record.stages)} stages"
                        + (f" ({latency:.2f} s after Stop)" if latency is not None else "")
                        + f", {record.elapsed_s():.1f} s in all",
                        AMBER,
                    )
                self.runs_tab.refresh()
                self.refresh_plots()

    def tick(self) -> None:
        """Refresh the status line of a running run: stage, what it does, elapsed time, the time left in the stage
        and in the whole run (:class:`pemviz.sinks.StageClock`)."""
        with self.lock:
            record = self.record
            if record is None or not self.running or record.done or self._stop_requested_at is not None:
                return
            with record.lock:
                stage = record.current_stage
                sampled = record.sampled_current
            if stage is None:
                return
            cfg = record.config
            assert record.plan is not None  # set by the run's first event, before any stage started
            label = record.plan.label(stage.stage, stage.kind)
            if stage.kind == "final" or not sampled:
                doing = f"simulating {stage.n_rollouts:,} rollouts"
            elif stage.kind == "pretrain":
                doing = f"pretraining the proposal ({cfg.adaptive.pretrain_epochs} epochs)"
            else:
                most = "at most " if cfg.adaptive.fit_tolerance is not None and cfg.adaptive.fit == "adam" else ""
                doing = f"cross-entropy update ({most}{cfg.adaptive.ce_epochs} epochs)"
            clock = record.clock
            stage_left, run_left = clock.stage_left_s(), clock.run_left_s()
            eta = ""
            if math.isfinite(stage_left):
                eta = f", about {stage_left:.1f} s left in it" if stage_left > 0.05 else ", nearly done"
            whole = ""
            if math.isfinite(run_left):
                why = LOAD_WORDS if clock.follow is None else ""  # the upper end: the load's drift alone
                whole = f", {range_text(run_left, clock.run_most_s(), left=' left in all', why=why)}"
            self.status(
                f"{record.short_label} · {label}: {doing} · stage {clock.stage_elapsed_s():.1f} s{eta} · run "
                f"{record.elapsed_s():.1f} s{whole}"
            )
            self.set_progress(record)

    def status(self, text: str, colour: str = BLUE) -> None:
        """Show ``text`` in the status line, in a box of ``colour``."""
        self.status_html.content = box(html.escape(text), colour)

    def _set_running_ui(self, running: bool) -> None:
        self.run_button.disabled = running or not self.form.parsed.ok
        self.stop_button.disabled = not running
        self.stage_progress.animated = running

    def set_progress(self, record: PanelRun) -> None:
        """Move the progress bars to where ``record`` is (the whole run, the stage)."""
        run, stage = record.progress()
        set_value(self.run_progress, run)
        set_value(self.stage_progress, stage)

    def refresh_plots(self) -> None:
        """Redraw the plots panel for the newest run and the kept ones."""
        with self.lock:
            runs = list(self.runs_tab.runs)
            record = self.record
            self.explain.hide_unused()  # no rollout of several objects explained (cleared for a new run): no charts
        self.plots_panel.fill(runs, record)


class RunListener(Sink):
    """The engine's listener for a run of a :class:`RunControl`: feeds the run's :class:`PanelRun`, then, while it is
    the newest run, refreshes the status line, rollouts, plots, kept runs and progress bars."""

    def __init__(self, control: RunControl, record: PanelRun) -> None:
        self.control, self.record = control, record

    def __call__(self, event) -> None:
        self.record(event)
        control = self.control
        if control.closed:
            return
        with control.lock:
            if self.record is not control.record:
                return
            super().__call__(event)
            control.set_progress(self.record)

    def on_run_started(self, event: RunStarted) -> None:
        self.control.status(f"{self.record.short_label}: started")

    def on_stage_started(self, event: StageStarted) -> None:
        self.control.tick()

    def on_rollouts_sampled(self, event: RolloutsSampled) -> None:
        self.control.rollouts_tab.set_rollouts(self.record)
        self.control.tick()

    def on_stage_finished(self, event: StageFinished) -> None:
        self._refresh()

    def on_final_estimate(self, event: FinalEstimate) -> None:
        self.control.result_html.content = accuracy_html(self.record, event)
        self.control.rollouts_tab.set_rollouts(self.record)  # every failure of the estimate, by its share of p
        self._refresh()

    def _refresh(self) -> None:
        self.control.refresh_plots()
        self.control.runs_tab.refresh()

    def on_run_finished(self, event: RunFinished) -> None:
        self.control.status(f"{self.record.short_label}: finished in {self.record.elapsed_s():.1f} s", GREEN)
        self.control.rollouts_tab.show_default_rollout(self.record)
