"""Sinks: listeners of the experiment engine's events (console table, rerun recording, rollout file, viser panel).

A sink only listens; it never drives the engine (the viser panel may set the cancel token). :class:`Sink` is their
base: one method per event of :mod:`pemviz.events` and one dispatch. :class:`StageClock` is the one clock of a run
that the console and the panel predict a stage's time from.
"""

from __future__ import annotations

import math
import time
from typing import Callable

from pemviz.events import (
    Event,
    FinalEstimate,
    RolloutChunk,
    RolloutsSampled,
    RunCancelled,
    RunFinished,
    RunStarted,
    StageFinished,
    StageResult,
    StageStarted,
)

HANDLERS: dict[type, str] = {
    RunStarted: "on_run_started",
    StageStarted: "on_stage_started",
    RolloutChunk: "on_rollout_chunk",
    RolloutsSampled: "on_rollouts_sampled",
    StageFinished: "on_stage_finished",
    FinalEstimate: "on_final_estimate",
    RunFinished: "on_run_finished",
    RunCancelled: "on_run_cancelled",
}
"""Event type -> the :class:`Sink` method that takes it."""


class Sink:
    """An engine listener: calling it with an event calls the method for the event's type (:data:`HANDLERS`); each
    does nothing unless a sink overrides it. An object of another type is ignored."""

    def __call__(self, event: Event) -> None:
        for kind in type(event).__mro__:
            name = HANDLERS.get(kind)
            if name is not None:
                getattr(self, name)(event)
                return

    def on_run_started(self, event: RunStarted) -> None:
        """The run starts: its config, plan (:class:`~pemviz.plan.RunPlan`) and problem view."""

    def on_stage_started(self, event: StageStarted) -> None:
        """A stage starts drawing its rollouts."""

    def on_rollout_chunk(self, event: RolloutChunk) -> None:
        """A chunk of a stage's rollouts has been simulated and weighed."""

    def on_rollouts_sampled(self, event: RolloutsSampled) -> None:
        """A stage's rollouts (or a bounded sample of a streamed stage) with their robustness and weights."""

    def on_stage_finished(self, event: StageFinished) -> None:
        """A stage has its threshold, elites, fit and estimate."""

    def on_final_estimate(self, event: FinalEstimate) -> None:
        """The run's answer."""

    def on_run_finished(self, event: RunFinished) -> None:
        """The run has ended with its answer."""

    def on_run_cancelled(self, event: RunCancelled) -> None:
        """The run was stopped before its answer."""


def expected_stage_s(done: list[StageResult], kind: str, n_rollouts: int,
                     sample_s_per_rollout: float = math.nan) -> float:  # fmt: skip
    """Expected seconds of a stage of ``n_rollouts`` rollouts (nan when nothing comparable has run yet).

    A CE stage takes as long as the last CE stage did (sampling plus the proposal update). The final batch
    only samples: ``n_rollouts`` times the seconds per rollout measured while the last CE stage sampled
    (``sample_s_per_rollout``). Pretraining predicts neither (its time is the fit of a few rollouts).
    """
    if kind == "final":
        return n_rollouts * sample_s_per_rollout
    alike = [r for r in done if r.kind == kind]
    return alike[-1].wall_s if alike else math.nan


class StageClock(Sink):
    """The wall clock of a run as its events arrive (``now``: seconds, default ``time.perf_counter``).

    Attributes:
        t0: when the run started; stage_t0: when the current stage started.
        sample_s_per_rollout: seconds per rollout while the last CE stage sampled, from its start to its
            :class:`~pemviz.events.RolloutsSampled`, over all of its rollouts (``n_rollouts``: a streamed stage's
            too, not its sample's); it predicts the final batch. nan before.
        done: the finished stages' results.
    """

    def __init__(self, now: Callable[[], float] = time.perf_counter) -> None:
        self.now = now
        self.t0 = self.stage_t0 = now()
        self.sample_s_per_rollout = math.nan
        self.done: list[StageResult] = []

    def on_run_started(self, event: RunStarted) -> None:
        self.t0 = self.stage_t0 = self.now()
        self.sample_s_per_rollout, self.done = math.nan, []

    def on_stage_started(self, event: StageStarted) -> None:
        self.stage_t0 = self.now()

    def on_rollouts_sampled(self, event: RolloutsSampled) -> None:
        if event.kind == "ce":
            self.sample_s_per_rollout = (self.now() - self.stage_t0) / max(1, event.n_rollouts)

    def on_stage_finished(self, event: StageFinished) -> None:
        self.done = self.done + [event.result]

    def expected_s(self, kind: str, n_rollouts: int) -> float:
        """Expected seconds of a stage (:func:`expected_stage_s` from the stages done and the time per rollout)."""
        return expected_stage_s(self.done, kind, n_rollouts, self.sample_s_per_rollout)

    def elapsed_s(self) -> float:
        """Seconds since the run started."""
        return self.now() - self.t0

    def stage_elapsed_s(self) -> float:
        """Seconds since the current stage started."""
        return self.now() - self.stage_t0
