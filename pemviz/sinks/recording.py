"""Rerun sink: writes an experiment's events into a rerun recording (``.rrd`` file, or a live viewer).

Layout (entity paths and timelines):

- ``description``: Markdown text of the run (static).
- ``proposal/pem`` and ``proposal/stage_KK``: p_PEM(detect | d) and each stage's proposal
  q(detect | d) as series on the ``gap_mm`` timeline (x axis = gap in millimetres).
- ``stages/{gamma,failure_rate,log10_mu_hat,nll,ess}``: per-stage numbers on the ``stage`` timeline.
- ``rollouts/stage_KK/gap_m``: the gap of every rollout of a stage over the ``step`` timeline (also
  indexed by ``stage``), one series per rollout, red when it crashed, grey otherwise.
- ``final/log10_mu_hat`` etc.: the final estimate.

The file is written to ``PATH.partial`` and moved to ``PATH`` when the sink is closed (also after an
exception or Ctrl-C), so a finished recording is never half-written.
"""

from __future__ import annotations

import math
import os
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
)
from pemviz.sampling import format_probability

APP_ID = "pemviz"
CRASH_RGBA = (230, 60, 50, 255)
SAFE_RGBA = (140, 140, 140, 90)
PEM_RGBA = (30, 30, 30, 255)


def stage_colour(stage: int, n_stages: int) -> tuple[int, int, int, int]:
    """Blue (early) to orange (late) for the proposal curves of stages 0..n_stages."""
    f = stage / max(1, n_stages)
    return (int(40 + 215 * f), int(110 + 40 * f), int(230 - 200 * f), 255)


def default_blueprint() -> rrb.Blueprint:
    """Proposal curves, stage metrics, gap traces and the description, ready to read."""
    return rrb.Blueprint(
        rrb.Grid(
            rrb.TimeSeriesView(origin="/proposal", name="q(detect | d) per stage vs PEM  [timeline gap_mm]"),
            rrb.TimeSeriesView(origin="/stages", name="Stage metrics  [timeline stage]"),
            rrb.TimeSeriesView(origin="/rollouts", name="Gap traces, red = crash  [timeline step]"),
            rrb.TextDocumentView(origin="/description", name="Run"),
        ),
        rrb.TimePanel(timeline="gap_mm", expanded=True),
        collapse_panels=False,
    )


class RerunSink:
    """Listens to engine events and logs them to a :class:`rerun.RecordingStream`.

    Args:
        stream: where to log (a file sink, a gRPC connection, or memory).
        rollout_traces: log every rollout's gap trace (the bulk of the recording).
    """

    def __init__(self, stream: rr.RecordingStream, *, rollout_traces: bool = True) -> None:
        self.stream = stream
        self.rollout_traces = rollout_traces
        self.n_stages = 1
        self._pending: RolloutsSampled | None = None

    # -- constructors -------------------------------------------------------------------------------
    @classmethod
    def to_file(cls, path: str | os.PathLike, **kw) -> "RerunSink":
        """A sink that saves to ``path`` (written as ``path.partial``, renamed by :meth:`close`)."""
        path = Path(path)
        stream = rr.RecordingStream(APP_ID)
        partial = path.with_name(path.name + ".partial")
        stream.save(partial, default_blueprint=default_blueprint())
        sink = cls(stream, **kw)
        sink._paths = (partial, path)
        return sink

    @classmethod
    def to_grpc(cls, url: str | None = None, *, serve: bool = False, **kw) -> "RerunSink":
        """A sink that streams to a running viewer (``url``) or serves a gRPC endpoint (``serve``)."""
        stream = rr.RecordingStream(APP_ID)
        if serve:
            stream.serve_grpc(default_blueprint=default_blueprint())
        else:
            stream.connect_grpc(url, default_blueprint=default_blueprint())
        return cls(stream, **kw)

    def close(self) -> Path | None:
        """Flush, finish the file and move it into place; returns the final path (None for gRPC)."""
        self.stream.flush()
        self.stream.disconnect()
        paths = getattr(self, "_paths", None)
        if paths is None:
            return None
        partial, final = paths
        os.replace(partial, final)
        return final

    # -- events -------------------------------------------------------------------------------------
    def __call__(self, event: Event) -> None:
        if isinstance(event, RunStarted):
            self._run_started(event)
        elif isinstance(event, RolloutsSampled):
            self._pending = event
        elif isinstance(event, StageFinished):
            self._stage_finished(event)
        elif isinstance(event, FinalEstimate):
            self._final(event)
        elif isinstance(event, RunCancelled):
            self.stream.log("description/status", rr.TextDocument(f"Run cancelled: {event.reason}"), static=True)

    def _curve(self, path: str, grid_m: np.ndarray, values: np.ndarray, colour, name: str) -> None:
        s = self.stream
        s.log(path, rr.SeriesLines(colors=[colour], names=[name], widths=[2.0]), static=True)
        s.send_columns(
            path,
            indexes=[rr.TimeColumn("gap_mm", sequence=np.round(grid_m * 1000).astype(np.int64))],
            columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=np.float64)),
        )

    def _run_started(self, ev: RunStarted) -> None:
        cfg = ev.config
        self.n_stages = cfg.n_stages + 1 if cfg.method == "adaptive" else 1
        self.grid_m = ev.curve_grid_m
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
        config_md = "\n".join(f"| {k} | `{v}` |" for k, v in vars(cfg).items())
        s.log(
            "description",
            rr.TextDocument(
                f"# pemviz run: {cfg.method}\n\nSafety spec `{ev.formula}` on the braking scenario; "
                f"robustness metric **{cfg.metric}**. Curves are on the `gap_mm` timeline, stage numbers on "
                f"`stage`, rollouts on `step` (switch timelines in the time panel).\n\n"
                f"| setting | value |\n|---|---|\n{config_md}\n",
                media_type=rr.MediaType.MARKDOWN,
            ),
            static=True,
        )
        self._curve("proposal/pem", ev.curve_grid_m, ev.pem_curve, PEM_RGBA, "PEM p(detect | d)")

    def _stage_finished(self, ev: StageFinished) -> None:
        res = ev.result
        s = self.stream
        if not np.all(np.isnan(res.proposal_curve)):
            self._curve(
                f"proposal/stage_{res.stage:02d}",
                self.grid_m,
                res.proposal_curve,
                stage_colour(res.stage, self.n_stages),
                f"q stage {res.stage} ({res.kind})",
            )
        e = res.estimate
        s.set_time("stage", sequence=res.stage)
        for name, value in (
            ("gamma", res.gamma),
            ("failure_rate", e.n_failures / e.n),
            ("log10_mu_hat", e.log10_mu_hat),
            ("nll", e.nll_mean),
            ("ess", e.ess),
        ):
            if math.isfinite(value):
                s.log(f"stages/{name}", rr.Scalars(value))
        if self.rollout_traces and self._pending is not None and self._pending.stage == res.stage:
            self._log_rollouts(self._pending)
        self._pending = None
        s.flush()

    def _log_rollouts(self, ev: RolloutsSampled) -> None:
        """All N gap traces of a stage as one entity with N series (red = crash), one ``send_columns``."""
        s = self.stream
        gap = ev.batch.gap_m
        n, t = gap.shape
        path = f"rollouts/stage_{ev.stage:02d}/gap_m"
        s.log(
            path,
            rr.SeriesLines(
                colors=[CRASH_RGBA if f else SAFE_RGBA for f in ev.failed],
                names=[f"s{ev.stage} r{i}{' crash' if f else ''}" for i, f in enumerate(ev.failed)],
            ),
            static=True,
        )
        s.send_columns(
            path,
            indexes=[rr.TimeColumn("step", sequence=np.arange(t)), rr.TimeColumn("stage", sequence=np.full(t, ev.stage))],
            columns=rr.Scalars.columns(scalars=np.ascontiguousarray(gap.T)),
        )

    def _final(self, ev: FinalEstimate) -> None:
        e = ev.estimate
        s = self.stream
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
        s.log(
            "description/final",
            rr.TextDocument(
                f"**Final estimate** mu_hat = {format_probability(e.log_mu_hat, 4)} "
                f"({e.n_failures}/{e.n} failures, ESS {e.ess:.2f}) from {ev.n_simulations} simulations "
                f"in {ev.wall_s:.1f} s.",
                media_type=rr.MediaType.MARKDOWN,
            ),
            static=True,
        )
        s.flush()
