"""Rerun sink: writes an experiment's events into a rerun recording (``.rrd`` file, or a live viewer).

The sink only listens to the engine's events (:mod:`pemviz.engine`); it never drives the engine.

Timelines: ``stage`` (0 = pretraining, 1..K = cross-entropy stages, K+1 = final batch: the engine's
numbering, :func:`pemviz.engine.stage_label`; the default timeline: scrubbing it steps the proposal curve,
the histograms and the estimate), ``step`` (0..T-1, one simulation step of dt = 0.05 s: the rollout traces
and the scene play on it) and ``repetition`` (only when the sink is given one). Colours are those of the
panel (:mod:`pemviz.sinks.colours`): detected green, missed orange, crash red.

Entity paths (``KK`` = stage number, two digits):

- ``estimate``: Markdown of the current estimate with its 95 % interval, k-hat, verdict and the exact
  answer where known (the blueprint's first view), re-logged static after each stage and at the end.
- ``description``: Markdown of the run (what it is, how to read it, its config, the stage table, how it
  ended), re-logged static after each stage.
- ``proposal/data/pem``, ``proposal/data/stage_KK``: p_PEM(detect | d) and each stage's proposal
  q(detect | d) after its update (the final batch's repeats stage K's), static :class:`rerun.LineStrips2D`,
  points ``(d [m], probability)``; ``proposal/data/current``: the same curve on the ``stage`` timeline
  (thick, so scrubbing steps it); ``proposal/data/elite_KK``: the elite rollouts' empirical detection
  rate per 0.1 m gap bin (for the final batch the "elites" are its crashes). ``proposal/data`` carries the
  transform from (metres, probability) to the plot box; ``proposal/axes`` the frame.
- ``stages/{failure_rate,gamma,log10_mu_hat,ess,nll,khat}``: per-stage values as :class:`rerun.Scalars` on
  ``stage``, styled once (static :class:`rerun.SeriesLines` and :class:`rerun.SeriesPoints`) for rerun's
  native time-series views (hover values, legends); ``stages/log10_mu_hat/{ci_low,ci_high,exact}``: the
  95 % interval and the exact answer where known.
- ``histograms/{robustness,log_weight}``: each stage's histogram of every rollout's robustness (configured
  metric) and importance log-weight (nats), a :class:`rerun.BarChart` on ``stage``.
- ``rollouts/{gap_m,ego_speed_mps,lead_speed_mps}/stage_KK``: the kept rollouts of a stage over ``step``
  (all of them up to :data:`ALL_ROLLOUTS_UP_TO`, else the least robust and a uniform sample), one entity
  with one series per rollout, one ``send_columns`` each: red = crash, grey = safe, yellow and wider = the
  stage's least-robust rollouts (tagged in the series name). ``rollouts/gap_m/thresholds``: the 2 m crash
  gap and the 10 m braking distance. ``rollouts/detected/stage_KK``: the gap at the steps where the
  detector saw the lead, as points (NaN where it missed), shown for the tagged rollouts.
  ``rollouts/summary/stage_KK``: static per-rollout values of the kept rollouts (index, robustness under
  each metric, importance log-weight in nats, crash flag, tag).
- ``scene/stage_KK/{lane,ego,lead,sight}``: top-down scene of each stage's least-robust rollout, one lane
  per stage, boxes with the true car sizes, playable on ``step``: the ego is green while the detector
  sees the lead and orange while it misses (the sight line likewise), the lead turns red once the gap is
  below the crash gap.
- ``final``: the final estimate (static :class:`rerun.AnyValues`).

Size: per stage the recording holds summaries, two histograms and at most
``ALL_ROLLOUTS_UP_TO`` rollouts' traces, so a run of 10^5 rollouts a stage stays a few MB.

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
    stage_label,
)
from pemviz.estimate import format_probability, relative_error
from pemviz.io.files import atomic_write
from pemviz.scenarios.braking import BrakingParams
from pemviz.sinks import colours as C
from pemviz.sinks.scene import car_positions

APP_ID = "pemviz"
CRASH_RGBA = C.rgba(C.CRASH, 170)
SAFE_RGBA = C.rgba(C.SAFE, 60)
TAG_RGBA = C.rgba(C.TAGGED)
TAG_CRASH_RGBA = C.rgba(C.CRASH)
PEM_RGBA = C.rgba(C.ON_DARK)
AXIS_RGBA = C.rgba(C.AXIS)
GRID_RGBA = C.rgba(C.GRID, 120)
DETECTED_RGBA = C.rgba(C.DETECTED)
MISSED_RGBA = C.rgba(C.MISSED)
LEAD_RGBA = C.rgba(C.LEAD)
LEAD_CRASH_RGBA = C.rgba(C.CRASH)
BRAKE_RGBA = C.rgba(C.BRAKE_ZONE)
ALL_ROLLOUTS_UP_TO = 500
"""Stages of at most this many rollouts are recorded rollout by rollout; larger ones keep the least-robust
rollouts and a uniform sample (:data:`SAMPLED_ROLLOUTS`)."""
SAMPLED_ROLLOUTS = 100
HISTOGRAM_BINS = 40
LANE_SPACING_M = 3.2
SCENE_X_RANGE_M = (-15.0, 38.0)
"""Top-down scene: lanes ``LANE_SPACING_M`` apart (the cars are 2 m wide), x from the lane labels to
past the lead's stop."""

STAGE_METRICS = (
    ("log10_mu_hat", "log10 mu_hat", C.BLUE),
    ("failure_rate", "failures / N", C.CRASH),
    ("gamma", "threshold gamma", C.VIOLET),
    ("ess", "ESS", C.DETECTED),
    ("khat", "Pareto k-hat", C.MISSED),
    ("nll", "NLL of the failures (nats)", C.NEUTRAL),
)
"""Per-stage values: key under ``stages/``, series name, colour."""


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
            background=C.FIGURE_BACKGROUND,
        )


PROPOSAL_FIG = Figure("proposal", "gap d (m)", "p(detect | d)")
SCENE_PATH = "scene"


def default_blueprint(n_lanes: int = 12) -> rrb.Blueprint:
    """The estimate and the proposal first, then the per-stage series and histograms, then rollouts and scene.

    The selected timeline is ``stage``: scrubbing it steps the proposal curve, the histograms and the
    per-stage series; the rollout traces and the scene play on ``step``. ``n_lanes`` sizes the scene view
    (one lane per stage).
    """
    stage_views = [
        rrb.TimeSeriesView(origin=f"/stages/{key}", name=name, plot_legend=rrb.PlotLegend(visible=key == "log10_mu_hat"))
        for key, name, _ in STAGE_METRICS
    ]
    traces = rrb.Tabs(
        rrb.TimeSeriesView(
            name="Gap (m): play on the step timeline",
            contents=["+ /rollouts/gap_m/**", "+ /rollouts/detected/**"],
            plot_legend=rrb.PlotLegend(visible=False),
        ),
        rrb.TimeSeriesView(name="Ego speed (m/s)", origin="/rollouts/ego_speed_mps", plot_legend=rrb.PlotLegend(visible=False)),
        rrb.TimeSeriesView(name="Lead speed (m/s)", origin="/rollouts/lead_speed_mps", plot_legend=rrb.PlotLegend(visible=False)),
    )
    scene = rrb.Spatial2DView(
        origin=f"/{SCENE_PATH}",
        name="Scene: play on the step timeline",
        background=C.FIGURE_BACKGROUND,
        visual_bounds=rrb.VisualBounds2D(
            x_range=list(SCENE_X_RANGE_M), y_range=[-0.6 * LANE_SPACING_M, (n_lanes - 0.4) * LANE_SPACING_M]
        ),
    )
    histograms = rrb.Tabs(
        rrb.BarChartView(origin="/histograms/robustness", name="Robustness histogram"),
        rrb.BarChartView(origin="/histograms/log_weight", name="Log-weight histogram (nats)"),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Horizontal(
                    rrb.TextDocumentView(origin="/estimate", name="Estimate"),
                    PROPOSAL_FIG.view("Proposal q(detect | d) vs PEM"),
                    column_shares=[1.0, 1.5],
                ),
                rrb.Horizontal(rrb.Grid(*stage_views, grid_columns=3), histograms, column_shares=[2.0, 1.0]),
                rrb.Horizontal(traces, scene),
                row_shares=[1.1, 1.0, 0.8],
            ),
            rrb.TextDocumentView(origin="/description", name="Run"),
            column_shares=[3.0, 1.0],
        ),
        rrb.TimePanel(timeline="stage", state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        collapse_panels=True,
    )


class RerunSink:
    """Listens to engine events and logs them to a :class:`rerun.RecordingStream`.

    Args:
        stream: where to log (a file sink, a gRPC connection, or memory).
        rollout_traces: log the rollouts' traces and the scene (the bulk of the recording; all rollouts of a
            stage up to :data:`ALL_ROLLOUTS_UP_TO`, else the least robust and a uniform sample).
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
        self.n_ce = 0
        self.exact_log_p: float | None = None
        self.estimate_md = ""
        self.n_lanes = 0
        self.curve_stages: list[int] = []
        self.finished = False
        self._pending: RolloutsSampled | None = None
        self.serve_url: str | None = None
        self._path: Path | None = None
        self._binary: rr.BinaryStream | None = None
        self._overwrite = False
        self._closed = False
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
            pemviz.io.files.OutputExists: the file appeared meanwhile and ``overwrite`` was not given.
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
                "\n## Stages\n\n| stage | name | gamma | failures | mu_hat | NLL | ESS | wall s |\n"
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
        entries = [("PEM", PEM_RGBA)] + [(f"q stage {k}", C.stage_rgba(k, self.n_stages)) for k in shown]
        x0, x1 = float(self.grid_m.min()), float(self.grid_m.max())
        x = x1 - 0.1 * (x1 - x0)
        pos = [[x, 0.75 - j * 0.1] for j in range(len(entries))]
        self.stream.log(
            "proposal/data/legend",
            rr.Points2D(pos, radii=-0.01, colors=[c for _, c in entries], labels=[t for t, _ in entries],
                        show_labels=True),
            static=True,
        )  # fmt: skip

    def _log_estimate(self, res: StageResult | None, final: FinalEstimate | None = None) -> None:
        """The ``estimate`` view: mu_hat with its interval, k-hat, verdict and the exact answer where known."""
        e = final.estimate if final is not None else res.estimate
        where = "Final estimate" if final is not None else f"Estimate after {stage_label(res.stage, res.kind, self.n_ce)}"
        lines = [
            f"# {where}", "",
            f"## mu_hat = {format_probability(e.log_mu_hat, 4)}", "",
            f"95 % interval **{e.interval_text()}**", "",
            f"**{e.verdict}**: {e.reason}",
        ]  # fmt: skip
        exact = self.exact_log_p
        if exact is not None:
            inside = "inside" if e.covers(exact) else "**outside**"
            lines += ["", f"exact answer **{format_probability(exact, 4)}**: relative error "
                          f"{relative_error(e.log_mu_hat, exact):.2g}, {inside} the interval"]  # fmt: skip
        if e.n_failures == 0:
            lines += ["", f"No failure among {e.n} rollouts: mu_hat = 0 says only that the sampler found no crash."]
        khat = "-" if math.isnan(e.khat) else f"{e.khat:.2f}"
        nll = f" · NLL {e.nll_mean:.1f} nats" if math.isfinite(e.nll_mean) else ""
        lines += ["", f"failures {e.n_failures}/{e.n} · ESS {e.ess:.1f} · k-hat {khat}{nll}"]
        if final is not None:
            lines += ["", f"{final.n_simulations:,} simulations in {final.wall_s:.1f} s"]
        self.estimate_md = "\n".join(lines) + "\n"
        self.stream.log("estimate", rr.TextDocument(self.estimate_md, media_type=rr.MediaType.MARKDOWN), static=True)

    def _log_series_styles(self) -> None:
        """Static styling of the per-stage series (names, colours, markers) for the time-series views."""
        s = self.stream
        for key, name, rgb in STAGE_METRICS:
            s.log(f"stages/{key}", rr.SeriesLines(colors=[C.rgba(rgb)], names=[name], widths=[2.0]),
                  rr.SeriesPoints(colors=[C.rgba(rgb)], names=[name], marker_sizes=[3.0]), static=True)  # fmt: skip
        for key, name, rgb in (("ci_low", "95 % interval, low", C.INTERVAL),
                               ("ci_high", "95 % interval, high", C.INTERVAL),
                               ("exact", "exact answer", C.DETECTED)):  # fmt: skip
            s.log(f"stages/log10_mu_hat/{key}", rr.SeriesLines(colors=[C.rgba(rgb)], names=[name], widths=[1.0]),
                  static=True)  # fmt: skip
        s.log(
            "rollouts/gap_m/thresholds",
            rr.SeriesLines(colors=[CRASH_RGBA[:3] + (255,), BRAKE_RGBA], widths=[2.0, 2.0],
                           names=[f"crash gap {self.params.crash_gap_m:g} m",
                                  f"braking distance {self.params.braking_distance_m:g} m"]),
            static=True,
        )  # fmt: skip
        t = np.arange(self.params.n_steps)
        levels = np.array([[self.params.crash_gap_m, self.params.braking_distance_m]] * t.size)
        s.send_columns("rollouts/gap_m/thresholds", indexes=self._indexes(step=t), columns=rr.Scalars.columns(scalars=levels))

    # -- run started ----------------------------------------------------------------------------------
    def _run_started(self, ev: RunStarted) -> None:
        cfg = ev.config
        self.n_stages = cfg.n_stages + 1 if cfg.method == "adaptive" else 1
        self.last_stage = cfg.n_stages + cfg.has_final_batch if cfg.method == "adaptive" else 1
        self.grid_m = np.asarray(ev.curve_grid_m, dtype=np.float64)
        self.n_ce = cfg.n_stages
        self.exact_log_p = ev.exact_log_p
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
            "ams": (f"**adaptive multilevel splitting** on robustness (Cerou & Guyader 2007): N = {cfg.n_per_stage} "
                    f"PEM rollouts, the k = {cfg.ams_killed} highest killed per iteration and branched from survivors; "
                    "each stage shows the particles after about N resamplings."),
        }[cfg.method]
        self.intro_md = (
            f"# pemviz: crash probability of the braking scenario\n\n"
            f"A car follows a lead that brakes for a red light; the ego brakes only when its detector, "
            f"a perception error model (PEM) p(detect | d), sees the lead within 10 m. A crash is the gap d "
            f"dropping below {self.params.crash_gap_m:g} m, safety spec `{ev.formula}`; rollouts are ranked "
            f"by **{cfg.metric}** robustness. Method: {method}\n\n"
            "**How to read it.** Stages are numbered as in the console: 0 = pretraining, 1..K = CE stages, "
            "K+1 = final batch. *Estimate*: mu_hat with its 95 % interval and verdict. *Proposal*: "
            "q(detect | d) after each stage (blue early, orange late) against the PEM (white); the thick curve "
            "is the stage selected on the `stage` timeline; dots are the elite rollouts' detection rate per gap "
            "bin. *Per-stage series* and *histograms* (robustness, importance log-weight) step with the `stage` "
            "timeline. Switch the timeline to `step` to play the *rollouts* (gap with the 2 m and 10 m lines; red = "
            "crash, yellow = least robust, green dots = detections) and the *scene* (ego green = detected, "
            "orange = missed).\n"
        )
        rows = "\n".join(f"| {k} | `{v}` |" for k, v in vars(cfg).items())
        self.config_md = f"\n## Config\n\n| setting | value |\n|---|---|\n{rows}\n"
        self._log_description()
        self._log_series_styles()
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
        colour = C.stage_rgba(res.stage, self.n_stages)
        s.set_time("stage", sequence=res.stage)
        if self.repetition is not None:
            s.set_time("repetition", sequence=self.repetition)
        if not np.all(np.isnan(res.proposal_curve)):
            strip = [np.column_stack([self.grid_m, res.proposal_curve])]
            s.log(f"proposal/data/stage_{res.stage:02d}", rr.LineStrips2D(strip, colors=colour, radii=-1.5), static=True)
            s.log("proposal/data/current", rr.LineStrips2D(strip, colors=colour, radii=-4.0,
                                                           labels=[stage_label(res.stage, res.kind, self.n_ce)]))
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
            "khat": e.khat,
        }
        if math.isfinite(e.log10_mu_hat):
            values["log10_mu_hat/ci_low"] = e.log_ci[0] / math.log(10.0)
            values["log10_mu_hat/ci_high"] = e.log_ci[1] / math.log(10.0)
        if self.exact_log_p is not None and math.isfinite(self.exact_log_p):
            values["log10_mu_hat/exact"] = self.exact_log_p / math.log(10.0)
        for key, value in values.items():
            if math.isfinite(value):
                s.log(f"stages/{key}", rr.Scalars(value))

        def num(x: float, fmt: str) -> str:
            return format(x, fmt) if math.isfinite(x) else "-"

        self.stage_rows.append(
            f"| {res.stage} | {stage_label(res.stage, res.kind, self.n_ce)} | {num(res.gamma, '.4f')} | "
            f"{e.n_failures}/{e.n} | {format_probability(e.log_mu_hat)} | {num(e.nll_mean, '.2f')} | "
            f"{num(e.ess, '.2f')} | {res.wall_s:.2f} |"
        )
        self._log_description()
        self._log_estimate(res)

        pending = self._pending
        if pending is not None and pending.stage == res.stage:
            self._log_histograms(pending)
            if self.rollout_traces:
                self._log_rollouts(pending)
        self._pending = None
        s.flush()

    def _least_robust(self, ev: RolloutsSampled, k: int) -> np.ndarray:
        """Indices of the ``k`` least-robust rollouts under the configured metric (ties: lower index)."""
        return np.argsort(ev.robustness, kind="stable")[: min(k, ev.robustness.size)]

    def _log_histograms(self, ev: RolloutsSampled) -> None:
        """Histograms of every rollout's robustness and log-weight at this stage (:class:`rerun.BarChart` on ``stage``)."""
        every = ev.n_total is not None  # a streamed stage: the sample's rows, every rollout's numbers
        for key, values in (("robustness", ev.stage_robustness if every else ev.robustness),
                            ("log_weight", ev.stage_log_weight if every else ev.log_weight)):  # fmt: skip
            v = np.asarray(values, dtype=np.float64)
            v = v[np.isfinite(v)]
            if v.size == 0:
                continue
            counts, edges = np.histogram(v, bins=HISTOGRAM_BINS if np.ptp(v) > 0 else 1)
            colour = CRASH_RGBA[:3] + (255,) if key == "robustness" else C.rgba(C.LOG_WEIGHT)
            self.stream.log(
                f"histograms/{key}",
                rr.BarChart(counts.astype(np.float64), abscissa=(edges[:-1] + edges[1:]) / 2, widths=np.diff(edges),
                            color=colour),
            )

    def kept_rollouts(self, ev: RolloutsSampled) -> np.ndarray:
        """Indices of the rollouts recorded in full, ascending: all up to :data:`ALL_ROLLOUTS_UP_TO`, else the
        ``tagged_per_stage`` least robust, every failure up to :data:`SAMPLED_ROLLOUTS` of them and a uniform
        sample of :data:`SAMPLED_ROLLOUTS` (every ``N / SAMPLED_ROLLOUTS``-th rollout); all of the engine's
        sample of a streamed stage (chosen the same way)."""
        n = ev.robustness.size
        if n <= ALL_ROLLOUTS_UP_TO or ev.n_total is not None:
            return np.arange(n)
        keep = set(self._least_robust(ev, max(self.tagged_per_stage, self.scene_per_stage)).tolist())
        keep |= set(np.flatnonzero(np.asarray(ev.failed, bool))[:SAMPLED_ROLLOUTS].tolist())
        keep |= set(np.linspace(0, n - 1, SAMPLED_ROLLOUTS).astype(int).tolist())
        return np.array(sorted(keep))

    def _log_rollouts(self, ev: RolloutsSampled) -> None:
        """The kept traces of a stage (:meth:`kept_rollouts`), one entity per signal with one series per
        rollout, one ``send_columns`` each, and their per-rollout values."""
        s = self.stream
        batch = ev.batch
        t = batch.n_steps
        keep = self.kept_rollouts(ev)
        order = self._least_robust(ev, self.tagged_per_stage)
        rank = {int(i): j for j, i in enumerate(order)}
        failed = np.asarray(ev.failed, bool)
        number = ev.rollout_numbers
        colours, widths, names = [], [], []
        for i in keep.tolist():
            tag = rank.get(i)
            crash = " crash" if failed[i] else ""
            if tag is None:
                colours.append(CRASH_RGBA if failed[i] else SAFE_RGBA)
                widths.append(1.0)
                names.append(f"s{ev.stage} r{number[i]}{crash}")
            else:
                colours.append(TAG_CRASH_RGBA if failed[i] else TAG_RGBA)
                widths.append(2.5)
                names.append(f"s{ev.stage} r{number[i]} least-robust #{tag + 1} rho={ev.robustness[i]:.3g}{crash}")
        index = self._indexes(step=np.arange(t))
        stage = f"stage_{ev.stage:02d}"
        for name in batch.observation_names:
            path = f"rollouts/{name}/{stage}"
            s.log(path, rr.SeriesLines(colors=colours, widths=widths, names=names), static=True)
            s.send_columns(path, indexes=index, columns=rr.Scalars.columns(scalars=batch.signal(name)[keep].T))
        visible = np.isin(keep, order)
        path = f"rollouts/detected/{stage}"
        s.log(
            path,
            rr.SeriesPoints(
                colors=[DETECTED_RGBA] * keep.size, names=[f"{nm} detected" for nm in names],
                marker_sizes=[1.5] * keep.size, visible_series=visible,
            ),
            static=True,
        )  # fmt: skip
        dots = np.where(batch.detected[keep], batch.gap_m[keep], np.nan)
        s.send_columns(path, indexes=index, columns=rr.Scalars.columns(scalars=dots.T))
        s.log(
            f"rollouts/summary/{stage}",
            rr.AnyValues(
                rollout=number[keep],
                log_weight=np.asarray(ev.log_weight, np.float64)[keep],
                failed=failed[keep],
                least_robust=np.isin(keep, order),
                **{f"robustness_{m.replace('-', '_')}": np.asarray(v, np.float64)[keep]
                   for m, v in ev.robustness_by_metric.items()},
            ),
            static=True,
        )  # fmt: skip
        if {"gap_m", "ego_speed_mps"} <= set(batch.observation_names):
            for i in order[: self.scene_per_stage]:
                self._log_scene_lane(ev, int(i))

    def _log_scene_lane(self, ev: RolloutsSampled, i: int) -> None:
        """One lane of the top-down scene: rollout ``i`` of the stage, playable on ``step``.

        Positions (metres along the road) are rebuilt from the observations by
        :func:`pemviz.sinks.scene.car_positions`.
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
        ego_x, lead_x = car_positions(gap, v, p)
        camera_x = ego_x + p.camera_offset_m
        lead_rear = camera_x + gap  # the sight line from the camera to the lead's rear
        ys = np.full(t, y)
        path = f"{SCENE_PATH}/stage_{ev.stage:02d}" + (f"_{lane}" if self.scene_per_stage > 1 else "")
        crash = " crash" if ev.failed[i] else ""
        label = f"stage {ev.stage}{crash}"
        detail = f"stage {ev.stage} ({ev.kind}) rollout {ev.rollout_numbers[i]}: robustness {ev.robustness[i]:.3g}{crash}"
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
                log_ci_low=e.log_ci[0],
                log_ci_high=e.log_ci[1],
                khat=e.khat,
                verdict=e.verdict,
                reason=e.reason,
                n_simulations=ev.n_simulations,
                wall_s=ev.wall_s,
            ),
            static=True,
        )
        self._log_estimate(None, ev)
        self.status_md = (
            f"**Final estimate** mu_hat = {format_probability(e.log_mu_hat, 4)} (log mu_hat = "
            f"{e.log_mu_hat:.4f} nats; {e.n_failures}/{e.n} failures, ESS {e.ess:.2f}) from "
            f"{ev.n_simulations} simulations in {ev.wall_s:.1f} s."
        )
        self._log_description()
        s.flush()
