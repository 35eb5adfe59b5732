"""Sinks: listeners of the engine's events (console table, rerun recording, rollout file, viser panel), which never
drive it. :class:`Sink` is their base (one method per event of :mod:`pemviz.engine.events`); :class:`StageClock` is
the clock the console and the panel predict time left from."""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, get_args

from pemviz.core.plan import RunPlan
from pemviz.engine import events as ev
from pemviz.engine.cost import (
    COST,
    N_STEPS,
    CostConstants,
    FollowOn,
    StageCost,
    follow_on,
    mc_rollouts,
    pilot_speed,
    stage_cost,
    start_reading,
    with_drift,
)

if TYPE_CHECKING:
    from pemviz.config import ExperimentConfig
    from pemviz.engine.resources import LoadReading, TaskTimes

MAX_SCALE = 20.0
"""The most a :class:`StageClock` scales a prediction by (either way): a first stage slowed by a one-off start
(an import, a warm-up) must not blow up the prediction of the rest."""
SCALE_PRIOR = 0.25
"""The model's prediction counts as this share of the whole plan's predicted seconds measured at the model's speed:
the first, short stages move the scale of what is left only as far as their share of the run warrants."""

HANDLERS: dict[type, str] = {
    kind: "on_" + re.sub("(?<!^)(?=[A-Z])", "_", kind.__name__).lower() for kind in get_args(ev.Event)
}
"""Event type (:data:`pemviz.engine.events.Event`) -> the :class:`Sink` method that takes it: ``RunStarted`` ->
``on_run_started``."""


class Sink:
    """An engine listener: calling it with an event calls the method for the event's type (:data:`HANDLERS`); each
    does nothing unless a sink overrides it. An object of another type is ignored."""

    def __call__(self, event: ev.Event) -> None:
        for kind in type(event).__mro__:
            name = HANDLERS.get(kind)
            if name is not None:
                getattr(self, name)(event)
                return

    def on_run_started(self, event: ev.RunStarted) -> None:
        """The run starts: its config, plan (:class:`~pemviz.core.plan.RunPlan`) and problem view."""

    def on_stage_started(self, event: ev.StageStarted) -> None:
        """A stage starts drawing its rollouts."""

    def on_rollout_chunk(self, event: ev.RolloutChunk) -> None:
        """A chunk of a stage's rollouts has been simulated and weighed."""

    def on_rollouts_sampled(self, event: ev.RolloutsSampled) -> None:
        """A stage's rollouts (or a bounded sample of a streamed stage) with their robustness and weights."""

    def on_stage_finished(self, event: ev.StageFinished) -> None:
        """A stage has its threshold, elites, fit and estimate."""

    def on_final_estimate(self, event: ev.FinalEstimate) -> None:
        """The run's answer."""

    def on_run_finished(self, event: ev.RunFinished) -> None:
        """The run has ended with its answer."""

    def on_run_cancelled(self, event: ev.RunCancelled) -> None:
        """The run was stopped before its answer."""


class StageClock(Sink):
    """The wall clock of a run as its events arrive, and the time its stages and the whole run have left (``now``:
    seconds, default ``time.perf_counter``).

    Each stage has a predicted time (:func:`pemviz.engine.cost.plan_costs`); as stages end the clock scales what is
    left by measured / predicted, simulating and what follows per kind of stage separately, and before any stage by the
    machine's load (``slowdown()``, default :func:`pemviz.engine.cost.start_reading`, whose :attr:`reading` also
    prices a pooled batch's workers). :meth:`run_most_s` adds what may follow the planned stages
    (:func:`pemviz.engine.cost.follow_on`).

    Attributes:
        t0: when the run started; stage_t0: when the current stage started; sampled_t: when its rollouts were
            sampled (None before).
        simulate_scale: measured / predicted seconds of simulating so far (:attr:`load` before any).
        done: the finished stages' results.
        follow: what may follow the planned stages (None: nothing)."""

    def __init__(
        self,
        now: Callable[[], float] = time.perf_counter,
        constants: CostConstants = COST,
        slowdown: Callable[[], float] | None = None,
    ) -> None:
        self.now = now
        self.constants = constants
        self._slowdown = slowdown
        self.load = 1.0
        """The machine's load at the run's start as a slowdown (:func:`pemviz.engine.resources.load_slowdown`): the
        scale of every prediction before the run has measured its own speed."""
        self.load_since: TaskTimes | None = None
        """Where the window the load is read over opens (:func:`pemviz.engine.resources.tasks_now`): when the clock is
        made, or earlier where its maker sets it (``pemviz run``: before the run's problem is built)."""
        self.pilot: list[tuple[int, float]] = []
        """The pilot of the scene's rollouts its maker timed before the run (:func:`pemviz.engine.experiment.
        scene_pilot`), which sets :attr:`speed` at the run's start; none: the model's speed."""
        self.speed = 1.0
        """How many times the model's CPU seconds the run's work takes here now (:func:`pemviz.engine.cost.
        pilot_speed` of :attr:`pilot`)."""
        self.reading: LoadReading | None = None
        """The load read at the run's start (:func:`pemviz.engine.resources.read_load`), which also prices a pooled
        batch (:func:`pemviz.engine.cost.stage_cost`); None: an idle machine (a ``slowdown`` given)."""
        if slowdown is None:
            from pemviz.engine.resources import tasks_now

            self.load_since = tasks_now()
        self.t0 = self.stage_t0 = now()
        self.sampled_t: float | None = None
        self.plan: RunPlan | None = None
        self._config: ExperimentConfig | None = None
        self._n_steps, self._look_ahead_s, self._stream_above = N_STEPS, 0.0, 20_000
        self.predicted: dict[int, StageCost] = {}
        self.current: ev.StageStarted | None = None
        self.done: list[ev.StageResult] = []
        self._measured: dict[str, list[float]] = {}  # part ("simulate", or "after:" + kind) -> [measured, predicted s]
        self._planned: dict[str, float] = {}  # part ("simulate", "after") -> the plan's predicted seconds
        self.follow: FollowOn | None = None
        self._last = -1  # the planned stages' last number
        self._phases: dict[str, list[tuple[int, str]]] = {}  # "plan", "retry" -> (stage, kind) of each stage
        self._rollouts: dict[int, int] = {}  # stage -> its rollouts, as started

    def on_run_started(self, event: ev.RunStarted) -> None:
        self.t0 = self.stage_t0 = self.now()
        self.sampled_t, self.current, self.done = None, None, []
        self.plan = event.plan
        self._config, self._n_steps = event.config, event.problem.n_steps or N_STEPS
        from pemviz.engine.experiment import stream_above  # the run's engine is loaded: where it streams a stage

        self._stream_above = stream_above(event.config, event.problem.n_objects)
        if self._slowdown is None:  # as the panel's cost line reads them
            self.speed, self.load, self.reading = start_reading(
                event.config, self.pilot, self._n_steps, since=self.load_since
            )
        else:
            self.speed, self.load = pilot_speed(event.config, self.pilot, self._n_steps), float(self._slowdown())
            self.reading = None
        self._look_ahead_s = float(event.problem.look_ahead_s)
        # an open-ended plan's added batches follow its last stage: no time is said for it (run_left_s)
        self.follow = None if event.plan.open_ended else follow_on(event.config, event.plan, event)
        self._rollouts = {}
        self._last = event.plan.stages[-1].stage if event.plan.stages else -1
        retry = self.follow.retry if self.follow is not None else None
        shift = self._last + 1
        self._phases = {
            "plan": [(s.stage, s.kind) for s in event.plan.stages],
            "retry": [(s.stage + shift, s.kind) for s in (retry.stages if retry is not None else ())],
        }
        self.predicted = {s.stage: self._model(s.kind, s.n_rollouts, s.stage) for s in event.plan.stages}
        for s in retry.stages if retry is not None else ():
            self.predicted[s.stage + shift] = self._model(s.kind, s.n_rollouts, s.stage + shift)
        self._measured = {}
        self._planned = {
            "simulate": sum(c.simulate_s for c in self.predicted.values()),
            "after": sum(c.after_s for c in self.predicted.values()),
        }

    def on_stage_started(self, event: ev.StageStarted) -> None:
        self.stage_t0, self.sampled_t, self.current = self.now(), None, event
        self._rollouts[event.stage] = event.n_rollouts

    def phase(self, stage: int) -> str:
        """Where stage number ``stage`` is: ``plan`` (a planned stage), ``retry`` (the stages once more) or ``plain``
        (the plain rollouts after them), by the engine's numbering (:class:`pemviz.engine.cost.FollowOn`)."""
        if self.follow is None or stage <= self._last:
            return "plan"
        return "retry" if stage <= self.follow.retry_last else "plain"

    def on_rollouts_sampled(self, event: ev.RolloutsSampled) -> None:
        self.sampled_t = self.now()
        if self.current is not None and self.current.stage == event.stage:  # all of a streamed stage's rollouts
            predicted = self._model(event.kind, event.n_rollouts, event.stage).simulate_s
            self._add(self._part(event.stage), self.sampled_t - self.stage_t0, predicted)

    def on_stage_finished(self, event: ev.StageFinished) -> None:
        self.done = self.done + [event.result]
        if self.current is not None and self.sampled_t is not None and self.current.stage == event.result.stage:
            cost = self._model(self.current.kind, self.current.n_rollouts, self.current.stage)
            self._add("after:" + self.current.kind, self.now() - self.sampled_t, cost.after_s)
        self.current = None

    def _add(self, part: str, measured_s: float, predicted_s: float) -> None:
        if predicted_s > 0.0:
            m = self._measured.setdefault(part, [0.0, 0.0])
            m[0] += measured_s
            m[1] += predicted_s

    def _scale(self, part: str) -> float | None:
        measured, predicted = self._measured.get(part, (0.0, 0.0))
        if predicted <= 0.0:
            return None
        prior = SCALE_PRIOR * self._planned.get(part.split(":")[0], 0.0)  # pseudo-seconds at the load's speed
        return min(MAX_SCALE, max(1.0 / MAX_SCALE, (measured + prior * self.load) / (predicted + prior)))

    @property
    def simulate_scale(self) -> float:
        scale = self._scale("simulate")
        return self.load if scale is None else scale

    def _part(self, stage: int | None) -> str:
        """The measured part simulating stage ``stage`` counts in: the plain rollouts' own, or every other stage's."""
        return "simulate:plain" if stage is not None and self.phase(stage) == "plain" else "simulate"

    def after_scale(self, kind: str) -> float:
        """Measured / predicted seconds after the rollouts of the stages of ``kind`` so far (the simulating scale
        before one)."""
        scale = self._scale("after:" + kind)
        return self.simulate_scale if scale is None else scale

    def _model(self, kind: str, n_rollouts: int, stage: int | None = None) -> StageCost:
        """The model's prediction of a stage of this run (nan before the run starts): a retry's stage as the planned
        stage of its number, a plain rollouts' stage as plain Monte Carlo's final batch."""
        if self._config is None:
            return StageCost(math.nan, math.nan)
        phase = "plan" if stage is None else self.phase(stage)
        c, cfg = self.constants, self._config
        kw: dict[str, Any] = {"speed": self.speed, "load": self.reading, "stream_above": self._stream_above}
        if phase == "plain":
            return stage_cost(cfg, "final", n_rollouts, self._n_steps, c, model="plain", **kw)
        if phase == "retry" and stage is not None:
            stage -= self._last + 1
        cost = stage_cost(cfg, kind, n_rollouts, self._n_steps, c, stage, **kw)
        if self._look_ahead_s > 0.0:  # the problem's look-ahead: the estimator weighs the rollouts before they are out
            cost = StageCost(cost.simulate_s + n_rollouts * self._look_ahead_s, cost.after_s)
        return cost

    def _scaled(self, cost: StageCost, kind: str, stage: int | None = None) -> tuple[float, float]:
        part = self._part(stage)
        measured = self._scale(part) if part != "simulate" else None  # plain rollouts: their own speed, once measured
        simulate = self.simulate_scale if measured is None else measured
        return cost.simulate_s * simulate, cost.after_s * self.after_scale(kind)

    def expected_s(self, kind: str, n_rollouts: int, stage: int | None = None) -> float:
        """Expected seconds of a stage of ``kind`` and ``n_rollouts`` (numbered ``stage``; None: a planned one): its
        predicted simulating and what follows (:func:`pemviz.engine.cost.stage_cost`), each scaled by what the run
        measured so far; nan before the run starts."""
        return sum(self._scaled(self._model(kind, n_rollouts, stage), kind, stage))

    def stage_left_s(self) -> float:
        """Expected seconds left in the current stage (0 once it has taken longer than expected; nan: none going)."""
        if self.current is None:
            return math.nan
        kind, stage = self.current.kind, self.current.stage
        simulate, after = self._scaled(self._model(kind, self.current.n_rollouts, stage), kind, stage)
        if self.sampled_t is None:
            return max(0.0, simulate - (self.now() - self.stage_t0)) + after
        return max(0.0, after - (self.now() - self.sampled_t))

    def _at(self) -> int:
        """The current stage's number, else the last finished one's (-1 before any)."""
        return self.current.stage if self.current is not None else (self.done[-1].stage if self.done else -1)

    def _stages_s(self, phase: str, after: int) -> float:
        """Expected seconds of the stages of ``phase`` numbered above ``after``."""
        stages = [(s, kind) for s, kind in self._phases.get(phase, ()) if s > after]
        return sum(sum(self._scaled(self.predicted[s], kind, s)) for s, kind in stages)

    def _plain_s(self, n: float) -> float:
        """Expected seconds of ``n`` plain rollouts more (as one batch; 0 for none)."""
        if n <= 0 or self._config is None:
            return 0.0
        return self.expected_s("final", int(n), self.follow.retry_last + 1 if self.follow is not None else None)

    def _plain_rest(self) -> tuple[float, float]:
        """Plain rollouts still to draw after the current batch: those the precision target needs at the failure rate
        seen so far (class docstring), and the most (the cap's rest)."""
        from pemviz.estimators.fallback import REL_ERROR
        from pemviz.estimators.precision import MARGIN

        assert self.follow is not None and self._config is not None
        drawn = sum(n for s, n in self._rollouts.items() if self.phase(s) == "plain")
        plain = [r for r in self.done if self.phase(r.stage) == "plain"]
        seen = sum(self._rollouts.get(r.stage, r.estimate.n) for r in plain)
        failures = sum(r.estimate.n_failures for r in plain)
        most = max(0, self.follow.plain_most - drawn)
        stop = self._config.stop
        if seen == 0 or stop.require is not None:  # nothing seen yet, or a decision: the current batch may end it
            return 0.0, float(most)
        rate = failures / seen if failures else min(1.0, 3.0 / seen)
        need = MARGIN * mc_rollouts(math.log(rate), stop.rel_error or REL_ERROR)
        return float(min(most, max(0.0, need - drawn))), float(most)

    def run_left_s(self) -> float:
        """Expected seconds left in the whole run: the current stage's rest and every later stage of the plan
        (:meth:`expected_s`), or of the retry while it runs, or the plain rollouts still needed while they run
        (class docstring); nan for an open-ended plan (AMS) or before the run starts."""
        if self.plan is None or self.plan.open_ended:
            return math.nan
        at = self._at()
        rest = self.stage_left_s() if self.current is not None else 0.0
        phase = self.phase(at)
        if phase == "plain":
            return rest + self._plain_s(self._plain_rest()[0])
        return rest + self._stages_s(phase, at)

    def run_most_s(self) -> float:
        """Expected seconds left in the whole run if all that may follow the planned stages runs (:attr:`follow`):
        what :meth:`run_left_s` says, the retry's stages still to come and the plain rollouts up to their cap; as
        :meth:`run_left_s` where nothing may follow."""
        left = self.run_left_s()
        if self.follow is None:  # nothing may follow: what the load's drift may add (pemviz.engine.cost.with_drift)
            return with_drift(left, self.load)
        if not math.isfinite(left):
            return left
        at = self._at()
        phase = self.phase(at)
        if phase == "plain":
            return left - self._plain_s(self._plain_rest()[0]) + self._plain_s(self._plain_rest()[1])
        retry = self._stages_s("retry", at) if phase == "plan" else 0.0
        return left + retry + self._plain_s(self.follow.plain_most)

    def elapsed_s(self) -> float:
        """Seconds since the run started."""
        return self.now() - self.t0

    def stage_elapsed_s(self) -> float:
        """Seconds since the current stage started."""
        return self.now() - self.stage_t0
