"""Rerun sink: writes an experiment's events into a rerun recording (``.rrd`` file, or a live viewer).

The sink only listens to the engine's events (:mod:`pemviz.engine`); it never drives the engine.

Timelines: ``step`` (0..T-1, one simulation step of dt = 0.05 s; the default timeline, the scene plays on
it), ``stage`` (0 = pretraining, 1..K = cross-entropy stages, K+1 = final batch) and ``repetition`` (only
when the sink is given one). Figures that summarise stages are static 2D plots (drawn with
:class:`Figure`: a frame, ticks and a transform from axis units to the plot box), so they show on
whatever timeline is selected; a time-series view would go blank when the timeline is switched.

Entity paths (``KK`` = stage number, two digits):

- ``description``: Markdown of the run (what it is, how to read it, its config, the stage table, the
  final estimate or how it ended), re-logged static after each stage.
- ``proposal/data/pem``, ``proposal/data/stage_KK``: p_PEM(detect | d) and each stage's proposal
  q(detect | d) after its update (the final batch's repeats stage K's), one :class:`rerun.LineStrips2D`
  each, points ``(d [m], probability)``;
  ``proposal/data/elite_KK``: the elite rollouts' empirical detection rate per 0.1 m gap bin
  (:class:`rerun.Points2D`; for the final batch the "elites" are its crashes). ``proposal/data``
  carries the transform from (metres, probability) to the plot box; ``proposal/axes`` the frame.
- ``stages/{gamma,failure_rate,log10_mu_hat,nll,ess}``: per-stage numbers as scalars on ``stage``;
  ``stage_metrics/<name>/data/bars``: the same as static bar plots over the stage number (visible on
  every timeline; one bar per stage from 0 to the value, in the stage's colour).
- ``rollouts/{gap_m,ego_speed_mps,lead_speed_mps}/stage_KK``: every rollout of a stage over ``step``,
  one entity with N series, sent with one ``send_columns`` each: red = crash, grey = safe, yellow/orange
  and wider = the stage's least-robust rollouts (tagged in the series name).
  ``rollouts/detected/stage_KK``: the gap at the steps where the detector saw the lead, as points
  (NaN where it missed), shown for the tagged rollouts (the others can be switched on).
  ``rollouts/summary/stage_KK``: static per-rollout values (robustness under each metric, importance
  log-weight in nats, crash flag, tag).
- ``scores/{robustness,log_weight}/data/stage_KK``: every rollout's robustness (configured metric) and
  importance log-weight against its stage, as static scatter plots; ``.../data/gamma`` the thresholds.
- ``scene/stage_KK/{lane,ego,lead,sight}``: top-down scene of each stage's least-robust rollout, one lane
  per stage, boxes with the true car sizes, playable on ``step``: the ego is green while the detector
  sees the lead and amber while it misses (the sight line from the camera to the lead likewise), the
  lead turns red once the gap is below the crash gap.
- ``final``: the final estimate (static :class:`rerun.AnyValues`).

Recording properties (``pemviz``): pemviz and rerun-sdk versions, method, metric, formula, seed.
The file is written when the sink is closed (after the run, Ctrl-C or SIGTERM) under a unique temporary name and
moved to ``PATH``, so a recording is never half-written, keeps every finished stage, and a kill leaves an
existing ``PATH`` as it was.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

import pemviz
from pemviz.engine import (
    Event,
    FinalEstimate,
    RolloutsSampled,
    RunCancelled,
    RunStarted,
    StageFinished,
    StageResult,
)
from pemviz.sampling import format_probability
from pemviz.scenarios.braking import BrakingParams

APP_ID = "pemviz"
CRASH_RGBA = (230, 60, 50, 140)
SAFE_RGBA = (150, 150, 150, 60)
TAG_RGBA = (250, 210, 60, 255)
TAG_CRASH_RGBA = (255, 120, 40, 255)
PEM_RGBA = (245, 245, 245, 255)
AXIS_RGBA = (170, 170, 170, 255)
GRID_RGBA = (90, 90, 90, 120)
DETECTED_RGBA = (70, 200, 110, 255)
MISSED_RGBA = (250, 170, 40, 255)
LEAD_RGBA = (110, 160, 240, 255)
LEAD_CRASH_RGBA = (235, 50, 45, 255)
FIGURE_BACKGROUND_RGB = (25, 28, 32)
LANE_SPACING_M = 3.2
SCENE_X_RANGE_M = (-15.0, 38.0)
"""Top-down scene: lanes ``LANE_SPACING_M`` apart (the cars are 2 m wide), x from the lane labels to
past the lead's stop."""

STAGE_METRICS = (
    ("failure_rate", "failures / N"),
    ("gamma", "gamma"),
    ("log10_mu_hat", "log10 mu_hat"),
    ("ess", "ESS"),
    ("nll", "NLL (nats)"),
)


def stage_colour(stage: int, n_stages: int) -> tuple[int, int, int, int]:
    """Blue (early) to orange (late) for the curves and points of stages 0..n_stages."""
    f = min(1.0, stage / max(1, n_stages))
    return (int(40 + 215 * f), int(110 + 40 * f), int(230 - 200 * f), 255)


def nice_ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    """Round tick values in [lo, hi]: the step of 1, 2 or 5 x 10^k nearest (in ratio) to (hi - lo) / n."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return np.array([lo])
    raw = (hi - lo) / max(1, n)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 5, 10)), key=lambda st: abs(math.log(st / raw)))
    first = math.ceil(lo / step - 1e-9) * step
    return np.round(np.arange(first, hi + step * 1e-9, step), 10)


@dataclass(frozen=True)
class Figure:
    """A static x-y plot in a 2D view: data in axis units under ``PATH/data``, a frame under ``PATH/axes``.

    A :class:`rerun.Transform3D` on ``PATH/data`` maps (x, y) in axis units to a ``width`` x ``height``
    box with y pointing up (rerun's 2D y axis points down), so the logged points keep their real values.
    """

    path: str
    x_label: str
    y_label: str
    width: float = 160.0
    height: float = 100.0

    def draw_axes(
        self,
        stream: rr.RecordingStream,
        x_range: tuple[float, float],
        y_range: tuple[float, float],
        x_ticks: np.ndarray | None = None,
    ) -> None:
        """Log (static) the data transform, the frame, grid lines and tick labels for these ranges."""
        (x0, x1), (y0, y1) = x_range, y_range
        if y1 <= y0:
            y0, y1 = y0 - 0.5, y1 + 0.5
        sx, sy = self.width / (x1 - x0), self.height / (y1 - y0)
        stream.log(
            f"{self.path}/data",
            rr.Transform3D(translation=[-x0 * sx, y1 * sy, 0.0], scale=[sx, -sy, 1.0]),
            static=True,
        )
        w, h = self.width, self.height
        xt = nice_ticks(x0, x1, 6) if x_ticks is None else np.asarray(x_ticks, dtype=np.float64)
        yt = nice_ticks(y0, y1, 5)
        xt = xt[(xt >= x0) & (xt <= x1)]
        yt = yt[(yt >= y0) & (yt <= y1)]
        X = (xt - x0) * sx
        Y = (y1 - yt) * sy
        grid = [[[x, 0.0], [x, h]] for x in X] + [[[0.0, y], [w, y]] for y in Y]
        stream.log(f"{self.path}/axes/grid", rr.LineStrips2D(grid, colors=GRID_RGBA, radii=-0.5), static=True)
        stream.log(
            f"{self.path}/axes/frame",
            rr.LineStrips2D([[[0, 0], [w, 0], [w, h], [0, h], [0, 0]]], colors=AXIS_RGBA, radii=-1.0),
            static=True,
        )
        pos = [[x, h + 0.045 * h] for x in X] + [[-0.06 * w, y] for y in Y]
        labels = [f"{v:g}" for v in xt] + [f"{v:g}" for v in yt]
        for text, xy in ((self.x_label, [w / 2, h + 0.13 * h]), (self.y_label, [-0.06 * w, -0.07 * h])):
            if text:  # small figures leave the axis titles to the view's name
                pos.append(xy)
                labels.append(text)
        stream.log(
            f"{self.path}/axes/labels",
            rr.Points2D(pos, radii=-0.01, colors=AXIS_RGBA, labels=labels, show_labels=True),
            static=True,
        )

    def view(self, name: str) -> rrb.Spatial2DView:
        """A 2D view of this figure with bounds that fit the frame and labels."""
        w, h = self.width, self.height
        return rrb.Spatial2DView(
            origin=self.path,
            name=name,
            visual_bounds=rrb.VisualBounds2D(x_range=[-0.14 * w, 1.03 * w], y_range=[-0.12 * h, 1.2 * h]),
            background=FIGURE_BACKGROUND_RGB,
        )


PROPOSAL_FIG = Figure("proposal", "gap d (m)", "p(detect | d)")
ROBUSTNESS_FIG = Figure("scores/robustness", "stage", "robustness")
LOG_WEIGHT_FIG = Figure("scores/log_weight", "stage", "log-weight (nats)")
SCENE_PATH = "scene"
STAGE_FIGS = {key: Figure(f"stage_metrics/{key}", "", "", width=120.0) for key, _ in STAGE_METRICS}


def default_blueprint(n_lanes: int = 12) -> rrb.Blueprint:
    """Proposal curves, rollout scores, gap traces, the scene, stage metrics and the description.

    The selected timeline is ``step`` (the scene and the rollout traces play on it); every stage figure
    is static, so it shows on any timeline. ``n_lanes`` sizes the scene view (one lane per stage).
    """
    no_legend = rrb.PlotLegend(visible=False)
    traces = rrb.Tabs(
        rrb.TimeSeriesView(
            name="Gap d (m): red crash, yellow least robust, dots detections",
            contents=["+ /rollouts/gap_m/**", "+ /rollouts/detected/**"],
            plot_legend=no_legend,
        ),
        rrb.TimeSeriesView(name="Ego speed (m/s)", origin="/rollouts/ego_speed_mps", plot_legend=no_legend),
        rrb.TimeSeriesView(name="Lead speed (m/s)", origin="/rollouts/lead_speed_mps", plot_legend=no_legend),
    )
    scene = rrb.Spatial2DView(
        origin=f"/{SCENE_PATH}",
        name="Scene: least-robust rollout per stage (ego green = detected, amber = missed)",
        background=FIGURE_BACKGROUND_RGB,
        visual_bounds=rrb.VisualBounds2D(
            x_range=list(SCENE_X_RANGE_M), y_range=[-0.6 * LANE_SPACING_M, (n_lanes - 0.4) * LANE_SPACING_M]
        ),
    )
    scores = rrb.Tabs(
        ROBUSTNESS_FIG.view("Robustness per rollout and stage (red = crash, yellow = least robust)"),
        LOG_WEIGHT_FIG.view("Importance log-weight per rollout and stage"),
    )
    bars = {key: STAGE_FIGS[key].view(f"{label} per stage") for key, label in STAGE_METRICS}
    stage_metrics = rrb.Grid(
        bars["failure_rate"],
        bars["gamma"],
        bars["log10_mu_hat"],
        rrb.Tabs(bars["ess"], bars["nll"], rrb.TimeSeriesView(origin="/stages", name="Series [stage timeline]")),
        grid_columns=2,
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Horizontal(
                    PROPOSAL_FIG.view("Proposal q(detect | d) per stage vs the PEM; dots: elites' detection rate"),
                    scores,
                ),
                rrb.Horizontal(traces, scene),
            ),
            rrb.Vertical(rrb.TextDocumentView(origin="/description", name="Run"), stage_metrics, row_shares=[1, 2]),
            column_shares=[2.6, 1.0],
        ),
        rrb.TimePanel(timeline="step", fps=20.0, state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        collapse_panels=True,
    )


class RerunSink:
    """Listens to engine events and logs them to a :class:`rerun.RecordingStream`.

    Args:
        stream: where to log (a file sink, a gRPC connection, or memory).
        rollout_traces: log every rollout's traces and the scene (the bulk of the recording).
        tagged_per_stage: how many least-robust rollouts of each stage are tagged in the traces.
        scene_per_stage: how many least-robust rollouts of each stage get a lane in the scene.
        params: the braking scenario's constants (car sizes, camera offset, dt) for the scene.
        repetition: when set, an index on the ``repetition`` timeline added to every temporal row
            (static figures show the latest repetition).
    """

    def __init__(
        self,
        stream: rr.RecordingStream,
        *,
        rollout_traces: bool = True,
        tagged_per_stage: int = 3,
        scene_per_stage: int = 1,
        params: BrakingParams | None = None,
        repetition: int | None = None,
    ) -> None:
        self.stream = stream
        self.rollout_traces = rollout_traces
        self.tagged_per_stage = tagged_per_stage
        self.scene_per_stage = scene_per_stage
        self.params = params or BrakingParams()
        self.repetition = repetition
        self.n_stages = 1
        self.last_stage = 1
        self.grid_m = np.zeros(0)
        self.config_md = ""
        self.intro_md = ""
        self.status_md = ""
        self.stage_rows: list[str] = []
        self.stage_values: dict[str, list[tuple[int, float]]] = {key: [] for key, _ in STAGE_METRICS}
        self.scores: list[tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.gammas: list[tuple[int, float]] = []
        self.n_lanes = 0
        self.curve_stages: list[int] = []
        self.finished = False
        self._pending: RolloutsSampled | None = None
        self.serve_url: str | None = None
        self._path: Path | None = None
        self._binary: rr.BinaryStream | None = None
        self._overwrite = False
        self._closed = False
        self._axes: dict[str, tuple] = {}
        stream.set_log_time_enabled(False)
        stream.set_log_tick_enabled(False)

    # -- constructors -------------------------------------------------------------------------------
    @classmethod
    def to_file(cls, path: str | os.PathLike, *, overwrite: bool = False, **kw) -> "RerunSink":
        """A sink that saves to ``path`` when :meth:`close` commits it.

        The recording is encoded in memory (:meth:`rerun.RecordingStream.binary_stream`) and written by
        :meth:`close` to a temporary file of a unique name beside ``path``, then moved onto it: a kill leaves the
        previous ``path`` untouched, and a write error (disk full, file too large) is an ``OSError`` here, with
        no file left, instead of a stalled writer thread.
        """
        stream = rr.RecordingStream(APP_ID)
        sink = cls(stream, **kw)
        sink._binary = stream.binary_stream()
        sink._path = Path(path)
        sink._overwrite = overwrite
        return sink

    @classmethod
    def to_grpc(
        cls, url: str | None = None, *, serve: bool = False, grpc_port: int | None = None, **kw
    ) -> "RerunSink":
        """A sink that streams to a running viewer (``url``) or serves a gRPC endpoint (``serve``, on
        ``grpc_port``, default 9876; its ``rerun+http://...`` address is in :attr:`serve_url`)."""
        stream = rr.RecordingStream(APP_ID)
        serve_url = None
        if serve:
            serve_url = stream.serve_grpc(grpc_port=grpc_port)
        else:
            stream.connect_grpc(url)
        sink = cls(stream, **kw)
        sink.serve_url = serve_url
        return sink

    @classmethod
    def to_stdout(cls, **kw) -> "RerunSink":
        """A sink that writes the recording to standard output (``pemviz run --stdout | rerun -``)."""
        stream = rr.RecordingStream(APP_ID)
        stream.stdout()
        return cls(stream, **kw)

    def close(self, commit: bool = True) -> Path | None:
        """Finish the recording and (file sinks) write it; returns the file written (None for gRPC or no commit).

        A run that ended without a final estimate or a cancellation event (Ctrl-C, SIGTERM, an exception in a
        stage) is marked as interrupted in the description; every finished stage is already logged.
        ``commit=False`` drops a file recording (a run that failed on bad input writes nothing). Closing twice
        is harmless (the second call returns None).

        Raises:
            OSError: the file could not be written (nothing is left; an existing file is untouched).
            pemviz.files.OutputExists: the file appeared meanwhile and ``overwrite`` was not given.
        """
        if self._closed:
            return None
        self._closed = True
        if not self.finished and self.intro_md:
            done = len(self.stage_rows)
            self.status_md = f"**Interrupted** after {done} finished stage{'s' * (done != 1)}: no final estimate."
            self._log_description()
        if self._path is None:
            self.stream.flush()
            self.stream.disconnect()
            return None
        self.stream.flush()
        data = self._binary.read(flush=True) or b""
        self.stream.disconnect()
        self._binary = None
        if not commit:
            return None
        from pemviz.files import atomic_write

        return atomic_write(self._path, lambda tmp: Path(tmp).write_bytes(data), overwrite=self._overwrite)

    # -- events -------------------------------------------------------------------------------------
    def __call__(self, event: Event) -> None:
        if isinstance(event, RunStarted):
            self._run_started(event)
        elif isinstance(event, RolloutsSampled):
            self._pending = event
        elif isinstance(event, StageFinished):
            self._stage_finished(event.result)
        elif isinstance(event, FinalEstimate):
            self._final(event)
        elif isinstance(event, RunCancelled):
            self.finished = True
            self.status_md = f"**Run cancelled** ({event.reason}) after {len(event.stages)} finished stages."
            self._log_description()
            self.stream.flush()

    # -- helpers ------------------------------------------------------------------------------------
    def _indexes(self, **sequences: np.ndarray) -> list[rr.TimeColumn]:
        n = len(next(iter(sequences.values())))
        cols = [rr.TimeColumn(name, sequence=np.asarray(seq, dtype=np.int64)) for name, seq in sequences.items()]
        if self.repetition is not None:
            cols.append(rr.TimeColumn("repetition", sequence=np.full(n, self.repetition, dtype=np.int64)))
        return cols

    def _log_description(self) -> None:
        table = ""
        if self.stage_rows:
            table = (
                "\n## Stages\n\n| stage | kind | gamma | failures | mu_hat | NLL | ESS | wall s |\n"
                "|---|---|---|---|---|---|---|---|\n" + "\n".join(self.stage_rows) + "\n"
            )
        status = f"\n## Result\n\n{self.status_md}\n" if self.status_md else ""
        self.stream.log(
            "description",
            rr.TextDocument(self.intro_md + status + table + self.config_md, media_type=rr.MediaType.MARKDOWN),
            static=True,
        )

    def _log_proposal_legend(self) -> None:
        """Legend in the proposal plot (data units: metres, probability): the PEM, the first and last stage."""
        shown = sorted({self.curve_stages[0], self.curve_stages[-1]}) if self.curve_stages else []
        entries = [("PEM", PEM_RGBA)] + [(f"q stage {k}", stage_colour(k, self.n_stages)) for k in shown]
        x0, x1 = float(self.grid_m.min()), float(self.grid_m.max())
        x = x1 - 0.1 * (x1 - x0)
        pos = [[x, 0.75 - j * 0.1] for j in range(len(entries))]
        self.stream.log(
            "proposal/data/legend",
            rr.Points2D(pos, radii=-0.01, colors=[c for _, c in entries], labels=[t for t, _ in entries],
                        show_labels=True),
            static=True,
        )  # fmt: skip

    def _draw_axes(self, fig: Figure, x_range, y_range, x_ticks: np.ndarray | None = None) -> None:
        """:meth:`Figure.draw_axes`, skipped when the ranges have not changed since the last stage."""
        key = (tuple(x_range), tuple(y_range), None if x_ticks is None else tuple(x_ticks))
        if self._axes.get(fig.path) != key:
            fig.draw_axes(self.stream, x_range, y_range, x_ticks)
            self._axes[fig.path] = key

    def _log_stage_bars(self, key: str) -> None:
        """One bar per finished stage from 0 to the value, in the stage's colour (static 2D plot)."""
        pts = self.stage_values[key]
        values = np.array([v for _, v in pts])
        lo, hi = min(0.0, float(values.min())), max(0.0, float(values.max()))
        pad = 0.05 * (hi - lo) if hi > lo else 0.5
        fig = STAGE_FIGS[key]
        self._draw_axes(fig, (-0.6, self.last_stage + 0.6), (lo - pad if lo < 0 else 0.0, hi + pad if hi > 0 else 0.0))
        self.stream.log(
            f"{fig.path}/data/bars",
            rr.LineStrips2D(
                [[[k, 0.0], [k, v]] for k, v in pts], colors=[stage_colour(k, self.n_stages) for k, _ in pts],
                radii=-4.0, labels=[f"stage {k}: {v:.4g}" for k, v in pts], show_labels=False,
            ),
            static=True,
        )  # fmt: skip

    # -- run started ----------------------------------------------------------------------------------
    def _run_started(self, ev: RunStarted) -> None:
        cfg = ev.config
        self.n_stages = cfg.n_stages + 1 if cfg.method == "adaptive" else 1
        self.last_stage = cfg.n_stages + cfg.has_final_batch if cfg.method == "adaptive" else 1
        self.grid_m = np.asarray(ev.curve_grid_m, dtype=np.float64)
        s = self.stream
        s.send_property(
            "pemviz",
            rr.AnyValues(
                pemviz_version=pemviz.__version__,
                rerun_sdk_version=rr.__version__,
                method=cfg.method,
                metric=cfg.metric,
                formula=ev.formula,
                seed=cfg.seed,
            ),
        )
        s.send_recording_name(f"pemviz {cfg.method} {cfg.metric} seed {cfg.seed}")
        n_batches = cfg.n_stages + (2 if cfg.has_final_batch else 1) if cfg.method == "adaptive" else 1
        s.send_blueprint(default_blueprint(n_batches * self.scene_per_stage))
        method = {
            "adaptive": (
                f"**adaptive importance sampling** (cross-entropy method, Innes & Ramamoorthy 2022): "
                f"{cfg.pretrain_rollouts} PEM-driven rollouts pretrain the proposal q(detect | d) (stage 0), "
                f"K = {cfg.n_stages} stages of N = {cfg.n_per_stage} rollouts each move it toward the "
                f"failures (elites: robustness at or below the (1 - sigma) quantile gamma, sigma = "
                f"{cfg.quantile_level}, smoothing alpha = {cfg.smoothing}), and a final batch of "
                f"N_e = {cfg.n_final} rollouts gives the estimate."
            ),
            "mc": f"plain **Monte Carlo** with the PEM: {cfg.n_per_stage} rollouts.",
            "naive50": f"a **50 % detector** at every step, weighted by the PEM: {cfg.n_per_stage} rollouts.",
            "mixed50": f"a **50 % detector inside 10 m**, the PEM outside: {cfg.n_per_stage} rollouts.",
        }[cfg.method]
        self.intro_md = (
            f"# pemviz: crash probability of the braking scenario\n\n"
            f"A car follows a lead that brakes for a red light; the ego brakes only when its detector, "
            f"a perception error model (PEM) p(detect | d), sees the lead within 10 m. A crash is the gap d "
            f"dropping below {self.params.crash_gap_m:g} m, safety spec `{ev.formula}`; rollouts are ranked "
            f"by **{cfg.metric}** robustness. Method: {method}\n\n"
            "**How to read it.** *Proposal*: q(detect | d) after each stage (blue early, orange late) against "
            "the PEM (white); dots are the elite rollouts' detection rate per gap bin. *Rollout scores*: "
            "robustness and importance log-weight of every rollout per stage (red = crash). *Rollouts*: "
            "gap, ego and lead speed over `step` (red = crash, yellow = least robust, dots = detections). "
            "*Scene*: the least-robust rollout of each stage, one lane per stage; press play on `step`. "
            "*Stage metrics*: bar charts per stage (also as series on the `stage` timeline).\n"
        )
        rows = "\n".join(f"| {k} | `{v}` |" for k, v in vars(cfg).items())
        self.config_md = f"\n## Config\n\n| setting | value |\n|---|---|\n{rows}\n"
        self._log_description()
        PROPOSAL_FIG.draw_axes(s, (float(self.grid_m.min()), float(self.grid_m.max())), (0.0, 1.0))
        s.log(
            "proposal/data/pem",
            rr.LineStrips2D([np.column_stack([self.grid_m, ev.pem_curve])], colors=PEM_RGBA, radii=-2.0),
            static=True,
        )
        self._log_proposal_legend()

    # -- stage finished -------------------------------------------------------------------------------
    def _stage_finished(self, res: StageResult) -> None:
        s = self.stream
        colour = stage_colour(res.stage, self.n_stages)
        if not np.all(np.isnan(res.proposal_curve)):
            s.log(
                f"proposal/data/stage_{res.stage:02d}",
                rr.LineStrips2D([np.column_stack([self.grid_m, res.proposal_curve])], colors=colour, radii=-1.5),
                static=True,
            )
            self.curve_stages.append(res.stage)
            self._log_proposal_legend()
        rate = np.asarray(res.elite_detect_rate, dtype=np.float64)
        ok = np.isfinite(rate)
        if ok.any():
            s.log(
                f"proposal/data/elite_{res.stage:02d}",
                rr.Points2D(np.column_stack([self.grid_m[ok], rate[ok]]), colors=colour, radii=-1.5),
                static=True,
            )

        e = res.estimate
        values = {
            "gamma": res.gamma,
            "failure_rate": e.n_failures / e.n,
            "log10_mu_hat": e.log10_mu_hat,
            "nll": e.nll_mean,
            "ess": e.ess,
        }
        s.set_time("stage", sequence=res.stage)
        if self.repetition is not None:
            s.set_time("repetition", sequence=self.repetition)
        for key, value in values.items():
            if math.isfinite(value):
                s.log(f"stages/{key}", rr.Scalars(value))
                self.stage_values[key].append((res.stage, value))
                self._log_stage_bars(key)

        def num(x: float, fmt: str) -> str:
            return format(x, fmt) if math.isfinite(x) else "-"

        self.stage_rows.append(
            f"| {res.stage} | {res.kind} | {num(res.gamma, '.4f')} | {e.n_failures}/{e.n} | "
            f"{format_probability(e.log_mu_hat)} | {num(e.nll_mean, '.2f')} | {num(e.ess, '.2f')} | "
            f"{res.wall_s:.2f} |"
        )
        self._log_description()

        pending = self._pending
        if pending is not None and pending.stage == res.stage:
            self._log_scores(pending, res)
            if self.rollout_traces:
                self._log_rollouts(pending)
        self._pending = None
        s.flush()

    def _least_robust(self, ev: RolloutsSampled, k: int) -> np.ndarray:
        """Indices of the ``k`` least-robust rollouts under the configured metric (ties: lower index)."""
        return np.argsort(ev.robustness, kind="stable")[: min(k, ev.robustness.size)]

    def _log_scores(self, ev: RolloutsSampled, res: StageResult) -> None:
        """Every rollout's robustness and log-weight against its stage (static scatter plots)."""
        s = self.stream
        n = ev.robustness.size
        jitter = ev.stage + (np.arange(n) + 0.5) / n * 0.7 - 0.35
        r = np.asarray(ev.robustness, dtype=np.float64)
        lw = np.asarray(ev.log_weight, dtype=np.float64)
        self.scores.append((ev.stage, jitter, r, lw, np.asarray(ev.failed, bool)))
        if math.isfinite(res.gamma):
            self.gammas.append((ev.stage, res.gamma))
        tagged = np.zeros(n, bool)
        tagged[self._least_robust(ev, self.tagged_per_stage)] = True
        colours = np.where(ev.failed[:, None], np.array(CRASH_RGBA), np.array(SAFE_RGBA)).astype(np.uint8)
        colours[:, 3] = 200
        colours[tagged] = TAG_RGBA
        stages = [k for k, *_ in self.scores]
        x_range = (min(stages) - 0.6, max(stages) + 0.6)
        for fig, values in ((ROBUSTNESS_FIG, r), (LOG_WEIGHT_FIG, lw)):
            ok = np.isfinite(values)
            s.log(
                f"{fig.path}/data/stage_{ev.stage:02d}",
                rr.Points2D(np.column_stack([jitter[ok], values[ok]]), colors=colours[ok], radii=-2.0),
                static=True,
            )
            idx = 2 if fig is ROBUSTNESS_FIG else 3
            allv = np.concatenate([sc[idx][np.isfinite(sc[idx])] for sc in self.scores] + [np.zeros(1)])
            lo, hi = float(allv.min()), float(allv.max())
            pad = 0.05 * (hi - lo) if hi > lo else 1.0
            ticks = np.arange(min(stages), max(stages) + 1) if len(stages) <= 16 else None
            self._draw_axes(fig, x_range, (lo - pad, hi + pad), ticks)
        zero = [[[x_range[0], 0.0], [x_range[1], 0.0]]]
        s.log(f"{ROBUSTNESS_FIG.path}/data/zero", rr.LineStrips2D(zero, colors=CRASH_RGBA, radii=-1.0), static=True)
        if self.gammas:
            s.log(
                f"{ROBUSTNESS_FIG.path}/data/gamma",
                rr.LineStrips2D(
                    [[[k - 0.4, g], [k + 0.4, g]] for k, g in self.gammas], colors=PEM_RGBA, radii=-1.5,
                    labels=[f"gamma {g:.2f}" for _, g in self.gammas], show_labels=False,
                ),
                static=True,
            )  # fmt: skip
        s.log(
            f"rollouts/summary/stage_{ev.stage:02d}",
            rr.AnyValues(
                rollout=np.arange(n),
                log_weight=lw,
                failed=np.asarray(ev.failed, bool),
                least_robust=tagged,
                **{f"robustness_{m.replace('-', '_')}": np.asarray(v, np.float64)
                   for m, v in ev.robustness_by_metric.items()},
            ),
            static=True,
        )  # fmt: skip

    def _log_rollouts(self, ev: RolloutsSampled) -> None:
        """All N traces of a stage, one entity per signal with N series, one ``send_columns`` each."""
        s = self.stream
        batch = ev.batch
        n, t = batch.n, batch.n_steps
        order = self._least_robust(ev, self.tagged_per_stage)
        rank = {int(i): j for j, i in enumerate(order)}
        failed = np.asarray(ev.failed, bool)
        colours, widths, names = [], [], []
        for i in range(n):
            tag = rank.get(i)
            crash = " crash" if failed[i] else ""
            if tag is None:
                colours.append(CRASH_RGBA if failed[i] else SAFE_RGBA)
                widths.append(1.0)
                names.append(f"s{ev.stage} r{i}{crash}")
            else:
                colours.append(TAG_CRASH_RGBA if failed[i] else TAG_RGBA)
                widths.append(2.5)
                names.append(f"s{ev.stage} r{i} least-robust #{tag + 1} rho={ev.robustness[i]:.3g}{crash}")
        index = self._indexes(step=np.arange(t))
        stage = f"stage_{ev.stage:02d}"
        for name in batch.observation_names:
            path = f"rollouts/{name}/{stage}"
            s.log(path, rr.SeriesLines(colors=colours, widths=widths, names=names), static=True)
            s.send_columns(path, indexes=index, columns=rr.Scalars.columns(scalars=batch.signal(name).T))
        visible = np.zeros(n, bool)
        visible[order] = True
        path = f"rollouts/detected/{stage}"
        s.log(
            path,
            rr.SeriesPoints(
                colors=[DETECTED_RGBA] * n, names=[f"{nm} detected" for nm in names], marker_sizes=[1.5] * n,
                visible_series=visible,
            ),
            static=True,
        )  # fmt: skip
        dots = np.where(batch.detected, batch.gap_m, np.nan)
        s.send_columns(path, indexes=index, columns=rr.Scalars.columns(scalars=dots.T))
        if {"gap_m", "ego_speed_mps"} <= set(batch.observation_names):
            for i in order[: self.scene_per_stage]:
                self._log_scene_lane(ev, int(i))

    def _log_scene_lane(self, ev: RolloutsSampled, i: int) -> None:
        """One lane of the top-down scene: rollout ``i`` of the stage, playable on ``step``.

        Positions (metres along the road) are rebuilt from the observations with the scenario's explicit
        Euler step (highway-env moves a vehicle by its speed before updating the speed): ego centre
        x_t = dt * sum_{s<t} v_s; the lead's rear is the camera (``camera_offset_m`` ahead of the ego
        centre) plus the gap.
        """
        p = self.params
        s = self.stream
        batch = ev.batch
        gap = batch.gap_m[i]
        v = batch.signal("ego_speed_mps")[i]
        seen = batch.detected[i]
        t = gap.size
        lane = self.n_lanes
        self.n_lanes += 1
        y = lane * LANE_SPACING_M
        ego_x = p.dt_s * np.concatenate([[0.0], np.cumsum(v[:-1])])
        camera_x = ego_x + p.camera_offset_m
        lead_rear = camera_x + gap
        lead_x = lead_rear + p.lead_length_m / 2
        ys = np.full(t, y)
        path = f"{SCENE_PATH}/stage_{ev.stage:02d}" + (f"_{lane}" if self.scene_per_stage > 1 else "")
        crash = " crash" if ev.failed[i] else ""
        label = f"stage {ev.stage}{crash}"
        detail = f"stage {ev.stage} ({ev.kind}) rollout {i}: robustness {ev.robustness[i]:.3g}{crash}"
        half = LANE_SPACING_M / 2 - 0.1
        x_end = float(max(lead_x.max() + p.lead_length_m, SCENE_X_RANGE_M[1]))
        s.log(
            f"{path}/lane",
            rr.LineStrips2D(
                [[[-4.0, y - half], [x_end, y - half]], [[-4.0, y + half], [x_end, y + half]]],
                colors=GRID_RGBA, radii=-0.75, labels=[detail, detail], show_labels=False,
            ),
            static=True,
        )  # fmt: skip
        s.log(
            f"{path}/label",
            rr.Points2D([[-9.0, y]], radii=-0.01, colors=LEAD_CRASH_RGBA if ev.failed[i] else AXIS_RGBA,
                        labels=label, show_labels=True),
            static=True,
        )  # fmt: skip
        index = self._indexes(step=np.arange(t))
        ego_half = np.tile([p.ego_length_m / 2, p.vehicle_width_m / 2], (t, 1))
        lead_half = np.tile([p.lead_length_m / 2, p.vehicle_width_m / 2], (t, 1))
        det_col = np.where(seen[:, None], np.array(DETECTED_RGBA), np.array(MISSED_RGBA)).astype(np.uint8)
        lead_col = np.where((gap < p.crash_gap_m)[:, None], np.array(LEAD_CRASH_RGBA), np.array(LEAD_RGBA))
        s.send_columns(
            f"{path}/ego",
            indexes=index,
            columns=rr.Boxes2D.columns(
                centers=np.column_stack([ego_x, ys]), half_sizes=ego_half, colors=det_col, radii=np.full(t, -2.0)
            ),
        )
        s.send_columns(
            f"{path}/lead",
            indexes=index,
            columns=rr.Boxes2D.columns(
                centers=np.column_stack([lead_x, ys]), half_sizes=lead_half, colors=lead_col.astype(np.uint8),
                radii=np.full(t, -2.0),
            ),
        )
        sight = np.stack([np.column_stack([camera_x, ys]), np.column_stack([lead_rear, ys])], axis=1)
        s.send_columns(
            f"{path}/sight",
            indexes=index,
            columns=rr.LineStrips2D.columns(strips=sight, colors=det_col, radii=np.full(t, -1.5)),
        )

    # -- final --------------------------------------------------------------------------------------
    def _final(self, ev: FinalEstimate) -> None:
        e = ev.estimate
        s = self.stream
        self.finished = True
        s.log(
            "final",
            rr.AnyValues(
                log_mu_hat=e.log_mu_hat,
                mu_hat=format_probability(e.log_mu_hat, 4),
                n_failures=e.n_failures,
                n=e.n,
                nll_mean=e.nll_mean,
                ess=e.ess,
                n_simulations=ev.n_simulations,
                wall_s=ev.wall_s,
            ),
            static=True,
        )
        self.status_md = (
            f"**Final estimate** mu_hat = {format_probability(e.log_mu_hat, 4)} (log mu_hat = "
            f"{e.log_mu_hat:.4f} nats; {e.n_failures}/{e.n} failures, ESS {e.ess:.2f}) from "
            f"{ev.n_simulations} simulations in {ev.wall_s:.1f} s."
        )
        self._log_description()
        s.flush()
