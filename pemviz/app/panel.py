"""The viser panel of ``pemviz serve``: run experiments from the browser and watch them.

Layout:

- the control panel (right): Run / Stop, a run and a stage progress bar, the final estimate, and tabs
  *Experiment* (metric, alpha, sigma, K, N, N_e, seed, PEM, simulator, preset, advanced knobs),
  *Rollouts* (the least-robust rollouts of the run; choosing one plays it in the 3D scene, with a step
  slider and play / pause) and *Runs* (the runs kept for comparison and the ``.rrd`` export);
- a plots panel (left) with tabs *Live* (the proposal q(detect | gap) per stage beside the PEM, and
  gamma, failures / N, log10 mu_hat and NLL per stage for every kept run) and *Compare* (each kept run's
  proposal curves side by side, as in the paper's Fig. 4);
- the 3D scene: the road and the two cars as boxes at their true size; the ego is green at steps where
  the detector saw the lead and red where it missed.

The experiment runs in a worker thread (:class:`pemviz.engine.Experiment`); the panel only listens to its
events and stops it through the cancel token. All GUI and scene state is the server's, so every browser
tab shows the same run.
"""

from __future__ import annotations

import html
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import viser
import viser.uplot

import pemviz.config
from pemviz.app.runs import (
    MAX_RUNS,
    PANEL_PRESETS,
    RunRecord,
    Trajectory,
    config_from_values,
    config_has,
    export_path,
    export_run,
    scene_positions,
)
from pemviz.config import FINAL_MODES, METHODS, METRICS, WEIGHT_MODES, ConfigError, ExperimentConfig
from pemviz.engine import (
    Event,
    FinalEstimate,
    RolloutsSampled,
    RunCancelled,
    RunFinished,
    RunStarted,
    StageFinished,
    StageStarted,
)
from pemviz.sampling import format_probability
from pemviz.scenarios.braking import BrakingParams

RUN_COLOURS = ("#1f6fd1", "#d6402b", "#2a9d4b")
"""Series colour of a run in the comparison plots: run id modulo 3 (the kept runs are consecutive)."""
DETECTED_RGB = (40, 170, 80)
MISSED_RGB = (220, 50, 40)
LEAD_RGB = (95, 110, 140)
CAR_HEIGHT_M = 1.5
CAMERA_OFFSET_M = np.array([-5.0, -20.0, 13.0])
"""Initial camera position relative to the point between the cars (metres; behind-left, above)."""
NO_ROLLOUT = "(choose a rollout)"
TABLE_STYLE = (
    "<style>.pemviz-table{border-collapse:collapse;text-align:right}"
    ".pemviz-table td,.pemviz-table th{padding:0.05em 0.3em}"
    ".pemviz-table tr:nth-child(even){background:#0000000a}</style>"
)
CRASH_CELL = '<b style="color:#d6402b">crash</b>'
STAGE_PLOTS = (
    ("gamma", "gamma per stage"),
    ("failure_rate", "failures / N per stage"),
    ("log10_mu_hat", "log10 mu_hat per stage"),
    ("nll", "NLL of failures per stage (nats)"),
)


def stage_colour(stage: int, n_stages: int) -> str:
    """Blue (early) to orange (late), as in the rerun recording."""
    f = stage / max(1, n_stages)
    return f"rgb({int(40 + 215 * f)}, {int(110 + 40 * f)}, {int(230 - 200 * f)})"


def _fmt(x: float, spec: str) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, spec)


def _box(text: str, colour: str) -> str:
    return (
        f'<div style="margin:0 0.6em 0.5em; padding:0.4em 0.6em; border-radius:4px; font-size:0.85em; '
        f'border-left:4px solid {colour}; background:{colour}14">{text}</div>'
    )


class PanelApp:
    """The ``pemviz serve`` application: a viser server with the panel, its runs and the 3D scene.

    Args:
        host: interface to bind (``127.0.0.1``: this machine only).
        port: TCP port (0: any free port; viser tries the next ports when it is taken; see :attr:`port`).
        recordings_dir: where exports are written (created on the first export).
        config: the controls' initial values (default: ``preset``'s settings).
        preset: the preset the panel starts with, one of :data:`pemviz.app.runs.PANEL_PRESETS`.
        warm_up: import the simulator and run a tiny experiment in the background, so that the first
            Run starts at full speed.
        verbose: let viser print its banner.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8080,
        *,
        recordings_dir: str | Path = "recordings",
        config: ExperimentConfig | None = None,
        preset: str = pemviz.config.DEFAULT_PRESET,
        warm_up: bool = True,
        verbose: bool = False,
    ) -> None:
        if preset not in PANEL_PRESETS:
            raise ValueError(f"preset {preset!r} is invalid: use one of {', '.join(PANEL_PRESETS)}")
        self.preset_name = preset
        self.config0 = config or ExperimentConfig(**PANEL_PRESETS[preset])
        self.recordings_dir = Path(recordings_dir)
        self.params = BrakingParams()
        self.lock = threading.RLock()
        self.runs: list[RunRecord] = []
        self._next_run_id = 1
        self._worker: threading.Thread | None = None
        self._cancel = threading.Event()
        self._stop_requested_at: float | None = None
        self.last_stop_latency_s: float | None = None
        """Seconds from Stop to the worker's end, for the last stopped run."""
        self.shown: Trajectory | None = None
        """The rollout the 3D scene shows."""
        self.shown_step = 0
        self._shown_x: tuple[np.ndarray, np.ndarray] | None = None
        self.playing = False
        self._closed = threading.Event()
        self._rollout_labels: dict[str, Trajectory] = {}
        self.last_export: Path | None = None

        self.server = viser.ViserServer(host=host, port=port, label="pemviz", verbose=verbose)
        self.host = host
        self._build_gui()
        self._build_scene()
        self.server.on_client_connect(self._on_connect)
        self._validate()
        self._warm = threading.Thread(target=self._warm_up, name="pemviz-warm-up", daemon=True)
        if warm_up:
            self._warm.start()
        self._player = threading.Thread(target=self._play_loop, name="pemviz-player", daemon=True)
        self._player.start()

    # == public API ================================================================================
    @property
    def port(self) -> int:
        """The port the server actually bound."""
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    @property
    def current(self) -> RunRecord | None:
        """The latest run (running or done), or None before the first."""
        with self.lock:
            return self.runs[-1] if self.runs else None

    @property
    def running(self) -> bool:
        return self._worker is not None and self._worker.is_alive()

    def control_values(self) -> dict[str, Any]:
        """The controls' values as :class:`ExperimentConfig` fields."""
        values = {name: handle.value for name, handle in self.controls.items()}
        if values.get("pem") == self._default_pem:
            values["pem"] = self.config0.pem
        return values

    def read_config(self) -> ExperimentConfig:
        """The config the controls describe; raises :class:`ConfigError` with a one-line message."""
        return config_from_values(self.control_values())

    def start_run(self) -> str | None:
        """Start a run with the controls' values; returns an error message instead when refused."""
        with self.lock:
            if self.running:
                return "a run is going: press Stop first"
            try:
                cfg = self.read_config()
            except ConfigError as exc:
                self._show_error(f"Run refused: {exc}")
                return str(exc)
            self._show_error("")
            record = RunRecord(self._next_run_id, cfg)
            self._next_run_id += 1
            self.runs = (self.runs + [record])[-MAX_RUNS:]
            self._cancel = threading.Event()
            self._stop_requested_at = None
            self._worker = threading.Thread(
                target=self._work, args=(record, self._cancel), name=f"pemviz-run-{record.run_id}", daemon=True
            )
            self._set_running_ui(True)
            self._status(f"{record.label}: starting ...")
            self.result_html.content = ""
            self._set_rollouts(record)
            self.export_name.value = f"run{record.run_id}-{cfg.metric}"
            self._refresh_plots()
            self._worker.start()
        return None

    def stop_run(self) -> None:
        """Set the running experiment's cancel token (the engine stops at its next check)."""
        with self.lock:
            if not self.running:
                return
            self._stop_requested_at = time.perf_counter()
            self._cancel.set()
            self.stop_button.disabled = True
            self._status("stopping ...")

    def wait_for_run(self, timeout: float | None = None) -> bool:
        """Block until the current run's worker ends; True when it has."""
        worker = self._worker
        if worker is None:
            return True
        worker.join(timeout)
        return not worker.is_alive()

    def select_rollout(self, label: str) -> None:
        """Show the rollout with this list label (what choosing it in the panel does)."""
        self.rollout_dropdown.value = label

    def export_current(self, name: str) -> Path:
        """Write the latest run to ``recordings_dir / <sanitised name>.rrd``.

        Raises:
            ValueError: no run yet, or an unusable name.
        """
        record = self.current
        if record is None or not record.events:
            raise ValueError("nothing to export yet: run an experiment first")
        path = export_path(self.recordings_dir, name)
        export_run(record, path)
        self.last_export = path
        return path

    def close(self) -> None:
        """Cancel a running experiment, wait for it (up to 10 s) and stop the server."""
        self._closed.set()
        self._cancel.set()
        self.wait_for_run(10.0)
        self.server.stop()

    # == GUI =======================================================================================
    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_width="large", show_share_button=False, brand_color=(31, 111, 209))
        gui.set_panel_label("pemviz")
        gui.add_markdown(
            "**pemviz**: adaptive importance sampling of a PEM-driven braking scenario "
            "(Innes & Ramamoorthy 2022). Set the experiment, press **Run**."
        )
        self.run_button = gui.add_button("Run", color="green", icon=viser.Icon.PLAYER_PLAY)
        self.stop_button = gui.add_button("Stop", color="red", icon=viser.Icon.PLAYER_STOP, disabled=True)
        self.status_html = gui.add_html(_box("idle", "#888888"))
        self.run_progress = gui.add_progress_bar(0.0, color="blue")
        self.stage_progress = gui.add_progress_bar(0.0, color="teal", animated=False)
        self.result_html = gui.add_html("")
        self.error_html = gui.add_html("")

        tabs = gui.add_tab_group()
        with tabs.add_tab("Experiment", viser.Icon.SETTINGS):
            self._build_controls()
        with tabs.add_tab("Rollouts", viser.Icon.CAR):
            self._build_rollouts()
        with tabs.add_tab("Runs", viser.Icon.CHART_LINE):
            self._build_runs_tab()

        self.run_button.on_click(lambda _: self.start_run())
        self.stop_button.on_click(lambda _: self.stop_run())

        panel = gui.add_panel()
        with panel.add_tab("Live", viser.Icon.CHART_LINE):
            self.proposal_plot = gui.add_uplot(
                data=(np.linspace(0, 13, 2), np.full(2, np.nan)),
                series=(viser.uplot.Series(label="gap (m)"), viser.uplot.Series(label="PEM", stroke="black")),
                **self._curve_plot_options("q(detect | gap) per stage vs PEM"),
            )
            self.stage_plots = {}
            for key, title in STAGE_PLOTS:
                self.stage_plots[key] = gui.add_uplot(
                    data=(np.arange(2, dtype=np.float64), np.full(2, np.nan)),
                    series=(viser.uplot.Series(label="stage"), viser.uplot.Series(label="-")),
                    title=title,
                    scales={"x": viser.uplot.Scale(time=False, auto=True)},
                    legend=viser.uplot.Legend(show=True),
                    height=150,
                )
        with panel.add_tab("Compare", viser.Icon.A_B):
            self.compare_html = gui.add_html("")
            self.compare_plots = [
                gui.add_uplot(
                    data=(np.linspace(0, 13, 2), np.full(2, np.nan)),
                    series=(viser.uplot.Series(label="gap (m)"), viser.uplot.Series(label="PEM", stroke="black")),
                    **self._curve_plot_options(f"slot {i + 1}: no run yet", height=190),
                )
                for i in range(MAX_RUNS)
            ]
        panel.dock_left()
        panel.set_width(430)
        gui.main_panel.dock_right()

    @staticmethod
    def _curve_plot_options(title: str, height: int = 230) -> dict[str, Any]:
        return dict(
            title=title,
            scales={
                "x": viser.uplot.Scale(time=False, auto=False, range=(0.0, 13.0)),
                "y": viser.uplot.Scale(auto=False, range=(0.0, 1.0)),
            },
            legend=viser.uplot.Legend(show=True),
            height=height,
        )

    def _build_controls(self) -> None:
        gui = self.server.gui
        c0 = self.config0
        from pemviz.pem import DEFAULT_PEM_NAME, assets_dir

        simulators = _simulators()

        shipped = sorted(p.stem[len("pem_") :] for p in assets_dir().glob("pem_*.pt")) or [DEFAULT_PEM_NAME]
        self._default_pem = DEFAULT_PEM_NAME if DEFAULT_PEM_NAME in shipped else shipped[0]
        pem_options = list(shipped) + ([c0.pem] if c0.pem and c0.pem not in shipped else [])
        pem0 = c0.pem if c0.pem else self._default_pem

        self.preset = gui.add_dropdown(
            "preset", tuple(PANEL_PRESETS), initial_value=self.preset_name,
            hint="paper: the paper's settings; authors-code: how the authors' code ran; quick: a few-second run",
        )  # fmt: skip
        self.controls: dict[str, Any] = {}
        add = self.controls.__setitem__
        add("metric", gui.add_dropdown("metric", METRICS, initial_value=c0.metric, hint="robustness semantics"))
        add("smoothing", gui.add_number("alpha", float(c0.smoothing), step=0.001, hint="smoothing alpha in (0, 1]"))
        add("quantile_level", gui.add_number("sigma", float(c0.quantile_level), step=0.001, hint="in [0.5, 1)"))
        add("n_stages", gui.add_number("K", int(c0.n_stages), step=1, hint="cross-entropy stages"))
        add("n_per_stage", gui.add_number("N", int(c0.n_per_stage), step=1, hint="rollouts per stage"))
        add("n_final", gui.add_number("N_e", int(c0.n_final), step=1, hint="rollouts of the final estimate"))
        add("seed", gui.add_number("seed", int(c0.seed), step=1))
        add("pem", gui.add_dropdown("PEM", tuple(pem_options), initial_value=pem0, hint="shipped PEM (assets/)"))
        sim0 = getattr(c0, "sim", simulators[0])
        sim = gui.add_dropdown(
            "simulator", simulators, initial_value=sim0 if sim0 in simulators else simulators[0],
            disabled=len(simulators) < 2 or not config_has("sim"), hint="back-end of the braking scenario",
        )  # fmt: skip
        add("sim", sim)
        with gui.add_folder("advanced", expand_by_default=False):
            add("method", gui.add_dropdown("method", METHODS, initial_value=c0.method))
            add("ce_epochs", gui.add_number("CE epochs", int(c0.ce_epochs), step=1))
            add("pretrain_rollouts", gui.add_number("pretrain rollouts", int(c0.pretrain_rollouts), step=1))
            add("pretrain_epochs", gui.add_number("pretrain epochs", int(c0.pretrain_epochs), step=1))
            add("learning_rate", gui.add_number("learning rate", float(c0.learning_rate), step=0.0001))
            add("weights", gui.add_dropdown("weights", WEIGHT_MODES, initial_value=c0.weights))
            executors = getattr(pemviz.config, "EXECUTORS", ())
            if config_has("executor") and executors:
                add("executor", gui.add_dropdown("executor", executors, initial_value=c0.executor))
            add("final_estimate", gui.add_dropdown("final estimate", FINAL_MODES, initial_value=c0.final_estimate))
        gui.add_markdown("Changes apply to the next run.")
        for handle in self.controls.values():
            handle.on_update(lambda _: self._validate())
        self.preset.on_update(lambda _: self._apply_preset(self.preset.value))

    def _apply_preset(self, name: str) -> None:
        base = ExperimentConfig()
        keep = {"metric", "seed", "pem", "sim", "method"}
        values = {**{k: getattr(base, k) for k in self.controls if hasattr(base, k)}, **PANEL_PRESETS.get(name, {})}
        for key, value in values.items():
            if key in keep and key not in PANEL_PRESETS.get(name, {}):
                continue
            handle = self.controls.get(key)
            if handle is not None:
                handle.value = value
        self._validate()

    def _build_rollouts(self) -> None:
        gui = self.server.gui
        self.rollout_dropdown = gui.add_dropdown(
            "rollout", (NO_ROLLOUT,), initial_value=NO_ROLLOUT, hint="least robust first (the run's metric)"
        )
        self.rollout_html = gui.add_html(_box("No rollouts yet: run an experiment.", "#888888"))
        self.step_slider = gui.add_slider("step", min=0, max=self.params.n_steps - 1, step=1, initial_value=0)
        self.play_button = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
        self.follow = gui.add_checkbox("follow cars", True, hint="move every tab's camera along with the cars")
        self.scene_html = gui.add_html("")
        self.rollout_dropdown.on_update(lambda _: self._on_rollout_chosen(self.rollout_dropdown.value))
        self.step_slider.on_update(lambda _: self._render_step(int(self.step_slider.value)))
        self.play_button.on_click(lambda _: self._toggle_play())

    def _build_runs_tab(self) -> None:
        gui = self.server.gui
        self.runs_html = gui.add_html(_box("No runs yet.", "#888888"))
        gui.add_markdown(f"Up to {MAX_RUNS} runs are kept side by side (plots: *Live* and *Compare* tabs).")
        with gui.add_folder("export to rerun (.rrd)"):
            self.export_name = gui.add_text("export name", "run")
            self.export_button = gui.add_button("Export current run", icon=viser.Icon.DOWNLOAD)
            self.export_html = gui.add_html("")
        self.export_button.on_click(self._on_export)

    # -- state -> GUI ------------------------------------------------------------------------------
    def _status(self, text: str, colour: str = "#1f6fd1") -> None:
        self.status_html.content = _box(html.escape(text), colour)

    def _show_error(self, text: str) -> None:
        self.error_html.content = _box(f"<b>Invalid setting.</b> {html.escape(text)}", "#d6402b") if text else ""

    def _validate(self) -> None:
        try:
            self.read_config()
        except ConfigError as exc:
            self._show_error(str(exc))
            return
        self._show_error("")

    def _set_running_ui(self, running: bool) -> None:
        self.run_button.disabled = running
        self.stop_button.disabled = not running
        self.stage_progress.animated = running

    def _set_progress(self, record: RunRecord) -> None:
        run, stage = record.progress()
        self.run_progress.value = run
        self.stage_progress.value = stage

    # == the worker ================================================================================
    def _warm_up(self) -> None:
        """Import highway-env and run torch once, so that the first real run is not slowed by them."""
        try:
            from pemviz.engine import Experiment

            tiny = ExperimentConfig(
                n_stages=1, n_per_stage=2, n_final=1, ce_epochs=1, pretrain_rollouts=1, pretrain_epochs=1
            )
            Experiment(tiny, [], self._closed).run()
        except Exception:  # warming up is best effort; a real run reports its own errors
            pass

    def _work(self, record: RunRecord, cancel: threading.Event) -> None:
        if self._warm.is_alive():
            self._warm.join()
        try:
            from pemviz.engine import Experiment

            Experiment(record.config, [lambda e: self._on_event(record, e)], cancel).run()
        except Exception as exc:  # a bad PEM file, a simulator error: show it, keep serving
            record.fail(f"{type(exc).__name__}: {exc}")
            self._status(f"{record.label} failed: {record.message}", "#d6402b")
        finally:
            with self.lock:
                if self._stop_requested_at is not None:
                    self.last_stop_latency_s = time.perf_counter() - self._stop_requested_at
                self._set_running_ui(False)
                if record.status == "cancelled":
                    latency = self.last_stop_latency_s
                    self._status(
                        f"{record.label}: stopped after {len(record.stages)} stages"
                        + (f" ({latency:.2f} s after Stop)" if latency is not None else ""),
                        "#c98a00",
                    )
                self._refresh_runs()

    def _on_event(self, record: RunRecord, event: Event) -> None:
        record(event)
        with self.lock:
            if record is not self.current:
                return
            if isinstance(event, RunStarted):
                self._status(f"{record.label}: started")
            elif isinstance(event, StageStarted):
                self._status(f"{record.label} · {self._stage_text(record, event.stage, event.kind)}: sampling "
                             f"{event.n_rollouts} rollouts")  # fmt: skip
            elif isinstance(event, RolloutsSampled):
                cfg = record.config
                doing = {
                    "pretrain": f"pretraining the proposal ({cfg.pretrain_epochs} epochs)",
                    "ce": f"cross-entropy update ({cfg.ce_epochs} epochs)",
                }.get(event.kind, "estimating")
                self._status(f"{record.label} · {self._stage_text(record, event.stage, event.kind)}: {doing}")
                self._set_rollouts(record)
            elif isinstance(event, StageFinished):
                self._refresh_plots()
                self._refresh_runs()
            elif isinstance(event, FinalEstimate):
                self.result_html.content = self._final_text(record, event)
                self._refresh_plots()
                self._refresh_runs()
            elif isinstance(event, RunFinished):
                self._status(f"{record.label}: finished", "#2a9d4b")
            elif isinstance(event, RunCancelled):
                self._status(f"{record.label}: cancelled", "#c98a00")
            self._set_progress(record)

    @staticmethod
    def _stage_text(record: RunRecord, stage: int, kind: str) -> str:
        total = record.n_stage_events
        name = {"pretrain": "pretraining", "ce": "CE stage", "final": "final batch"}.get(kind, kind)
        return f"stage {stage + (1 if record.config.method == 'adaptive' else 0)}/{total} ({name})"

    @staticmethod
    def _final_text(record: RunRecord, ev: FinalEstimate) -> str:
        e = ev.estimate
        return _box(
            f"<b>Final estimate</b> ({html.escape(record.label)}): mu_hat = <b>{format_probability(e.log_mu_hat, 4)}"
            f"</b> &nbsp;·&nbsp; failures {e.n_failures}/{e.n} &nbsp;·&nbsp; NLL {_fmt(e.nll_mean, '.2f')} nats "
            f"&nbsp;·&nbsp; ESS {_fmt(e.ess, '.2f')} &nbsp;·&nbsp; {ev.n_simulations} simulations in "
            f"{ev.wall_s:.1f} s",
            "#2a9d4b",
        )

    # == plots =====================================================================================
    def _refresh_plots(self) -> None:
        with self.lock:
            runs = list(self.runs)
            record = self.current
        with self.server.atomic():
            if record is not None:
                self._fill_curve_plot(self.proposal_plot, record, f"{record.label}: q(detect | gap) per stage vs PEM")
            for i, plot in enumerate(self.compare_plots):
                if i < len(runs):
                    r = runs[i]
                    fin = r.final.estimate if r.final is not None else None
                    mu = f", mu_hat {format_probability(fin.log_mu_hat)}" if fin is not None else ""
                    self._fill_curve_plot(plot, r, f"{r.label}{mu}")
            for key, plot in self.stage_plots.items():
                self._fill_stage_plot(plot, key, runs)

    def _fill_curve_plot(self, plot: viser.GuiUplotHandle, record: RunRecord, title: str) -> None:
        with record.lock:
            grid = record.curve_grid_m
            pem = record.pem_curve
            stages = [s for s in record.stages if not np.all(np.isnan(s.proposal_curve))]
        if grid.size == 0:
            return
        n_colour = max(1, record.config.n_stages if record.config.method == "adaptive" else 1)
        series = [viser.uplot.Series(label="gap (m)"), viser.uplot.Series(label="PEM", stroke="black", width=2)]
        data = [grid, pem]
        for s in stages:
            name = {"pretrain": "pretrained", "final": "final"}.get(s.kind, f"stage {s.stage}")
            if s.kind == "final":
                continue  # the final batch samples from the last stage's proposal: the same curve
            series.append(viser.uplot.Series(label=name, stroke=stage_colour(s.stage, n_colour), width=1.5))
            data.append(np.asarray(s.proposal_curve, dtype=np.float64))
        plot.title = title
        plot.series = tuple(series)
        plot.data = tuple(data)

    @staticmethod
    def _fill_stage_plot(plot: viser.GuiUplotHandle, key: str, runs: list[RunRecord]) -> None:
        if not runs:
            return
        n = max(r.n_stage_events for r in runs)
        x = np.arange(n, dtype=np.float64)
        series = [viser.uplot.Series(label="stage")]
        data = [x]
        for r in runs:
            values = r.stage_series(key)
            y = np.full(n, np.nan)
            for stage, value in values.items():
                if 0 <= stage < n:
                    y[stage] = value
            colour = RUN_COLOURS[(r.run_id - 1) % len(RUN_COLOURS)]
            series.append(
                viser.uplot.Series(
                    label=f"run {r.run_id} ({r.config.metric})", stroke=colour, width=2,
                    points={"show": True, "size": 5, "fill": colour},
                )
            )  # fmt: skip
            data.append(y)
        plot.series = tuple(series)
        plot.data = tuple(data)
        # uPlot's auto-range breaks on NaN (stages without a value): give the y range explicitly.
        plot.scales = {
            "x": viser.uplot.Scale(time=False, auto=True),
            "y": viser.uplot.Scale(auto=False, range=y_range(key, data[1:])),
        }

    def _refresh_runs(self) -> None:
        with self.lock:
            runs = list(self.runs)
        if not runs:
            return
        rows = []
        for r in runs:
            cfg = r.config
            fin = r.final.estimate if r.final is not None else None
            colour = RUN_COLOURS[(r.run_id - 1) % len(RUN_COLOURS)]
            rows.append(
                f'<tr><td style="color:{colour}"><b>{r.run_id}</b></td><td style="text-align:left">{cfg.metric}</td>'
                f"<td>{cfg.smoothing:g}</td><td>{cfg.quantile_level:g}</td>"
                f"<td>{format_probability(fin.log_mu_hat) if fin else '-'}</td>"
                f"<td>{f'{fin.n_failures}/{fin.n}' if fin else '-'}</td>"
                f"<td>{_fmt(fin.nll_mean if fin else None, '.1f')}</td>"
                f"<td>{r.status}</td></tr>"
            )
        table = (
            TABLE_STYLE + '<table class="pemviz-table" style="width:100%; font-size:0.75em; white-space:nowrap">'
            '<tr><th>run</th><th style="text-align:left">metric</th><th>alpha</th><th>sigma</th><th>mu_hat</th>'
            "<th>fail</th><th>NLL</th><th>status</th></tr>" + "".join(rows) + "</table>"
        )
        box = f'<div style="margin:0 0.6em 0.5em">{table}</div>'
        self.runs_html.content = box
        self.compare_html.content = box

    # == rollouts and the 3D scene =================================================================
    @staticmethod
    def rollout_label(t: Trajectory) -> str:
        """The rollout list entry: stage, rollout, robustness, log-weight (nats), crash flag.

        No rank in it, so that a chosen rollout stays chosen while later stages re-rank the list.
        """
        crash = " · CRASH" if t.crashed else ""
        return f"stage {t.stage} rollout {t.index} · rho {t.robustness:+.4g} · log w {t.log_weight:.1f}{crash}"

    def _set_rollouts(self, record: RunRecord) -> None:
        trajectories = list(record.trajectories)
        labels = {self.rollout_label(t): t for t in trajectories}
        self._rollout_labels = labels
        current = self.rollout_dropdown.value
        self.rollout_dropdown.options = (NO_ROLLOUT, *labels)
        if current not in labels:
            self.rollout_dropdown.value = NO_ROLLOUT
        if not trajectories:
            self.rollout_html.content = _box("No rollouts yet.", "#888888")
            return
        rows = "".join(
            f"<tr><td>{i + 1}</td><td>{t.stage}</td><td>{t.index}</td><td>{t.robustness:+.4g}</td>"
            f"<td>{t.log_weight:.1f}</td><td>{CRASH_CELL if t.crashed else 'no'}</td></tr>"
            for i, t in enumerate(trajectories[:10])
        )
        self.rollout_html.content = TABLE_STYLE + (
            f'<div style="margin:0 0.6em 0.5em; font-size:0.8em">Least robust rollouts of {html.escape(record.label)} '
            f"(metric {record.config.metric}; log w in nats):"
            '<table class="pemviz-table" style="width:100%">'
            "<tr><th>#</th><th>stage</th><th>rollout</th><th>robustness</th><th>log w</th><th>crash</th></tr>"
            f"{rows}</table></div>"
        )

    def _on_rollout_chosen(self, label: str) -> None:
        traj = self._rollout_labels.get(label)
        if traj is None:
            return
        with self.lock:
            self.shown = traj
            self._shown_x = scene_positions(traj, self.params)
            self.step_slider.max = traj.n_steps - 1
            self.shown_step = -1
            if self.step_slider.value != 0:
                self.step_slider.value = 0  # renders step 0 through the slider's callback
            else:
                self._render_step(0)
            self._set_playing(True)

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

    def _play_loop(self) -> None:
        dt = self.params.dt_s
        while not self._closed.wait(dt):
            with self.lock:
                if not self.playing or self.shown is None:
                    continue
                step = int(self.step_slider.value) + 1
                if step > self.shown.n_steps - 1:
                    self._set_playing(False)
                    continue
                self.step_slider.value = step

    def _build_scene(self) -> None:
        scene = self.server.scene
        p = self.params
        scene.set_up_direction("+z")
        road_len, x0 = 90.0, -15.0
        lane = 4.0
        scene.add_box(
            "/road", color=(70, 70, 75), dimensions=(road_len, lane + 1.0, 0.05),
            position=(x0 + road_len / 2, 0.0, -0.03), cast_shadow=False,
        )  # fmt: skip
        edges = np.array(
            [[[x0, s * lane / 2, 0.0], [x0 + road_len, s * lane / 2, 0.0]] for s in (-1, 1)], dtype=np.float32
        )
        scene.add_line_segments("/road/edges", edges, colors=(235, 235, 235), thickness=0.12)
        ticks = np.array([[[x, -lane / 2, 0.01], [x, -lane / 2 - 0.6, 0.01]] for x in range(0, 75, 10)], np.float32)
        scene.add_line_segments("/road/ticks_10m", ticks, colors=(235, 235, 235), thickness=0.08)
        size = (p.ego_length_m, p.vehicle_width_m, CAR_HEIGHT_M)
        ego0 = 0.0
        lead0 = ego0 + p.camera_offset_m + p.gap0_m + p.lead_length_m / 2
        self.ego_box = scene.add_box("/ego", color=DETECTED_RGB, dimensions=size, position=(ego0, 0, CAR_HEIGHT_M / 2))
        self.lead_box = scene.add_box(
            "/lead", color=LEAD_RGB, dimensions=(p.lead_length_m, p.vehicle_width_m, CAR_HEIGHT_M),
            position=(lead0, 0.0, CAR_HEIGHT_M / 2),
        )  # fmt: skip
        # zones ahead of the ego's camera, moving with it: the controller brakes only for a lead detected
        # inside 10 m (yellow); a gap under 2 m is a crash (red)
        zones = (
            ("brake_zone_10m", p.braking_distance_m, (240, 200, 40)),
            ("crash_zone_2m", p.crash_gap_m, (230, 60, 50)),
        )
        for name, length, rgb in zones:
            scene.add_box(
                f"/ego/{name}", color=rgb, dimensions=(length, p.vehicle_width_m + 0.6, 0.02), opacity=0.35,
                position=(p.camera_offset_m + length / 2, 0.0, -CAR_HEIGHT_M / 2 + 0.02), cast_shadow=False,
                receive_shadow=False,
            )  # fmt: skip
        cam = p.camera_height_m
        self.gap_line = scene.add_line_segments(
            "/gap", np.array([[[ego0 + p.camera_offset_m, 0, cam], [lead0 - p.lead_length_m / 2, 0, cam]]], np.float32),
            colors=DETECTED_RGB, thickness=0.08,
        )  # fmt: skip
        self.scene_label = scene.add_label(
            "/ego/label", "ego (start)", position=(0.0, 0.0, CAR_HEIGHT_M / 2 + 1.2), anchor="bottom-center"
        )
        target = np.array([(ego0 + lead0) / 2, 0.0, 0.0])
        self.server.initial_camera.position = tuple(target + CAMERA_OFFSET_M)
        self.server.initial_camera.look_at = tuple(target)

    def _render_step(self, step: int) -> None:
        with self.lock:
            traj, xs = self.shown, self._shown_x
            if traj is None or xs is None:
                return
            t = int(np.clip(step, 0, traj.n_steps - 1))
            self.shown_step = t
            p = self.params
            ego_x, lead_x = float(xs[0][t]), float(xs[1][t])
            detected = bool(traj.detected[t])
            colour = DETECTED_RGB if detected else MISSED_RGB
            gap = float(traj.gap_m[t])
            cam = p.camera_height_m
            with self.server.atomic():
                self.ego_box.position = (ego_x, 0.0, CAR_HEIGHT_M / 2)
                self.ego_box.color = colour
                self.lead_box.position = (lead_x, 0.0, CAR_HEIGHT_M / 2)
                self.gap_line.points = np.array(
                    [[[ego_x + p.camera_offset_m, 0, cam], [lead_x - p.lead_length_m / 2, 0, cam]]], np.float32
                )
                self.gap_line.colors = np.array(colour, dtype=np.uint8)  # (3,): one colour (per-vertex shows white)
                self.scene_label.text = f"{traj.key} t={t * p.dt_s:.2f}s gap {gap:.2f}m"
            if self.follow.value:
                self._follow(np.array([(ego_x + lead_x) / 2, 0.0, 0.0]))
            seen = "detected" if detected else "<b style='color:#d6402b'>missed</b>"
            crash = " · <b style='color:#d6402b'>CRASH</b>" if traj.crashed else ""
            self.scene_html.content = _box(
                f"Scene: <b>{traj.key}</b> (stage {traj.stage}, rollout {traj.index}{crash}) · step {t} "
                f"(t = {t * p.dt_s:.2f} s) · gap {gap:.2f} m · ego {traj.ego_speed_mps[t]:.2f} m/s · lead "
                f"{traj.lead_speed_mps[t]:.2f} m/s · detector: {seen}",
                "#d6402b" if traj.crashed else "#1f6fd1",
            )

    def _follow(self, target: np.ndarray, clients=None) -> None:
        """Put every client's camera at ``target + CAMERA_OFFSET_M``, looking at ``target`` (a chase view)."""
        for client in (clients if clients is not None else self.server.get_clients().values()):
            try:
                with client.atomic():
                    client.camera.position = tuple(target + CAMERA_OFFSET_M)
                    client.camera.look_at = tuple(target)  # after position: position moves look_at along
            except (AssertionError, ValueError):  # the client has not reported its camera yet
                continue

    def _on_connect(self, client: viser.ClientHandle) -> None:
        with self.lock:
            xs, step = self._shown_x, self.shown_step
            if xs is None or not self.follow.value or step < 0:
                return
            target = np.array([(xs[0][step] + xs[1][step]) / 2, 0.0, 0.0])
        for _ in range(50):  # the camera state arrives shortly after the connection
            try:
                client.camera.look_at
                break
            except AssertionError:
                time.sleep(0.1)
        self._follow(target, [client])

    # == export ====================================================================================
    def _on_export(self, event: viser.GuiEvent) -> None:
        name = self.export_name.value
        try:
            path = self.export_current(name)
        except (ValueError, OSError) as exc:
            self.export_html.content = _box(f"<b>Export refused.</b> {html.escape(str(exc))}", "#d6402b")
            return
        shown = _display_path(path)
        size_kb = path.stat().st_size / 1024
        self.export_html.content = _box(
            f"Saved <b>{html.escape(shown)}</b> ({size_kb:.0f} KB). Open it with "
            f"<code>rerun {html.escape(shown)}</code>; the download link is in this tab's notification.",
            "#2a9d4b",
        )
        client = event.client
        if client is not None:
            client.send_file_download(path.name, path.read_bytes(), save_immediately=False)


def y_range(key: str, series: list[np.ndarray]) -> tuple[float, float]:
    """A padded y range covering the finite values of ``series`` ((0, 1) for rates or without values)."""
    if key == "failure_rate":
        return (-0.05, 1.05)
    values = np.concatenate([np.asarray(s, dtype=np.float64).ravel() for s in series]) if series else np.zeros(0)
    values = values[np.isfinite(values)]
    if values.size == 0:
        return (0.0, 1.0)
    lo, hi = float(values.min()), float(values.max())
    pad = 0.08 * (hi - lo) if hi > lo else max(0.5, 0.1 * abs(lo))
    return (lo - pad, hi + pad)


def _simulators() -> tuple[str, ...]:
    """The braking scenario's back-ends (``pemviz.config.SIMULATORS`` where the config has ``sim``)."""
    sims = getattr(pemviz.config, "SIMULATORS", None)
    if not sims:
        from pemviz.problems import SIMULATORS as sims
    return tuple(sims)


def _display_path(path: Path) -> str:
    try:
        return str(path.resolve().relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(path)


def serve(
    host: str = "127.0.0.1",
    port: int = 8080,
    *,
    recordings_dir: str | Path = "recordings",
    preset: str = pemviz.config.DEFAULT_PRESET,
    on_ready: Callable[[PanelApp], None] | None = None,
) -> None:
    """Run the panel until Ctrl-C (what ``pemviz serve`` does).

    Raises:
        ValueError: an unknown ``preset``.
    """
    app = PanelApp(host, port, recordings_dir=recordings_dir, preset=preset)
    try:
        if on_ready is not None:
            on_ready(app)
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        app.close()
