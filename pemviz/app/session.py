"""One browser client's panel: its own form, runs, Stop, plots, rollout explanation and 3D scene.

A :class:`Session` is made for each client that connects (viser's ``server.on_client_connect``) and
builds everything in that client's own ``client.gui`` / ``client.scene``: two tabs never share a form,
a run or a Stop button. The experiment runs in a worker thread (:class:`pemviz.engine.experiment.Experiment`); the
session listens to its events and stops it through the cancel token.

Layout: the control panel (right) holds Run / Stop, the cost of the run, the status line (stage,
elapsed time, the time left in the stage and in the whole run), the accuracy of the final estimate and the tabs
*Experiment* (the form;
each field shows its own error), *Rollouts* (choose a rollout: the most likely failure found and the
least-robust ones; 3D playback) and *Runs* (kept runs with their settings, pin / unpin, export). The
plots panel (left) holds *Live* (what each stage's sampler did over the states its rollouts visited, per-stage
values of every kept run, mu_hat with its interval and the exact answer), *Explain* (the chosen rollout of the run
chosen under *Runs* step by step, synced with the 3D playback: its severity, what happened in words, the
controller's signals, its decisive misses, minimal miss set and last saving step) and *Compare* (each kept run's
final estimate with its 95 % interval on a log10 chart beside the exact answer or reference, the settings that differ
between the kept runs, and their reference-state proposal curves).
"""

from __future__ import annotations

import html
import math
import threading
import time
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import viser

from pemviz.app import charts, compare, plots
from pemviz.app.html import AMBER, BLUE, GREEN, GREY, NO_ROLLOUT, RED, accuracy_html, box, field_error
from pemviz.app.rollouts_tab import RolloutsTab
from pemviz.app.runs_tab import RunsTab
from pemviz.app.scene_view import SceneView
from pemviz.app._viser_compat import resend_value
from pemviz.app.explain import Explanation
from pemviz.app.objects_view import ObjectsExplanation
from pemviz.app.form import FIELDS_BY_KEY, NUMBER_FIELDS, FormResult, format_number, parse_form, run_cost
from pemviz.app.runs import PANEL_PRESETS, PanelRun, Trajectory, export_path, export_run, keep_runs
from pemviz.engine import experiment
from pemviz.config import SCENE_DEFAULTS, SETTINGS, SIMULATORS, ExperimentConfig
from pemviz.engine.cost import duration
from pemviz.core.estimate import format_probability
from pemviz.engine.events import FinalEstimate, RolloutsSampled, RunFinished, RunStarted, StageFinished, StageStarted
from pemviz.pem import DEFAULT_PEM_NAME, shipped_pems
from pemviz.presets import preset_help
from pemviz.scenarios.braking_failures import Severity
from pemviz.core.problems import problem_for
from pemviz.engine.resources import torch_threads
from pemviz.scenarios.braking import BrakingParams
from pemviz.sinks import Sink
from pemviz.sinks import colours as C


class PanelHost(Protocol):
    """What a session needs of the server that owns it (:class:`pemviz.app.panel.PanelApp`)."""

    params: BrakingParams
    """The scenario's constants."""
    config0: ExperimentConfig
    """The configuration the panel opened with."""
    preset_name: str
    recordings_dir: Path
    """Where exported recordings go."""

    def next_run_id(self) -> int: ...

    def wait_warm(self) -> None: ...

ROLLOUT_ORDERS = ("importance weight", "robustness", "log p", "severity")
"""How the Rollouts tab orders its rollouts: least robust, most probable under the PEM, or worst outcome first."""
class Session(RunsTab, RolloutsTab, SceneView):
    """The panel of one browser client (see the module docstring).

    Args:
        app: the server (recordings folder, scenario constants, warm-up).
        client: the viser client this session draws into.
    """

    def __init__(self, app: PanelHost, client: viser.ClientHandle) -> None:
        self.app = app
        self.client = client
        self.params = app.params
        self.lock = threading.RLock()
        self.runs: list[PanelRun] = []
        self.record: PanelRun | None = None
        """The run the live plots, status and rollouts show: the newest."""
        self._worker: threading.Thread | None = None
        self._cancel = threading.Event()
        self._stop_requested_at: float | None = None
        self.last_stop_latency_s: float | None = None
        """Seconds from Stop to the worker's end, for the last stopped run."""
        self.form = FormResult(None, {})
        self._confirmed_cost = False
        self.shown: Trajectory | None = None
        self.shown_record: PanelRun | None = None
        self.listed: PanelRun | None = None
        """The run whose rollouts the Rollouts tab lists and Explain explains: the one chosen under Runs (a new run
        chooses itself)."""
        self._severities: dict[tuple[int, str], Severity] = {}
        self.explanation: Explanation | None = None
        self.objects_ex: ObjectsExplanation | None = None
        """The shown rollout's explanation when its scene has several objects (then :attr:`explanation` is None)."""
        self.shown_step = -1
        self._shown_x: tuple[np.ndarray, np.ndarray] | None = None
        self._shown_span = 0.0
        """Metres of road the scene frames for the rollout shown (its cars' longest stretch)."""
        self.playing = False
        self._rollout_labels: dict[str, Trajectory] = {}
        self.last_export: Path | None = None
        self.closed = False
        self._build_gui()
        self._build_scene()
        self._validate()

    # == public API (what the buttons do) ============================================================
    @property
    def running(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    @property
    def current(self) -> PanelRun | None:
        return self.record

    def field_texts(self) -> dict[str, str]:
        return {key: handle.value for key, handle in self.fields.items()}

    def choice_values(self) -> dict[str, Any]:
        values = {key: handle.value for key, handle in self.choices.items()}
        if values.get("pem") == self._default_pem:
            values["pem"] = self.app.config0.pem
        return values

    def read_form(self) -> FormResult:
        """Parse what the form holds now (every field, every error)."""
        name = self.preset.value
        base = self.app.config0 if name == self.app.preset_name else ExperimentConfig(**PANEL_PRESETS[name])
        return parse_form(self.field_texts(), self.choice_values(), base)

    def start_run(self, confirmed: bool = False) -> str | None:
        """Start a run with the form's values; returns why it was refused instead.

        A run whose cost is above the limits (:meth:`pemviz.engine.cost.RunCost.needs_confirm`) starts only
        ``confirmed`` (the *Run anyway* button).
        """
        with self.lock:
            if self.running:
                return "a run is going: press Stop first"
            form = self.read_form()
            self._show_form(form)
            if not form.ok:
                return "invalid settings: " + "; ".join(form.errors.values())
            cfg = form.config
            cost = run_cost(cfg)
            if cost.needs_confirm and not confirmed:
                self.cost_html.content = box(
                    f"<b>This run is large:</b> {html.escape(cost.text())}. Press <b>Run anyway</b> to start it.", AMBER
                )
                self.confirm_button.visible = True
                return "confirm the cost first"
            self.confirm_button.visible = False
            self._echo_form()
            record = PanelRun(self.app.next_run_id(), cfg)
            self.runs = keep_runs(self.runs, record)
            self.record = record
            self.listed = record
            with self.client.atomic():
                self.run_choice.options = tuple(r.label for r in self.runs)
                self.run_choice.value = record.label
            self._cancel = threading.Event()
            self._stop_requested_at = None
            self._worker = threading.Thread(
                target=self._work, args=(record, self._cancel), name=f"pemviz-run-{record.run_id}", daemon=True
            )
            self._set_running_ui(True)
            self._status(f"{record.label}: starting ...")
            self.result_html.content = ""
            self._clear_scene(f"{record.short_label} is going: its rollouts appear in the Rollouts tab")
            self._set_rollouts(record)
            self._refresh_plots()
            self._refresh_runs()
            self._worker.start()
        return None

    def _echo_form(self) -> None:
        """Send every field's value as the server has it back to the browser, so the form shows what runs.

        viser's browser client sends GUI updates through one 50 ms throttle shared by all inputs and buttons:
        of several messages inside one window only the last goes out, so a value typed just before pressing
        Run (or before typing into the next field) can be lost on the way. Echoing makes such a field show
        the value the run really uses instead of what the browser alone remembers.
        """
        with self.client.atomic():
            for handle in (*self.fields.values(), *self.choices.values(), self.preset):
                resend_value(handle)

    def stop_run(self) -> None:
        """Set this session's cancel token (the engine stops at its next check)."""
        with self.lock:
            if not self.running:
                return
            self._stop_requested_at = time.perf_counter()
            self._cancel.set()
            self.stop_button.disabled = True
            self._status("stopping ...")

    def wait_for_run(self, timeout: float | None = None) -> bool:
        worker = self._worker
        if worker is None:
            return True
        worker.join(timeout)
        return not worker.is_alive()

    def kept_run(self, run_id: int) -> PanelRun:
        for r in self.runs:
            if r.run_id == run_id:
                return r
        raise ValueError(f"run {run_id} is not kept in this tab")

    def set_pinned(self, run_id: int, pinned: bool) -> None:
        self.kept_run(run_id).pinned = pinned
        self._refresh_runs()

    def export(self, run_id: int, name: str) -> Path:
        """Write a kept run to ``recordings_dir / <sanitised name>.rrd``.

        Raises:
            ValueError: the run is not kept or has no events, or an unusable name.
        """
        record = self.kept_run(run_id)
        if not record.events:
            raise ValueError(f"{record.short_label} has nothing to export yet")
        path = export_path(self.app.recordings_dir, name)
        export_run(record, path)
        self.last_export = path
        return path

    def close(self) -> None:
        """The client left: stop its run."""
        self.closed = True
        self._cancel.set()

    # == GUI ===========================================================================================
    def _build_gui(self) -> None:
        gui = self.client.gui
        gui.configure_theme(control_width="large", show_share_button=False, brand_color=C.BLUE)
        gui.set_panel_label("pemviz")
        gui.add_markdown(
            "**pemviz**: the failure probability of a PEM-driven scenario (braking, or a cut-in among several cars) by "
            "adaptive importance sampling (Innes & Ramamoorthy 2022). Set the experiment, press **Run**; this tab has "
            "its own runs."
        )
        self.run_button = gui.add_button("Run", color="green", icon=viser.Icon.PLAYER_PLAY)
        self.stop_button = gui.add_button("Stop", color="red", icon=viser.Icon.PLAYER_STOP, disabled=True)
        self.cost_html = gui.add_html("")
        self.confirm_button = gui.add_button("Run anyway", color="orange", visible=False)
        self.status_html = gui.add_html(box("idle", GREY))
        self.run_progress = gui.add_progress_bar(0.0, color="blue")
        self.stage_progress = gui.add_progress_bar(0.0, color="teal", animated=False)
        self.result_html = gui.add_html("")
        self.error_html = gui.add_html("")

        tabs = gui.add_tab_group()
        with tabs.add_tab("Experiment", viser.Icon.SETTINGS):
            self._build_form()
        with tabs.add_tab("Rollouts", viser.Icon.CAR):
            self._build_rollouts()
        with tabs.add_tab("Runs", viser.Icon.CHART_LINE):
            self._build_runs_tab()
        self.tabs = tabs

        self.run_button.on_click(lambda _: self.start_run())
        self.confirm_button.on_click(lambda _: self.start_run(confirmed=True))
        self.stop_button.on_click(lambda _: self.stop_run())

        panel = gui.add_panel()
        with panel.add_tab("Live", viser.Icon.CHART_LINE):
            self.marginal_note = gui.add_html(charts.marginal_note(None))  # why the q(detect) charts are hidden
            self.marginal_plots = charts.marginal_plots(gui)
            self.stage_plots = {key: plots.stage_plot(gui, title, y) for key, title, y in plots.STAGE_PLOTS}
        with panel.add_tab("Explain", viser.Icon.ZOOM_QUESTION):
            self.explain_html = gui.add_html(box("Choose a rollout in the Rollouts tab to explain it.", GREY))
            self.strip = plots.strip_plots(gui)
            self.strip["controller"] = charts.controller_plot(gui, order=self.strip["gap"].order + 0.5)
            # a cut-in rollout: the cut-in car's gap and lateral offset, truth and tracker, and the ACC (hidden until
            # one is shown), then the decisive errors, every car's events and the scene from above
            self.object_plots = charts.object_plots(gui)
            self.objects_html = gui.add_html("")
        with panel.add_tab("Compare", viser.Icon.A_B):
            self.compare_estimates = compare.estimate_plot(gui)
            self.compare_html = gui.add_html("")
            self.compare_html_ref = gui.add_html(
                '<div style="margin:0 0.6em; font-size:0.8em; color:#555">Reference-state curves: q(detect | gap) with '
                "the proposal's other inputs (speeds, pending brake) held at the start state; for the cut-in, "
                "q(detect | range) of car 0 straight ahead in the ego's lane. The Live tab shows what each sampler "
                "did over the states its rollouts visited. One chart per kept run.</div>"
            )
            self.compare_plots = [plots.curve_plot(gui, f"slot {i + 1}: no run yet", height=190, visible=False)
                                  for i in range(4)]  # fmt: skip
        self.plot_panel = panel
        panel.dock_left()
        panel.set_width(460)
        gui.main_panel.dock_right()

    def _build_form(self) -> None:
        gui = self.client.gui
        c0 = self.app.config0
        simulators = SIMULATORS
        shipped = shipped_pems() or [DEFAULT_PEM_NAME]
        self._default_pem = DEFAULT_PEM_NAME if DEFAULT_PEM_NAME in shipped else shipped[0]
        pem_options = list(shipped) + ([c0.pem] if c0.pem and c0.pem not in shipped else [])

        self.preset = gui.add_dropdown(
            "preset", tuple(PANEL_PRESETS), initial_value=self.app.preset_name,
            hint=f"sampler settings: {preset_help(PANEL_PRESETS)}",
        )  # fmt: skip
        self.choices: dict[str, Any] = {}
        self.fields: dict[str, viser.GuiTextHandle] = {}
        self.field_errors: dict[str, viser.GuiHtmlHandle] = {}

        def number(key: str) -> None:  # label, range and hint from the setting (pemviz.config.SETTINGS)
            f = FIELDS_BY_KEY[key]
            self.fields[key] = gui.add_text(f.label, format_number(f, getattr(c0, key)), hint=f.hint)
            self.field_errors[key] = gui.add_html("")

        def dropdown(key: str, options: tuple[str, ...] | None = None, value: str | None = None, **kw: Any) -> None:
            s = SETTINGS[key]
            self.choices[key] = gui.add_dropdown(s.label, options or s.choices, initial_value=value or getattr(c0, key),
                                                 hint=s.hint, **kw)  # fmt: skip

        dropdown("scenario")
        dropdown("metric")
        for key in ("smoothing", "quantile_level", "n_stages", "n_per_stage", "n_final", "seed"):
            number(key)
        dropdown("pem", tuple(pem_options), c0.pem or self._default_pem)
        dropdown("sim", simulators, c0.sim if c0.sim in simulators else simulators[0], disabled=len(simulators) < 2)
        with gui.add_folder("advanced", expand_by_default=False):
            dropdown("method")
            for key in ("rel_error", "max_sims", "max_time_s", "ce_epochs", "pretrain_rollouts", "pretrain_epochs",
                        "learning_rate"):
                number(key)
            dropdown("weights")
            dropdown("final_estimate")
        gui.add_markdown("Changes apply to the next run.")
        for handle in (*self.fields.values(), *self.choices.values()):
            handle.on_update(lambda _: self._validate())
        self.preset.on_update(lambda _: self._apply_preset(self.preset.value))
        self.choices["scenario"].on_update(lambda _: self._apply_scene(self.choices["scenario"].value))

    def _apply_scene(self, scenario: str) -> None:
        """Set the method and N to ``scenario``'s own defaults (:data:`pemviz.config.SCENE_DEFAULTS`) where it has
        them, and back to the preset's where it has none."""
        fields = SCENE_DEFAULTS.get(scenario) or {
            "method": "adaptive", "n_per_stage": ExperimentConfig(**PANEL_PRESETS.get(self.preset.value, {})).n_per_stage}
        with self.client.atomic():
            self.choices["method"].value = fields["method"]
            self.fields["n_per_stage"].value = format_number(FIELDS_BY_KEY["n_per_stage"], fields["n_per_stage"])
        self._validate()

    def _apply_preset(self, name: str) -> None:
        """Set the fields to ``name``'s settings (metric, seed, PEM, simulator and method stay)."""
        cfg = ExperimentConfig(**PANEL_PRESETS.get(name, {}))
        with self.client.atomic():
            for f in NUMBER_FIELDS:
                if f.name in self.fields and f.name != "seed":
                    self.fields[f.name].value = format_number(f, getattr(cfg, f.name))
            for key in ("weights", "final_estimate"):
                self.choices[key].value = getattr(cfg, key)
        self._validate()

    def _build_rollouts(self) -> None:
        gui = self.client.gui
        self.rollout_dropdown = gui.add_dropdown(
            "rollout", (NO_ROLLOUT,), initial_value=NO_ROLLOUT,
            hint="the most likely failure found, then the rollouts in the order of sort by (the first 100)",
        )  # fmt: skip
        self.rollout_order = gui.add_dropdown(
            "sort by", ROLLOUT_ORDERS, initial_value=ROLLOUT_ORDERS[0],
            hint="importance weight: the largest share of p first; robustness: least robust first; log p: most "
                 "probable under the PEM first; severity: worst first",
        )  # fmt: skip
        self.failures_only = gui.add_checkbox("failures only", False, hint="list only the rollouts that failed")
        self.rollout_html = gui.add_html(box("No rollouts yet: run an experiment.", GREY))
        self.step_slider = gui.add_slider("step", min=0, max=self.params.n_steps - 1, step=1, initial_value=0)
        self.play_button = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
        self.follow = gui.add_checkbox("follow cars", True, hint="move the camera along with the cars")
        self.scene_html = gui.add_html("")
        self.rollout_dropdown.on_update(lambda _: self._on_rollout_chosen(self.rollout_dropdown.value))
        for handle in (self.rollout_order, self.failures_only):
            handle.on_update(lambda _: self._relist())
        self.step_slider.on_update(lambda _: self._render_step(int(self.step_slider.value)))
        self.play_button.on_click(lambda _: self._toggle_play())

    def _build_runs_tab(self) -> None:
        gui = self.client.gui
        self.runs_html = gui.add_html(box("No runs yet.", GREY))
        gui.add_markdown(
            "Up to 4 runs are kept; a new run drops stopped runs first, then the oldest finished one; pinned runs stay."
        )
        self.run_choice = gui.add_dropdown("kept run", ("(no run yet)",), initial_value="(no run yet)",
                                           hint="the run to pin or export")
        self.pin_button = gui.add_button("Pin", icon=viser.Icon.PIN, disabled=True)
        with gui.add_folder("export to rerun (.rrd)"):
            self.export_name = gui.add_text("export name", "run")
            self.export_button = gui.add_button("Export chosen run", icon=viser.Icon.DOWNLOAD, disabled=True)
            self.export_html = gui.add_html("")
        self.run_choice.on_update(lambda _: self._on_run_choice())
        self.pin_button.on_click(lambda _: self._toggle_pin())
        self.export_button.on_click(self._on_export)

    # -- form -> GUI ---------------------------------------------------------------------------------
    def _validate(self) -> None:
        # read and show under the lock: callbacks run in a thread pool, and the last one must win
        with self.lock:
            self._show_form(self.read_form())

    def _show_form(self, form: FormResult) -> None:
        with self.lock:
            self.form = form
            with self.client.atomic():
                for key, handle in self.field_errors.items():
                    handle.content = field_error(form.errors.get(key, ""))
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
                    cost = run_cost(form.config)
                    colour = AMBER if cost.needs_confirm else GREY
                    self.cost_html.content = box(f"Cost: {html.escape(cost.text())}", colour)
                else:
                    self.cost_html.content = ""

    # == the worker ===================================================================================
    def _work(self, record: PanelRun, cancel: threading.Event) -> None:
        self.app.wait_warm()
        try:
            with torch_threads(1):
                problem = problem_for(record.config)
                record.problem = problem
                experiment.Experiment(record.config, [RunListener(self, record)], cancel, problem=problem).run()
        except Exception as exc:  # a bad PEM file, a simulator error: show it, keep serving
            record.fail(f"{type(exc).__name__}: {exc}")
            self._status(f"{record.label} failed: {record.message}", RED)
        finally:
            with self.lock:
                if self._stop_requested_at is not None:
                    self.last_stop_latency_s = time.perf_counter() - self._stop_requested_at
                self._set_running_ui(False)
                if record.status in ("cancelled", "failed"):
                    self._after_run(record)
                if record.status == "cancelled":
                    latency = self.last_stop_latency_s
                    self._status(
                        f"{record.short_label}: stopped after {len(record.stages)} stages"
                        + (f" ({latency:.2f} s after Stop)" if latency is not None else "")
                        + f", {record.elapsed_s():.1f} s in all",
                        AMBER,
                    )
                self._refresh_runs()
                self._refresh_plots()

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
            label = record.plan.label(stage.stage, stage.kind)
            if stage.kind == "final" or not sampled:
                doing = f"simulating {stage.n_rollouts:,} rollouts"
            elif stage.kind == "pretrain":
                doing = f"pretraining the proposal ({cfg.pretrain_epochs} epochs)"
            else:
                most = "at most " if cfg.fit_tolerance is not None and cfg.fit == "adam" else ""
                doing = f"cross-entropy update ({most}{cfg.ce_epochs} epochs)"
            clock = record.clock
            stage_left, run_left = clock.stage_left_s(), clock.run_left_s()
            eta = ""
            if math.isfinite(stage_left):
                eta = f", about {stage_left:.1f} s left in it" if stage_left > 0.05 else ", nearly done"
            whole = f", about {duration(run_left)} left in all" if math.isfinite(run_left) else ""
            self._status(
                f"{record.short_label} · {label}: {doing} · stage {clock.stage_elapsed_s():.1f} s{eta} · run "
                f"{record.elapsed_s():.1f} s{whole}"
            )
            self._set_progress(record)

    # -- state -> GUI --------------------------------------------------------------------------------
    def _status(self, text: str, colour: str = BLUE) -> None:
        self.status_html.content = box(html.escape(text), colour)

    def _set_running_ui(self, running: bool) -> None:
        self.run_button.disabled = running or not self.form.ok
        self.stop_button.disabled = not running
        self.stage_progress.animated = running

    def _set_progress(self, record: PanelRun) -> None:
        run, stage = record.progress()
        self.run_progress.value = run
        self.stage_progress.value = stage

    def _refresh_plots(self) -> None:
        with self.lock:
            runs = list(self.runs)
            record = self.record
            if self.objects_ex is None:  # no cut-in rollout explained (cleared for a new run): none of its charts
                with self.client.atomic():
                    charts.hide_object_plots(self.object_plots)
                    self.objects_html.content = ""
        with self.client.atomic():
            if record is not None:
                charts.fill_marginal_plots(self.marginal_plots, record, self.marginal_note)
            for i, plot in enumerate(self.compare_plots):
                plot.visible = i < len(runs) and runs[i].curve_grid_m.size > 0  # a slot without a run is hidden
                if i < len(runs):
                    r = runs[i]
                    fin = r.final.estimate if r.final is not None else None
                    mu = f", mu_hat {format_probability(fin.log_mu_hat)}" if fin is not None else ""
                    ref = ", reference-state q" if r.config.proposal_inputs == "state" else ""
                    plots.fill_curve_plot(plot, r, f"{r.short_label}{mu}{ref}")
            for key, plot in self.stage_plots.items():
                plots.fill_stage_plot(plot, key, runs)
                if key == "log10_mu_hat":
                    charts.fill_mu_hat_plot(plot, runs)

class RunListener(Sink):
    """The engine's listener for a session's run: feeds the run's :class:`PanelRun`, then, while it is the run the
    session shows, refreshes the status line, rollouts, plots, kept runs and progress bars."""

    def __init__(self, session: Session, record: PanelRun) -> None:
        self.session, self.record = session, record

    def __call__(self, event) -> None:
        self.record(event)
        session = self.session
        if session.closed:
            return
        with session.lock:
            if self.record is not session.record:
                return
            super().__call__(event)
            session._set_progress(self.record)

    def on_run_started(self, event: RunStarted) -> None:
        self.session._status(f"{self.record.short_label}: started")

    def on_stage_started(self, event: StageStarted) -> None:
        self.session.tick()

    def on_rollouts_sampled(self, event: RolloutsSampled) -> None:
        self.session._set_rollouts(self.record)
        self.session.tick()

    def on_stage_finished(self, event: StageFinished) -> None:
        self._refresh()

    def on_final_estimate(self, event: FinalEstimate) -> None:
        self.session.result_html.content = accuracy_html(self.record, event)
        self.session._set_rollouts(self.record)  # every failure of the estimate, by its share of p
        self._refresh()

    def _refresh(self) -> None:
        self.session._refresh_plots()
        self.session._refresh_runs()

    def on_run_finished(self, event: RunFinished) -> None:
        self.session._status(f"{self.record.short_label}: finished in {self.record.elapsed_s():.1f} s", GREEN)
        self.session._show_default_rollout(self.record)
