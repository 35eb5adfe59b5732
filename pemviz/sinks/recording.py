"""Rerun sink: writes an experiment's events into a rerun recording (``.rrd`` file, or a live viewer).

The sink only listens to the engine's events. Its look is :mod:`pemviz.sinks.rerun_views`'s,
its layout :mod:`pemviz.sinks.rerun_blueprint`'s. Timelines ``stage``, ``step`` and ``repetition``; the entity paths
are listed in docs/recording.md. The file is written when the sink is closed (after the run, Ctrl-C or SIGTERM) under a
temporary name and moved to ``PATH``: never half-written, and a kill leaves an existing ``PATH`` as it was."""

from __future__ import annotations

import math
import os
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

import pemviz
from pemviz.core.counterfactuals import LikelyFailure, LogPParts, most_likely_failure
from pemviz.core.estimate import Reference
from pemviz.core.files import atomic_write
from pemviz.core.plan import RunPlan
from pemviz.core.problem_view import ProblemView
from pemviz.core.proposal_view import batch_proposal_view, bins_over, object_detect_probabilities
from pemviz.engine.events import FinalEstimate, RolloutsSampled, RunCancelled, RunStarted, StageFinished, StageResult
from pemviz.sinks import Sink
from pemviz.sinks import colours as C
from pemviz.sinks.population import FailureGroups, SharedGroups, log_failures
from pemviz.sinks.rerun_blueprint import default_blueprint
from pemviz.sinks.rerun_explain import log_explanation
from pemviz.sinks.rerun_features import log_stage_features
from pemviz.sinks.rerun_odd import log_odd_map
from pemviz.sinks.rerun_rollouts import kept_rollouts, least_robust, log_stage_rollouts
from pemviz.sinks.rerun_stage_figures import StageFigures, log_histograms, log_series_styles
from pemviz.sinks.rerun_text import (
    config_markdown,
    description_markdown,
    estimate_markdown,
    final_status,
    final_values,
    stage_row,
)
from pemviz.sinks.rerun_views import (
    PEM_RGBA,
    PROPOSAL_FIG,
    SCENE_PATH,
    contact_share,
    draws_scene,
    intro_markdown,
    log_marginal_proposal,
    log_scene_lane,
    log_thresholds,
)

APP_ID = "pemviz"

FILE_BATCHER = rr.ChunkBatcherConfig(flush_tick=timedelta(seconds=3600), flush_num_bytes=8 << 20, flush_num_rows=4096)
"""A file recording's batching: the rows an entity gets over the run (one per stage) go into a few chunks rather than
one each (a chunk costs about 4 kB of file), so a default run's file is ~25 % smaller; a file is written at
:meth:`RerunSink.close` anyway."""


class RerunSink(Sink):
    """Listens to engine events and logs them to a :class:`rerun.RecordingStream`.

    Args:
        stream: where to log (a file sink, a gRPC connection, or memory).
        rollout_traces: log the rollouts' traces and the scene (the bulk of the recording; all rollouts of a
            stage up to :data:`~pemviz.sinks.rerun_views.ALL_ROLLOUTS_UP_TO`, else a sample of them).
        tagged_per_stage: how many least-robust rollouts of each stage are tagged in the traces and featured
            (entities of their own, :func:`pemviz.sinks.rerun_rollouts.featured`).
        likely_per_stage: how many of each stage's most likely failures are featured.
        scene_per_stage: how many least-robust rollouts of each stage get a lane in the scene (drawn where the
            problem's drawing object draws one, :attr:`pemviz.sinks.drawing.RecordingDrawing.draws_scene`).
        repetition: when set, an index on the ``repetition`` timeline added to every temporal row
            (static figures show the latest repetition).
        problem: the run's :class:`pemviz.core.problems.Problem` (also settable as :attr:`problem` before the run),
            for the failures' severity (``final/failures``' min distance and impact speed,
            ``final/severity_of_failures``); None: not logged."""

    def __init__(
        self,
        stream: rr.RecordingStream,
        *,
        rollout_traces: bool = True,
        tagged_per_stage: int = 3,
        likely_per_stage: int = 3,
        scene_per_stage: int = 1,
        repetition: int | None = None,
        problem: object = None,
    ) -> None:
        self.stream = stream
        self.problem = problem
        self.rollout_traces = rollout_traces
        self.tagged_per_stage = tagged_per_stage
        self.likely_per_stage = likely_per_stage
        self.scene_per_stage = scene_per_stage
        self.repetition = repetition
        self.plan: RunPlan | None = None
        """The run's :class:`~pemviz.core.plan.RunPlan` (from :class:`~pemviz.engine.events.RunStarted`)."""
        self.view: ProblemView | None = None
        """The problem's :class:`~pemviz.core.problem_view.ProblemView` (from :class:`RunStarted`)."""
        self.drawing: object = None
        """The scenario's drawing object (the view's, :class:`pemviz.sinks.drawing.RecordingDrawing`), None: none."""
        self.grid_m = np.zeros(0)
        self.bins_m: np.ndarray | None = None
        """Gap bins of the marginal proposal view (:func:`pemviz.core.proposal_view.bins_over` of the curve grid)."""
        self.likely: LikelyFailure | None = None
        """The most likely failure so far (:func:`pemviz.core.counterfactuals.most_likely_failure`: its stage, row,
        rollout number and log p), None before a failure."""
        self.most_likely: RolloutsSampled | None = None
        """:attr:`likely` as an event of one rollout."""
        self.most_likely_log_p = -math.inf
        """:attr:`likely`'s log p under the PEM (nats over T - 1 steps; the log-probability of its detections plus,
        where the PEM mislocates, the log-density of its measurement errors), -inf before a failure."""
        self.most_likely_parts: LogPParts | None = None
        """:attr:`most_likely_log_p` split into the log-probability of the detections and the log-density of the
        measurement errors (nats; :func:`pemviz.core.counterfactuals.failure_log_p_parts` under the event's target),
        None before a failure or where they cannot be told apart (errors and no target)."""
        self.most_likely_detect: tuple[np.ndarray, np.ndarray] | None = None
        """Each object's p(detect) and q(detect) [T, M] along :attr:`most_likely` (several objects and an event that
        names its detectors; else None), read while the sampler that drew it was unchanged."""
        self.n_failures_seen, self.explained = 0, False
        self.config_md = self.intro_md = self.status_md = self.estimate_md = ""
        self.stage_rows: list[str] = []
        self.exact_log_p: float | None = None
        self.reference: Reference | None = None
        self.n_lanes, self.thresholds_logged = 0, False
        self.curve_stages: list[int] = []
        self.finished = False
        self._pending: RolloutsSampled | None = None
        self.figures: StageFigures | None = None
        """The per-stage series as static figures (:mod:`pemviz.sinks.rerun_stage_figures`), from the run's start."""
        self._groups: SharedGroups = FailureGroups()
        """Each stage's failing rollouts, in which the final estimate's failures are found and grouped (``failures``);
        its scene and problem are set when the run starts."""
        self.serve_url: str | None = None
        self._path: Path | None = None
        self._binary: rr.BinaryStream | None = None
        self._overwrite = False
        self._closed = False
        stream.set_log_time_enabled(False)
        stream.set_log_tick_enabled(False)

    # -- constructors -------------------------------------------------------------------------------
    @classmethod
    def to_file(cls, path: str | os.PathLike, *, overwrite: bool = False, **kw: Any) -> RerunSink:
        """A sink that saves to ``path`` when :meth:`close` commits it: encoded in memory
        (:meth:`rerun.RecordingStream.binary_stream`), written by :meth:`close` to a unique temporary file beside
        ``path`` and moved onto it, so a kill leaves the previous ``path`` untouched and a write error is an
        ``OSError`` with no file left."""
        stream = rr.RecordingStream(APP_ID, batcher_config=FILE_BATCHER)
        sink = cls(stream, **kw)
        sink._binary = rr.binary_stream(stream)  # what stream.binary_stream() calls, in words mypy reads
        sink._path = Path(path)
        sink._overwrite = overwrite
        return sink

    @classmethod
    def to_grpc(
        cls, url: str | None = None, *, serve: bool = False, grpc_port: int | None = None, **kw: Any
    ) -> RerunSink:
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
    def to_stdout(cls, **kw: Any) -> RerunSink:
        """A sink that writes the recording to standard output (``pemviz run --stdout | rerun -``)."""
        stream = rr.RecordingStream(APP_ID)
        stream.stdout()
        return cls(stream, **kw)

    def close(self, commit: bool = True) -> Path | None:
        """Finish the recording and (file sinks) write it; returns the file written (None for gRPC or no commit). A
        run that ended without a final estimate or a cancellation is marked interrupted; ``commit=False`` drops a
        file recording; closing twice is harmless.

        Raises:
            OSError: the file could not be written (nothing is left; an existing file is untouched).
            pemviz.core.files.OutputExists: the file appeared meanwhile and ``overwrite`` was not given."""
        if self._closed:
            return None
        self._closed = True
        if not self.finished and self.intro_md:
            done = len(self.stage_rows)
            self.status_md = f"**Interrupted** after {done} finished stage{'s' * (done != 1)}: no final estimate."
            self._log_description()
        if commit and self.intro_md:
            self._explain()
        if self._path is None:
            self.stream.flush()
            self.stream.disconnect()
            return None
        self.stream.flush()
        assert self._binary is not None  # a file sink (to_file) encodes into it
        data = self._binary.read(flush=True) or b""
        self.stream.disconnect()
        self._binary = None
        if not commit:
            return None

        def write(tmp: str) -> None:
            Path(tmp).write_bytes(data)

        return atomic_write(self._path, write, overwrite=self._overwrite)

    # -- events -------------------------------------------------------------------------------------
    def share_failure_groups(self, groups: SharedGroups) -> None:
        """Use ``groups`` (a listener of the same run, heard before or after this sink) for the final estimate's
        failures instead of grouping them again."""
        self._groups = groups

    def on_rollouts_sampled(self, event: RolloutsSampled) -> None:
        self._pending = event
        self._groups(event)
        log_stage_features(self.stream, event, self.problem, self._colour(event.stage))  # while its sampler drew

    def on_run_cancelled(self, event: RunCancelled) -> None:
        self.finished = True
        self.status_md = f"**Run cancelled** ({event.reason}) after {len(event.stages)} finished stages."
        self._log_description()
        self._explain()
        self.stream.flush()

    # -- helpers ------------------------------------------------------------------------------------
    def _indexes(self, **sequences: np.ndarray) -> list[rr.TimeColumn]:
        n = len(next(iter(sequences.values())))
        cols = [rr.TimeColumn(name, sequence=np.asarray(seq, dtype=np.int64)) for name, seq in sequences.items()]
        if self.repetition is not None:
            cols.append(rr.TimeColumn("repetition", sequence=np.full(n, self.repetition, dtype=np.int64)))
        return cols

    def _colour(self, stage: int) -> tuple[int, int, int, int]:
        """A stage's colour, blue (stage 0) to orange (the plan's last stage)."""
        return C.stage_rgba(stage, C.stage_span(self.plan))

    def _label(self, stage: int, kind: str) -> str:
        """A stage's name in the run's plan (:meth:`pemviz.core.plan.RunPlan.label`)."""
        assert self.plan is not None  # set when the run starts, before any stage
        return self.plan.label(stage, kind)

    def _log_description(self) -> None:
        text = description_markdown(self.intro_md, self.status_md, self.stage_rows, self.config_md)
        self.stream.log("description", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), static=True)

    def _log_proposal_legend(self) -> None:
        """Legend right of the reference-state plot (data units: metres, probability): the PEM, the first and last
        stage's curves."""
        shown = sorted({self.curve_stages[0], self.curve_stages[-1]}) if self.curve_stages else []
        entries = [("PEM", PEM_RGBA)] + [(f"q stage {k}", self._colour(k)) for k in shown]
        entries.append(("dots: elites", PEM_RGBA))
        x0, x1 = float(self.grid_m.min()), float(self.grid_m.max())
        x = x1 + 0.13 * (x1 - x0)
        pos = [[x, 0.9 - j * 0.12] for j in range(len(entries))]
        self.stream.log(
            "proposal/data/legend",
            rr.Points2D(
                pos, radii=-0.01, colors=[c for _, c in entries], labels=[t for t, _ in entries], show_labels=True
            ),
            static=True,
        )

    def _log_estimate(self, res: StageResult | None, final: FinalEstimate | None = None) -> None:
        """The ``estimate`` view: mu_hat with its interval, k-hat, verdict and the exact answer where known."""
        if final is not None:
            e, where = final.estimate, "Final estimate"
        else:
            assert res is not None  # a stage's estimate, where not the final one
            e, where = res.estimate, f"Estimate after {self._label(res.stage, res.kind)}"
        self.estimate_md = estimate_markdown(e, where, self.exact_log_p, self.reference, final)
        self.stream.log("estimate", rr.TextDocument(self.estimate_md, media_type=rr.MediaType.MARKDOWN), static=True)

    # -- run started ----------------------------------------------------------------------------------
    def on_run_started(self, ev: RunStarted) -> None:
        cfg, state = ev.config, ev.config.method_record.feature_view  # a state proposal: its feature view
        self.plan, self.view, self.drawing = ev.plan, ev.problem, ev.problem.drawing
        if self._groups.problem is None:  # its own; a shared one knows the run's problem already
            self._groups.drawing, self._groups.problem = ev.problem.drawing, self.problem
        self.grid_m = np.asarray(ev.curve_grid_m, dtype=np.float64)
        self.bins_m = bins_over(self.grid_m) if np.ptp(self.grid_m) > 0 else None
        self.exact_log_p, self.reference = ev.exact_log_p, ev.reference
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
                scenario=cfg.scenario,
                scenario_params=", ".join(f"{name}={value!r}" for name, value in cfg.scenario_params),
            ),
        )
        s.send_recording_name(f"pemviz {cfg.method} {cfg.metric} seed {cfg.seed}")
        s.send_blueprint(default_blueprint(len(self.plan.stages) * self.scene_per_stage, self.view, features=state))
        self.intro_md = intro_markdown(ev)
        self.config_md = config_markdown(cfg)
        self._log_description()
        log_series_styles(s, draws_scene(self.drawing))
        known = (
            ev.exact_log_p
            if ev.exact_log_p is not None and math.isfinite(ev.exact_log_p)
            else (ev.reference.log_p if ev.reference is not None else None)
        )
        self.figures = StageFigures(
            s, self.plan.last_stage, None if known is None else known / math.log(10.0), draws_scene(self.drawing)
        )
        PROPOSAL_FIG.draw_axes(s, (float(self.grid_m.min()), float(self.grid_m.max())), (0.0, 1.0))
        s.log(
            "proposal/data/pem",
            rr.LineStrips2D([np.column_stack([self.grid_m, ev.pem_curve])], colors=PEM_RGBA, radii=-2.0),
            static=True,
        )
        self._log_proposal_legend()

    # -- stage finished -------------------------------------------------------------------------------
    def on_stage_finished(self, event: StageFinished) -> None:
        s, res = self.stream, event.result
        colour = self._colour(res.stage)
        s.set_time("stage", sequence=res.stage)
        if self.repetition is not None:
            s.set_time("repetition", sequence=self.repetition)
        if not np.all(np.isnan(res.proposal_curve)):
            strip = [np.column_stack([self.grid_m, res.proposal_curve])]
            s.log(
                f"proposal/data/stage_{res.stage:02d}", rr.LineStrips2D(strip, colors=colour, radii=-1.5), static=True
            )
            s.log(
                "proposal/data/current",
                rr.LineStrips2D(strip, colors=colour, radii=-4.0, labels=[self._label(res.stage, res.kind)]),
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
            "khat": e.khat,
        }
        if math.isfinite(e.log10_mu_hat):
            lo, hi = e.shown_log_ci  # a bound alone where the weights back no interval: no upper line then
            values["log10_mu_hat/ci_low"] = lo / math.log(10.0)
            if math.isfinite(hi):
                values["log10_mu_hat/ci_high"] = hi / math.log(10.0)
        if self.exact_log_p is not None and math.isfinite(self.exact_log_p):
            values["log10_mu_hat/exact"] = self.exact_log_p / math.log(10.0)
        elif self.reference is not None:
            values["log10_mu_hat/reference"] = self.reference.log_p / math.log(10.0)
        pending = self._pending if self._pending is not None and self._pending.stage == res.stage else None
        if pending is not None:
            values.update(self._log_marginal(pending, colour))
            values.update(contact_share(self.drawing, pending.batch, pending.failed))
        for key, value in values.items():
            if math.isfinite(value):
                s.log(f"stages/{key}", rr.Scalars(value))
        if self.figures is not None:
            self.figures.add(res.stage, values)  # the same series as static figures: shown on every timeline

        self.stage_rows.append(stage_row(res, self._label(res.stage, res.kind)))
        self._log_description()
        self._log_estimate(res)

        if pending is not None:
            log_histograms(self.stream, pending)
            self._track_most_likely(pending)
            if self.rollout_traces:
                self._log_rollouts(pending)
        self._pending = None
        if self._binary is None:  # a viewer shows the stage now; a file's rows batch into fewer, larger chunks
            s.flush()

    def _log_marginal(self, ev: RolloutsSampled, colour: tuple[int, ...]) -> dict[str, float]:
        """The stage's marginal proposal view (bars on ``stage``); returns its mean miss probabilities inside the
        window for the per-stage series (none when its rollouts report no gap)."""
        if self.bins_m is None:
            return {}
        assert self.view is not None  # set when the run starts, with bins_m
        window = self.view.thresholds.window if self.view.thresholds is not None else float(self.bins_m[-1])
        pv = batch_proposal_view(ev.batch, self.bins_m, window)
        if pv is None:
            return {}
        self.stream.set_time("step", sequence=0)  # on step, the last stage's bars (each stage's on stage)
        log_marginal_proposal(self.stream, pv, colour)
        self.stream.disable_timeline("step")
        return {"miss_in_window/q": pv.q_miss_window, "miss_in_window/pem": pv.p_miss_window}

    def kept_rollouts(self, ev: RolloutsSampled) -> np.ndarray:
        """Indices of the rollouts recorded in full (:func:`pemviz.sinks.rerun_rollouts.kept_rollouts`)."""
        return kept_rollouts(ev, max(self.tagged_per_stage, self.likely_per_stage, self.scene_per_stage))

    def _track_most_likely(self, ev: RolloutsSampled) -> None:
        """Keep the run's most likely failure so far (:func:`pemviz.core.counterfactuals.most_likely_failure`, ties:
        the earlier) as an event of one rollout."""
        self.n_failures_seen += int(np.count_nonzero(ev.failed))
        likely = most_likely_failure(ev, self.likely)
        if likely is self.likely:
            return
        assert likely is not None  # None only while no failure is seen, and self.likely is None then
        self.likely, self.most_likely_log_p = likely, likely.log_p
        i = np.array([likely.row])
        self.most_likely = RolloutsSampled(
            ev.stage,
            ev.kind,
            ev.batch.select(i),
            ev.robustness[i],
            {m: np.asarray(v)[i] for m, v in ev.robustness_by_metric.items()},
            np.asarray(ev.failed)[i],
            np.asarray(ev.log_weight)[i],
            index=ev.rollout_numbers[i],
        )
        features = getattr(self.problem, "features", None)  # a state proposal is asked with the replayed features
        self.most_likely_detect = object_detect_probabilities(ev.batch, likely.row, ev.sampler, ev.target, features)
        target = ev.target if ev.target is not None else getattr(self.problem, "target", None)
        try:
            self.most_likely_parts = LogPParts.of(ev.batch, likely.row, target)
        except ValueError:  # measurement errors and no target to tell their density from the detections
            self.most_likely_parts = None

    def _log_rollouts(self, ev: RolloutsSampled) -> None:
        """The kept traces of a stage and its featured rollouts
        (:func:`pemviz.sinks.rerun_rollouts.log_stage_rollouts`), the thresholds once, and the scene's lanes."""
        s = self.stream
        assert self.view is not None  # set when the run starts, before any stage
        if not self.thresholds_logged:
            log_thresholds(s, self.view, ev.batch.n_steps, self._indexes)
            self.thresholds_logged = True
        log_stage_rollouts(
            s,
            ev,
            self.view,
            self._label(ev.stage, ev.kind),
            self.tagged_per_stage,
            self.likely_per_stage,
            self._indexes,
        )
        if draws_scene(self.drawing):
            for i in least_robust(ev, self.scene_per_stage):
                path = f"{SCENE_PATH}/stage_{ev.stage:02d}" + (f"_{self.n_lanes}" if self.scene_per_stage > 1 else "")
                if not log_scene_lane(s, path, self.n_lanes, ev, int(i), self.drawing, self._indexes):
                    break
                self.n_lanes += 1

    def _explain(self) -> None:
        """Log the most likely failure's entities once (:func:`pemviz.sinks.rerun_explain.log_explanation`)."""
        if self.explained or self.view is None:
            return
        self.explained = True
        best = self.most_likely
        name = self._label(best.stage, best.kind) if best is not None else ""
        log_explanation(
            self.stream,
            best,
            self.most_likely_log_p,
            self.n_failures_seen,
            self.view,
            name,
            self._indexes,
            object_detect=self.most_likely_detect,
            parts=self.most_likely_parts,
        )

    # -- final --------------------------------------------------------------------------------------
    def on_final_estimate(self, ev: FinalEstimate) -> None:
        s = self.stream
        self.finished = True
        s.log("final", rr.AnyValues(**final_values(ev)), static=True)
        self._log_estimate(None, ev)
        self.status_md = final_status(ev)
        if ev.severity is not None and len(ev.severity.points) > 1:
            levels = [pt.level if pt.level is not None else math.nan for pt in ev.severity.points]
            s.log(
                "final/severity",
                rr.AnyValues(
                    level=levels,
                    log_p=[pt.estimate.log_mu_hat for pt in ev.severity.points],
                    verdict=[pt.estimate.verdict for pt in ev.severity.points],
                ),
                static=True,
            )
        self._explain()  # before the grouping, which a shared listener may still be computing
        self._groups(ev)  # the final estimate's failures, grouped (FailureGroups keeps each stage's failing rows)
        if ev.failures is not None and self._groups.grouping is not None:
            self.status_md += log_failures(s, self._groups.grouping, self.problem)
        if ev.odd_map is not None:  # over an operating design domain: where p_ODD comes from
            log_odd_map(s, ev.odd_map)
        self._log_description()
        s.flush()
