"""The runs of the conformance kit (:mod:`pemviz.testing`): an experiment driven by the engine (:func:`run_engine`),
with its rollout file and recording (:func:`run_with_files`), each sink's errors kept for the check that owns it.
Importing this module imports no simulator, PEM, recording library or torch."""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pemviz.config import ExperimentConfig
    from pemviz.core.problems import Problem


class GuardedListener:
    """A listener whose exceptions are kept, not raised: the run goes on, the check that owns the listener fails.
    An exception at the run's start is kept as :attr:`refused` (a sink saying the run is not for it)."""

    def __init__(self, listener: Callable[[Any], None]) -> None:
        self.listener = listener
        self.refused: str | None = None
        self.error: str | None = None

    def __call__(self, event: Any) -> None:
        from pemviz.engine.events import RunStarted

        if self.refused is not None or self.error is not None:
            return
        try:
            self.listener(event)
        except Exception as exc:  # the sink's code: any error is the finding
            if isinstance(exc, ValueError) and isinstance(event, RunStarted):
                self.refused = str(exc)
            else:
                self.error = f"{type(exc).__name__} at {type(event).__name__}: {exc}"


@dataclass
class KitRun:
    """One engine run: its final event, every stage's and the final estimate, and the files its sinks wrote."""

    final: Any
    estimates: list[Any]
    rollouts: Path | None = None
    rollouts_refused: str | None = None
    rollouts_error: str | None = None
    recording: Path | None = None
    recording_error: str | None = None


def run_engine(config: ExperimentConfig, problem: Problem, listeners: tuple = ()) -> KitRun:
    """Run ``config`` on ``problem`` through the engine (:class:`pemviz.engine.experiment.Experiment`)."""
    from pemviz.engine.events import FinalEstimate, StageFinished
    from pemviz.engine.experiment import Experiment

    finals: list[Any] = []
    estimates: list[Any] = []

    def hear(event: Any) -> None:
        if isinstance(event, StageFinished):
            estimates.append(event.result.estimate)
        elif isinstance(event, FinalEstimate):
            finals.append(event)
            estimates.append(event.estimate)

    Experiment(config, [*listeners, hear], problem=problem).run()
    if not finals:
        raise RuntimeError(f"the run of {config.method} on {problem.name} ended without a final estimate")
    return KitRun(finals[0], estimates)


def run_with_files(config: ExperimentConfig, problem: Problem, folder: Path, stem: str) -> KitRun:
    """:func:`run_engine` with a rollout file (:class:`pemviz.sinks.rollouts.RolloutSink`) and a recording
    (:meth:`pemviz.sinks.recording.RerunSink.to_file`) written to ``folder`` (``dt_s = 1`` in the sidecar where the
    problem knows no step)."""
    from pemviz.sinks.recording import RerunSink
    from pemviz.sinks.rollouts import RolloutSink

    rollout_sink = RolloutSink(folder / f"{stem}.parquet", overwrite=True)
    rollout_sink.problem = problem
    recorder = RerunSink.to_file(folder / f"{stem}.rrd", overwrite=True, problem=problem)
    rollouts, recording = GuardedListener(rollout_sink), GuardedListener(recorder)
    try:
        run = run_engine(config, problem, (rollouts, recording))
    except BaseException:
        recorder.close(commit=False)
        rollout_sink.close()
        raise
    if rollouts.refused is not None or rollouts.error is not None:
        rollout_sink.close()
    try:
        path = recorder.close(commit=recording.error is None)
    except Exception as exc:
        path, recording.error = None, recording.error or f"close() raised {type(exc).__name__}: {exc}"
    run.rollouts, run.rollouts_refused, run.rollouts_error = rollout_sink.written, rollouts.refused, rollouts.error
    run.recording, run.recording_error = path, recording.error
    return run


class files_folder:
    """``with files_folder(path) as where``: ``path`` (made if need be), or a temporary folder removed afterwards."""

    def __init__(self, path: str | Path | None) -> None:
        self.path = path
        self._tmp: tempfile.TemporaryDirectory[str] | None = None

    def __enter__(self) -> Path:
        if self.path is not None:
            Path(self.path).mkdir(parents=True, exist_ok=True)
            return Path(self.path)
        self._tmp = tempfile.TemporaryDirectory(prefix="pemviz-check-")
        return Path(self._tmp.name)

    def __exit__(self, *exc: object) -> None:
        if self._tmp is not None:
            self._tmp.cleanup()
