"""One browser client's panel: its own form, runs, Stop, plots, rollout explanation and 3D scene.

A :class:`Session` is made for each client that connects (viser's ``server.on_client_connect``) and
builds everything in that client's own ``client.gui`` / ``client.scene``: two tabs never share a form,
a run or a Stop button. The experiment runs in a worker thread (:class:`pemviz.engine.Experiment`); the
session listens to its events and stops it through the cancel token.

Layout: the control panel (right) holds Run / Stop, the cost of the run, the status line (stage,
elapsed time, expected time), the accuracy of the final estimate and the tabs *Experiment* (the form;
each field shows its own error), *Rollouts* (choose a rollout: the most likely failure found and the
least-robust ones; 3D playback) and *Runs* (kept runs with their settings, pin / unpin, export). The
plots panel (left) holds *Live* (what each stage's sampler did over the states its rollouts visited, per-stage
values of every kept run, mu_hat with its interval and the exact answer), *Explain* (the chosen rollout of the run
chosen under *Runs* step by step, synced with the 3D playback: its severity, what happened in words, the
controller's signals, its decisive misses, minimal miss set and last saving step) and *Compare* (every setting of
every kept run and their reference-state proposal curves).
"""

from __future__ import annotations

import dataclasses
import html
import math
import threading
import time
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import viser

from pemviz.app import charts, plots
from pemviz.app._viser_compat import resend_value
from pemviz.app.explain import Explanation, explain
from pemviz.app.form import (
    FIELDS_BY_KEY,
    NUMBER_FIELDS,
    FormResult,
    format_number,
    parse_form,
    run_cost,
    setting_name,
    setting_value,
)
from pemviz.app.runs import PANEL_PRESETS, PanelRun, Trajectory, export_path, export_run, keep_runs, scene_positions
from pemviz import engine
from pemviz.config import SETTINGS, SIMULATORS, ExperimentConfig
from pemviz.estimate import format_probability, relative_error
from pemviz.events import FinalEstimate, RolloutsSampled, RunFinished, RunStarted, StageFinished, StageStarted
from pemviz.pem import DEFAULT_PEM_NAME, shipped_pems
from pemviz.scenarios.braking_failures import Severity, severity
from pemviz.problems import problem_for
from pemviz.sampling import torch_threads
from pemviz.scenarios.braking import BrakingParams
from pemviz.sinks import Sink
from pemviz.sinks import colours as C
from pemviz.sinks.colours import BRAKE_ZONE, CRASH, DETECTED, IDLE, LEAD, MISSED, hex_colour


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

CAR_HEIGHT_M = 1.5
CAMERA_OFFSET_M = np.array([-5.0, -20.0, 13.0])
"""Initial camera position relative to the point between the cars (metres; behind-left, above)."""
NO_ROLLOUT = "(choose a rollout)"
ROLLOUT_ORDERS = ("robustness", "log p", "severity")
"""How the Rollouts tab orders its rollouts: least robust, most probable under the PEM, or worst outcome first."""
TABLE_STYLE = (
    "<style>.pemviz-table{border-collapse:collapse;text-align:right}"
    ".pemviz-table td,.pemviz-table th{padding:0.05em 0.3em}"
    ".pemviz-table tr:nth-child(even){background:#0000000a}</style>"
)
GREY, BLUE, GREEN, AMBER, RED = (hex_colour(c) for c in (C.GREY, C.BLUE, C.GREEN, C.AMBER, C.RED))
VERDICT_COLOURS = {"reliable": GREEN, "doubtful": AMBER, "unreliable": RED}


def box(text: str, colour: str) -> str:
    return (
        f'<div style="margin:0 0.6em 0.5em; padding:0.4em 0.6em; border-radius:4px; font-size:0.85em; '
        f'border-left:4px solid {colour}; background:{colour}14">{text}</div>'
    )


def field_error(text: str) -> str:
    """The error line under a field (empty: none)."""
    if not text:
        return ""
    return f'<div style="margin:-0.3em 0.8em 0.4em; color:{RED}; font-size:0.8em">{html.escape(text)}</div>'


def accuracy_html(record: PanelRun, ev: FinalEstimate) -> str:
    """The final estimate with its 95 % interval, verdict and reason, and the exact answer where known."""
    e = ev.estimate
    colour = VERDICT_COLOURS.get(e.verdict, GREY)
    lines = [
        f"<b>Final estimate of {html.escape(record.short_label)}</b>: mu_hat = "
        f"<b>{format_probability(e.log_mu_hat, 4)}</b> &nbsp;(95 % interval {html.escape(e.interval_text())})",
        f'<b style="color:{colour}">{html.escape(e.verdict)}</b>: {html.escape(e.reason)}',
    ]
    exact = record.exact_log_p
    if exact is not None:
        inside = "inside" if e.covers(exact) else "<b>outside</b>"
        lines.append(
            f"exact answer {format_probability(exact, 4)}: relative error "
            f"{relative_error(e.log_mu_hat, exact):.2g}, {inside} the interval"
        )
    if e.n_failures == 0:
        lines.append(f"no failure among {e.n} rollouts, so mu_hat = 0: " + no_failure_advice(record.config.method, e.n))
    lines.append(
        f"failures {e.n_failures}/{e.n} · ESS {plots.finite_or_dash(e.ess, '.1f')} · k-hat "
        f"{plots.finite_or_dash(e.khat, '.2f')} · NLL {plots.finite_or_dash(e.nll_mean, '.1f')} nats · "
        f"{ev.n_simulations:,} simulations in {ev.wall_s:.1f} s"
    )
    return box("<br>".join(lines), colour)


def explanation_html(record: PanelRun, traj: Trajectory, ex: Explanation, title: str, dt: float) -> str:
    """Explain's header: the rollout, its severity, what happened in words, the minimal miss set, the last step at
    which one detection still saves it, and the counterfactual's summary."""
    best = record.most_likely_failure
    what = "the most likely failure found" if traj is best else ("a failure" if traj.crashed else "no failure")
    cf = ex.counterfactual
    lines = [
        f"<b>{html.escape(title)}</b>: {what} · <b>{html.escape(ex.severity.short)}</b> · robustness "
        f"{traj.robustness:+.4g} ({record.config.metric}) · log p_PEM {traj.log_p_total:.1f} nats · log w "
        f"{traj.log_weight:.1f} nats",
        f"<b>What happened</b>: {html.escape(ex.sentence)}",
    ]
    if ex.crashed and ex.replay_matches:
        if cf.minimal_set.size:
            k = cf.minimal_set.size
            kind = "smallest" if cf.smallest else "minimal: none can be left out"
            steps = ", ".join(f"{t * dt:.2f}" for t in cf.minimal_set[:16]) + (" ..." * (k > 16))
            found = (
                f"<b>Minimal miss set</b> ({kind}): {k} miss{'es' * (k != 1)} at {steps} s; detected there, the gap "
                f"stays at or above {cf.minimal_set_min_gap_m:.2f} m"
            )
        else:
            found = "<b>Minimal miss set</b>: none: even a detection at every step fails"
        saving = (
            f"{cf.last_saving_step * dt:.2f} s (step {cf.last_saving_step})" if cf.last_saving_step is not None
            else "none: no single detection saves it"
        )
        lines.append(f"{found} · <b>last step at which one detection still saves it</b>: {saving}")
    lines.append(f"<b>Counterfactual</b> (misses flipped to detections, replayed): {html.escape(ex.summary())}")
    return box("<br>".join(lines), RED if traj.crashed else GREEN)


def no_failure_advice(method: str, n: int) -> str:
    """What to try after a run without a failure, in the terms of its ``method``."""
    if method == "adaptive":
        return (
            "the sampler never reached a crash. More stages (K), more rollouts (N) or the state-ce preset move the "
            "proposal further towards the failures."
        )
    if method == "mc":
        return (
            f"plain Monte Carlo draws every rollout from the PEM itself, so a failure of probability p shows up about "
            f"once in 1/p rollouts; none in {n:,} only says p is likely below {3.0 / n:.2g}. The adaptive method "
            "(state-ce preset) reaches failures far rarer than that."
        )
    if method == "ams":
        return "no particle reached a failure: more particles (N) or the adaptive method (state-ce preset)."
    return (
        f"this fixed sampler ({method}) reached no crash: more rollouts (N) or the adaptive method (state-ce preset), "
        "which learns where to miss."
    )


class Session:
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
        self.shown_step = -1
        self._shown_x: tuple[np.ndarray, np.ndarray] | None = None
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

        A run whose cost is above the limits (:meth:`pemviz.app.form.RunCost.needs_confirm`) starts only
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
            "**pemviz**: the crash probability of a PEM-driven braking scenario by adaptive importance sampling "
            "(Innes & Ramamoorthy 2022). Set the experiment, press **Run**; this tab has its own runs."
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
            self.marginal_plots = charts.marginal_plots(gui)
            self.stage_plots = {key: plots.stage_plot(gui, title, y) for key, title, y in plots.STAGE_PLOTS}
        with panel.add_tab("Explain", viser.Icon.ZOOM_QUESTION):
            self.explain_html = gui.add_html(box("Choose a rollout in the Rollouts tab to explain it.", GREY))
            self.strip = plots.strip_plots(gui)
            self.strip["controller"] = charts.controller_plot(gui, order=self.strip["gap"].order + 0.5)
        with panel.add_tab("Compare", viser.Icon.A_B):
            self.compare_html = gui.add_html("")
            self.compare_html_ref = gui.add_html(
                '<div style="margin:0 0.6em; font-size:0.8em; color:#555">Reference-state curves: q(detect | gap) with '
                "the proposal's other inputs (speeds, pending brake) held at the start state. The Live tab shows what "
                "each sampler did over the states its rollouts visited.</div>"
            )
            self.compare_plots = [plots.curve_plot(gui, f"slot {i + 1}: no run yet", height=190) for i in range(4)]
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
            hint="state-ce: the recommended sampler; paper: as published; authors-code: as the authors' code ran; "
                 "quick: a few-second run",
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

        dropdown("metric")
        for key in ("smoothing", "quantile_level", "n_stages", "n_per_stage", "n_final", "seed"):
            number(key)
        dropdown("pem", tuple(pem_options), c0.pem or self._default_pem)
        dropdown("sim", simulators, c0.sim if c0.sim in simulators else simulators[0], disabled=len(simulators) < 2)
        with gui.add_folder("advanced", expand_by_default=False):
            dropdown("method")
            for key in ("ce_epochs", "pretrain_rollouts", "pretrain_epochs", "learning_rate"):
                number(key)
            dropdown("weights")
            dropdown("final_estimate")
        gui.add_markdown("Changes apply to the next run.")
        for handle in (*self.fields.values(), *self.choices.values()):
            handle.on_update(lambda _: self._validate())
        self.preset.on_update(lambda _: self._apply_preset(self.preset.value))

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
            hint="the most likely failure found, then the least robust (the run's metric)",
        )  # fmt: skip
        self.rollout_order = gui.add_dropdown(
            "sort by", ROLLOUT_ORDERS, initial_value=ROLLOUT_ORDERS[0],
            hint="robustness: least robust first; log p: most probable under the PEM first; severity: worst first",
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
                engine.Experiment(record.config, [RunListener(self, record)], cancel, problem=problem).run()
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
        """Refresh the status line of a running run: stage, what it does, elapsed time, expected time."""
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
                doing = f"cross-entropy update ({cfg.ce_epochs} epochs)"
            in_stage = record.clock.stage_elapsed_s()
            expected = record.clock.expected_s(stage.kind, stage.n_rollouts)
            eta = ""
            if math.isfinite(expected):
                eta = f", about {max(0.0, expected - in_stage):.1f} s left in it" if in_stage < expected else ", nearly done"
            self._status(
                f"{record.short_label} · {label}: {doing} · stage {in_stage:.1f} s{eta} · run {record.elapsed_s():.1f} s"
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
        with self.client.atomic():
            if record is not None:
                charts.fill_marginal_plots(self.marginal_plots, record)
            for i, plot in enumerate(self.compare_plots):
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
            self.compare_html.content = block
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
        shown = _display_path(path)
        size_kb = path.stat().st_size / 1024
        self.export_html.content = box(
            f"Saved {html.escape(r.short_label)} to <b>{html.escape(shown)}</b> ({size_kb:.0f} KB). Open it with "
            f"<code>rerun {html.escape(shown)}</code>; the download link is in this tab's notification.",
            GREEN,
        )
        self.client.send_file_download(path.name, path.read_bytes(), save_immediately=False)

    # == rollouts, explanation and the 3D scene =======================================================
    @staticmethod
    def rollout_label(t: Trajectory, most_likely: bool = False, sev: Severity | None = None) -> str:
        """The rollout list entry (no rank in it, so a chosen rollout stays chosen while later stages re-rank); the
        outcome in :attr:`Severity.short`'s words when ``sev`` is given."""
        outcome = f" · {sev.short}" if sev is not None and (t.crashed or sev.failed) else (" · failed" * t.crashed)
        head = "most likely failure · " if most_likely else ""
        return (
            f"{head}stage {t.stage} rollout {t.index} · rho {t.robustness:+.4g} · log p {t.log_p_total:.1f}{outcome}"
        )

    def severity_of(self, record: PanelRun, t: Trajectory) -> Severity:
        """The severity of a listed rollout (computed once per rollout)."""
        key = (record.run_id, t.key)
        if key not in self._severities:
            self._severities[key] = severity(t.gap_m, self.params)
        return self._severities[key]

    def ordered_rollouts(self, record: PanelRun) -> list[Trajectory]:
        """The run's kept rollouts in the Rollouts tab's order (``sort by``), failures only if ticked."""
        with record.lock:
            kept = list(record.trajectories)
        if self.failures_only.value:
            kept = [t for t in kept if t.crashed]
        order = self.rollout_order.value
        if order == "log p":
            return sorted(kept, key=lambda t: -t.log_p_total)
        if order == "severity":
            return sorted(kept, key=lambda t: -self.severity_of(record, t).rank)
        return kept  # kept least robust first

    def _relist(self) -> None:
        with self.lock:
            if self.listed is not None:
                self._set_rollouts(self.listed)

    def _set_rollouts(self, record: PanelRun) -> None:
        if record is not self.listed:
            return  # another run is chosen under Runs
        with record.lock:
            best = record.most_likely_failure
            n_kept = len(record.trajectories)
        trajectories = self.ordered_rollouts(record)
        labels = {}
        if best is not None:
            labels[self.rollout_label(best, True, self.severity_of(record, best))] = best
        labels.update({self.rollout_label(t, sev=self.severity_of(record, t)): t for t in trajectories})
        self._rollout_labels = labels
        current = self.rollout_dropdown.value
        self.rollout_dropdown.options = (NO_ROLLOUT, *labels)
        if current not in labels:
            self.rollout_dropdown.value = NO_ROLLOUT
        if not n_kept:
            self.rollout_html.content = box(f"No rollouts of {html.escape(record.short_label)} yet.", GREY)
            return
        best_text = (
            f"Most likely failure found: stage {best.stage} rollout {best.index}, log p_PEM = "
            f"{best.log_p_total:.1f} nats (the failing rollout most probable under the PEM), "
            f"{self.severity_of(record, best).short}."
            if best is not None
            else "No failure found yet."
        )

        def outcome(t: Trajectory) -> str:
            sev = self.severity_of(record, t)
            return f"<b style=color:{RED}>{html.escape(sev.short)}</b>" if t.crashed else html.escape(sev.short)

        rows = "".join(
            f"<tr><td>{i + 1}</td><td>{t.stage}</td><td>{t.index}</td><td>{t.robustness:+.4g}</td>"
            f"<td>{t.log_p_total:.1f}</td><td style='text-align:left'>{outcome(t)}</td></tr>"
            for i, t in enumerate(trajectories[:10])
        )
        which = " that failed" if self.failures_only.value else ""
        self.rollout_html.content = TABLE_STYLE + (
            f'<div style="margin:0 0.6em 0.5em; font-size:0.8em">{html.escape(best_text)}<br>'
            f"The {n_kept} least robust rollouts of {html.escape(record.short_label)}{which} (metric "
            f"{record.config.metric}), by {html.escape(self.rollout_order.value)}; log p: log-probability under the "
            "PEM, nats:"
            '<table class="pemviz-table" style="width:100%">'
            "<tr><th>#</th><th>stage</th><th>rollout</th><th>robustness</th><th>log p</th><th>outcome</th></tr>"
            f"{rows}</table></div>"
        )

    def _show_default_rollout(self, record: PanelRun) -> None:
        """After a run: choose its most likely failure (else its least-robust rollout), paused at the start."""
        if record is not self.listed:
            return
        for label, t in self._rollout_labels.items():
            if t is record.most_likely_failure or record.most_likely_failure is None:
                if self.rollout_dropdown.value == label:  # the same label (an identical run): no callback
                    self._on_rollout_chosen(label)
                else:
                    self.rollout_dropdown.value = label
                return

    def _after_run(self, record: PanelRun) -> None:
        """A run ended without finishing (stopped, failed): explain its most likely failure, or say it ended."""
        if record is not self.listed or self.shown_record is record:
            return
        self._set_rollouts(record)
        self._show_default_rollout(record)
        if self.shown_record is not record:
            self._clear_scene(
                f"{record.short_label} {'was stopped' if record.status == 'cancelled' else 'failed'} after "
                f"{len(record.stages)} stages, before any rollout to show"
            )

    def _on_rollout_chosen(self, label: str) -> None:
        traj = self._rollout_labels.get(label)
        if traj is None:
            return
        with self.lock:
            record = self.listed or self.record
            scene = record.view.scene if record is not None and record.view is not None else None
            if scene is None:  # a problem without a scene: nothing to replay (the panel runs the braking scenario)
                return
            self.explanation = explain(traj.gap_m, traj.detected, traj.log_p, traj.log_q, scene)
            self.shown = traj
            self.shown_record = record
            self._shown_x = scene_positions(traj, scene)
            self.step_slider.max = traj.n_steps - 1
            self._set_playing(False)
            self._fill_explanation()
            self.shown_step = -1
            if self.step_slider.value != 0:
                self.step_slider.value = 0  # renders step 0 through the slider's callback
            else:
                self._render_step(0)

    def _fill_explanation(self) -> None:
        traj, ex, record = self.shown, self.explanation, self.shown_record
        if traj is None or ex is None or record is None:
            return
        title = f"{record.short_label} {traj.key}"
        plots.fill_strip_plots(self.strip, traj, ex, 0, title, record.view.thresholds)
        charts.fill_controller_plot(self.strip["controller"], ex, 0, title)
        self.explain_html.content = explanation_html(record, traj, ex, title, record.view.scene.dt_s)

    def _toggle_play(self) -> None:
        with self.lock:
            if self.shown is None:
                return
            if not self.playing and int(self.step_slider.value) >= self.shown.n_steps - 1:
                self.step_slider.value = 0
            self._set_playing(not self.playing)

    def _set_playing(self, playing: bool) -> None:
        self.playing = playing
        self.play_button.label = "Pause" if playing else "Play"
        self.play_button.icon = viser.Icon.PLAYER_PAUSE if playing else viser.Icon.PLAYER_PLAY

    def play_tick(self) -> None:
        """Advance the playback by one step (called every dt by the server's player thread)."""
        with self.lock:
            if not self.playing or self.shown is None:
                return
            step = int(self.step_slider.value) + 1
            if step > self.shown.n_steps - 1:
                self._set_playing(False)
                return
            self.step_slider.value = step

    def _build_scene(self) -> None:
        scene = self.client.scene
        p = self.params
        scene.set_up_direction("+z")
        road_len, x0, lane = 90.0, -15.0, 4.0
        scene.add_box(
            "/road", color=C.ROAD, dimensions=(road_len, lane + 1.0, 0.05),
            position=(x0 + road_len / 2, 0.0, -0.03), cast_shadow=False,
        )  # fmt: skip
        edges = np.array(
            [[[x0, s * lane / 2, 0.0], [x0 + road_len, s * lane / 2, 0.0]] for s in (-1, 1)], dtype=np.float32
        )
        scene.add_line_segments("/road/edges", edges, colors=C.ROAD_MARKING, thickness=0.12)
        ticks = np.array([[[x, -lane / 2, 0.01], [x, -lane / 2 - 0.6, 0.01]] for x in range(0, 75, 10)], np.float32)
        scene.add_line_segments("/road/ticks_10m", ticks, colors=C.ROAD_MARKING, thickness=0.08)
        size = (p.ego_length_m, p.vehicle_width_m, CAR_HEIGHT_M)
        lead0 = p.camera_offset_m + p.gap0_m + p.lead_length_m / 2
        self.ego_box = scene.add_box("/ego", color=IDLE, dimensions=size, position=(0.0, 0, CAR_HEIGHT_M / 2))
        self.lead_box = scene.add_box(
            "/lead", color=LEAD, dimensions=(p.lead_length_m, p.vehicle_width_m, CAR_HEIGHT_M),
            position=(lead0, 0.0, CAR_HEIGHT_M / 2),
        )  # fmt: skip
        scene.add_label("/lead/label", "lead", position=(0.0, 0.0, CAR_HEIGHT_M / 2 + 0.5), anchor="bottom-center")
        # zones ahead of the ego's camera, moving with it
        zones = (
            ("brake_zone_10m", p.braking_distance_m, BRAKE_ZONE, f"brakes if the lead is detected within {p.braking_distance_m:g} m"),
            ("crash_zone_2m", p.crash_gap_m, CRASH, f"crash: gap < {p.crash_gap_m:g} m"),
        )  # fmt: skip
        for i, (name, length, rgb, text) in enumerate(zones):
            scene.add_box(
                f"/ego/{name}", color=rgb, dimensions=(length, p.vehicle_width_m + 0.6, 0.02), opacity=0.35,
                position=(p.camera_offset_m + length / 2, 0.0, -CAR_HEIGHT_M / 2 + 0.02), cast_shadow=False,
                receive_shadow=False,
            )  # fmt: skip
            scene.add_label(
                f"/ego/{name}/label", text, position=(0.0, -(p.vehicle_width_m / 2 + 0.8 + 1.2 * i), 0.05),
                anchor="top-center",
            )  # fmt: skip
        cam = p.camera_height_m
        self.gap_line = scene.add_line_segments(
            "/gap", np.array([[[p.camera_offset_m, 0, cam], [lead0 - p.lead_length_m / 2, 0, cam]]], np.float32),
            colors=IDLE, thickness=0.08,
        )  # fmt: skip
        self.scene_label = scene.add_label(
            "/ego/label", "ego: no rollout chosen", position=(0.0, 0.0, CAR_HEIGHT_M / 2 + 1.2), anchor="bottom-center"
        )
        target = np.array([lead0 / 2, 0.0, 0.0])
        self.client.camera.position = tuple(target + CAMERA_OFFSET_M)
        self.client.camera.look_at = tuple(target)

    def _clear_scene(self, why: str) -> None:
        """Back to the idle scene (no rollout shown): the cars at the start, the ego grey."""
        p = self.params
        self.shown, self.shown_record, self.explanation, self._shown_x = None, None, None, None
        self._set_playing(False)
        self.shown_step = -1
        lead0 = p.camera_offset_m + p.gap0_m + p.lead_length_m / 2
        with self.client.atomic():
            self.ego_box.position = (0.0, 0.0, CAR_HEIGHT_M / 2)
            self.ego_box.color = IDLE
            self.lead_box.position = (lead0, 0.0, CAR_HEIGHT_M / 2)
            self.gap_line.colors = np.array(IDLE, dtype=np.uint8)
            self.scene_label.text = "ego: no rollout chosen"
            self.scene_html.content = box(html.escape(why), GREY)
            self.explain_html.content = box(html.escape(why), GREY)

    def _render_step(self, step: int) -> None:
        with self.lock:
            traj, xs, ex, record = self.shown, self._shown_x, self.explanation, self.shown_record
            if traj is None or xs is None or ex is None or record is None:
                return
            t = int(np.clip(step, 0, traj.n_steps - 1))
            self.shown_step = t
            p = self.params
            ego_x, lead_x = float(xs[0][t]), float(xs[1][t])
            detected = bool(traj.detected[t])
            colour = DETECTED if detected else MISSED
            gap = float(traj.gap_m[t])
            cam = p.camera_height_m
            decisive = t in set(ex.decisive.tolist())
            seen = "detected" if detected else ("missed (decisive)" if decisive else "missed")
            with self.client.atomic():
                self.ego_box.position = (ego_x, 0.0, CAR_HEIGHT_M / 2)
                self.ego_box.color = colour
                self.lead_box.position = (lead_x, 0.0, CAR_HEIGHT_M / 2)
                self.gap_line.points = np.array(
                    [[[ego_x + p.camera_offset_m, 0, cam], [lead_x - p.lead_length_m / 2, 0, cam]]], np.float32
                )
                self.gap_line.colors = np.array(colour, dtype=np.uint8)  # (3,): one colour (per-vertex shows white)
                self.scene_label.text = f"{record.short_label} {traj.key} t={t * p.dt_s:.2f}s gap {gap:.2f}m {seen}"
                plots.move_strip_marker(self.strip, t)
            if self.follow.value:
                target = np.array([(ego_x + lead_x) / 2, 0.0, 0.0])
                try:
                    with self.client.atomic():
                        self.client.camera.position = tuple(target + CAMERA_OFFSET_M)
                        self.client.camera.look_at = tuple(target)
                except (AssertionError, ValueError):  # the client has not reported its camera yet
                    pass
            mark = {"detected": "detected", "missed": f"<b style='color:rgb{MISSED}'>missed</b>",
                    "missed (decisive)": f"<b style='color:{RED}'>missed (decisive)</b>"}[seen]  # fmt: skip
            crash = f" · <b style='color:{RED}'>{html.escape(ex.severity.short)}</b>" if traj.crashed else ""
            c = ex.controller
            brake = "applied" if c.brake_applied[t] else ("commanded" if c.brake_command[t] else "off")
            self.scene_html.content = box(
                f"Scene: <b>{html.escape(record.short_label)} {traj.key}</b> (stage {traj.stage}, rollout "
                f"{traj.index}{crash}) · step {t} (t = {t * p.dt_s:.2f} s) · gap {gap:.2f} m · ego "
                f"{traj.ego_speed_mps[t]:.2f} m/s · lead {traj.lead_speed_mps[t]:.2f} m/s · detector: {mark} · "
                f"brake {brake} · acceleration {c.accel_mps2[t]:+.2f} m/s^2",
                RED if traj.crashed else BLUE,
            )


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
        self._refresh()

    def _refresh(self) -> None:
        self.session._refresh_plots()
        self.session._refresh_runs()

    def on_run_finished(self, event: RunFinished) -> None:
        self.session._status(f"{self.record.short_label}: finished in {self.record.elapsed_s():.1f} s", GREEN)
        self.session._show_default_rollout(self.record)


def _display_path(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)
