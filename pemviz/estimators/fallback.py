"""Plain Monte Carlo after a weighted run whose weights back no interval: the cross-entropy sampler's answer on a scene
its proposal family cannot follow.

A proposal learned by cross-entropy can land on a failure region that is not the one that carries the probability
(e.g. on a stack that mislocates objects behind a tracker, a family that tilts the detections finds failures by
twenty misses while the likely ones need one large range error and two misses at the right steps): its failures then
weigh e^-30 each, a few dominate, and the verdict is ``unreliable`` while mu_hat is orders of magnitude low. No
importance weight can say by how much. Plain Monte Carlo can, at its own cost, wherever p is not too small for the
rollouts one is willing to draw: :class:`PlainFallback` draws them after the method's stages when its verdict is not
``reliable``, to the run's precision target (``rel_error``, else :data:`REL_ERROR`) or requirement, at most
``plain_fallback`` times the simulations the method spent and never more than :data:`MOST` nor than the run's own
``max_sims`` allows (the default 500: a million after the default run's 2,100; a quick run of a few
hundred gets a proportionate few) (:class:`pemviz.estimators.precision.PrecisionTarget` on
:func:`pemviz.estimators.fixed.monte_carlo`), from a stream of their own (the method's rollouts are those of the run
without it). Its answer is plain Monte Carlo's (Clopper-Pearson interval: exact, whatever the sampler before it)
where those rollouts saw a failure; else the method's, with plain Monte Carlo's 95 % upper bound in the stop line.

Choosing the answer by the first estimate's verdict, and the second estimate from rollouts independent of the first,
keeps the second one's coverage: its rollouts are drawn whatever the first run found (Hesterberg, "Weighted average
importance sampling and defensive mixture distributions", Technometrics 37(2), 1995, for the idea that the target
bounds what a poor proposal can cost).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from pemviz.config import ExperimentConfig
from pemviz.core.estimate import Estimate
from pemviz.core.plan import RunPlan
from pemviz.core.problems import Problem
from pemviz.core.rollouts import RolloutBatch
from pemviz.estimators.base import Estimator, StageOutcome, StagePlan
from pemviz.estimators.extras import extras
from pemviz.estimators.fixed import monte_carlo
from pemviz.estimators.precision import PrecisionTarget

REL_ERROR = 0.2
"""The relative half-width plain Monte Carlo is drawn to when the run has no precision target of its own."""
FIRST_BATCH = 10_000
"""Plain rollouts of the fallback's first batch (fewer when ``plain_fallback`` is smaller); later batches follow the
precision target's law (:func:`pemviz.estimators.precision.added_batch_size`: as many again while no failure)."""
MOST = 1_000_000
"""The most plain rollouts after any run, whatever its size (``plain_fallback`` times the stages' simulations below it:
a large run of the stages gets no larger fallback)."""
UNSTREAMED_BATCH = 20_000
"""The most plain rollouts of one batch, divided by the objects a rollout perceives, on a problem that cannot stream
its rollouts chunk by chunk (or on another executor): a batch is then held whole (the engine's own threshold,
:data:`pemviz.engine.experiment.STREAM_ABOVE`)."""
STREAMED_BATCH = 200_000
"""The most plain rollouts of one batch on a problem that streams them: a stage's per-rollout numbers stay bounded."""
STREAM = 0x706C61696E
"""Mixed into the seed of the fallback's own stream (``numpy.random.default_rng([seed, STREAM])``)."""


def with_plain_fallback(estimator: Estimator, config: ExperimentConfig, problem: Problem) -> Estimator:
    """``estimator`` followed by plain Monte Carlo where its verdict is not ``reliable`` (:class:`PlainFallback`), or
    ``estimator`` itself with ``plain_fallback`` = 0 or over an operating design domain (whose verdict is capped
    anyway, and whose map is the sampler's)."""
    ratio = int(config.adaptive.plain_fallback)
    if ratio <= 0 or getattr(problem, "odd", None) is not None:
        return estimator
    return PlainFallback(estimator, config, problem, ratio)


class PlainFallback:
    """Runs ``inner``; if its estimate's interval is not backed (:attr:`Estimate.interval_backed`), plain Monte Carlo
    rollouts, up to ``ratio`` times its simulations, follow as stages numbered after its last (kind ``final``), and
    :meth:`result` is theirs once they saw a failure (module docstring).

    Args:
        inner: the method's estimator (with its stop rule's added batches, if any).
        config: the run's settings: ``seed``, ``weights_until_failure``, ``rel_error`` / ``require``, ``max_time_s``.
        problem: what to estimate.
        ratio: the most plain rollouts per simulation of ``inner`` (>= 1).
        clock: seconds, monotonic (tests pass their own).
    Raises:
        ValueError: ``ratio`` < 1.
    """

    def __init__(
        self, inner: Estimator, config: ExperimentConfig, problem: Problem, ratio: int, clock: Any = time.perf_counter
    ) -> None:
        if ratio < 1:
            raise ValueError(f"PlainFallback: ratio must be >= 1, got {ratio}")
        self.inner, self.config, self.problem, self.ratio, self.clock = inner, config, problem, int(ratio), clock
        self.cap = 0
        """The most plain rollouts: ``ratio`` times the method's simulations (set once its stages are done)."""
        self.t0 = clock()
        self.plain: PrecisionTarget | None = None
        """The plain Monte Carlo run, once the method's weights backed no interval."""
        self.before: Estimate | None = None
        """The method's own estimate, once its stages are done."""
        self._inner_rollouts = 0
        self._last_stage = -1

    def __getattr__(self, name: str) -> Any:  # the method's other attributes (its proposal, its settings)
        if name in ("inner", "plain"):
            raise AttributeError(name)
        return getattr(self.inner, name)

    @property
    def rng(self) -> np.random.Generator:
        """The stream the next batch is drawn from: the method's, then the fallback's own."""
        return self.inner.rng if self.plain is None else self.plain.rng

    @rng.setter
    def rng(self, value: np.random.Generator) -> None:
        (self.inner if self.plain is None else self.plain).rng = value

    @property
    def used_plain(self) -> bool:
        """Whether the answer is plain Monte Carlo's (it ran and saw a failure)."""
        return self.plain is not None and self.plain.result()[0].n_failures > 0

    def plan(self) -> RunPlan:
        """The method's plan: the fallback's batches, if any, follow it unplanned."""
        return self.inner.plan()

    def next_stage(self) -> StagePlan | None:
        if self.plain is None:
            plan = self.inner.next_stage()
            if plan is not None:
                self._inner_rollouts += plan.n
                self._last_stage = plan.stage
                return plan
            self.before = self.inner.result()[0]
            self.plain = self._start()
            if self.plain is None:
                return None
        return self.plain.next_stage()

    def _start(self) -> PrecisionTarget | None:
        """The plain run, or None: the method's interval is backed, or no time is left."""
        assert self.before is not None
        if self.before.interval_backed:
            return None
        stop = self.config.stop
        spent = self._method_simulations()
        self.cap = min(self.ratio * max(1, spent), MOST)
        if stop.max_sims is not None:  # the run's own cap holds for everything it simulates
            self.cap = min(self.cap, stop.max_sims - spent)
        if self.cap < 1:
            return None
        changes: dict[str, Any] = {"method": "mc", "max_sims": self.cap}
        if stop.rel_error is None and stop.require is None:
            changes["rel_error"] = REL_ERROR
        if stop.max_time_s is not None:
            left = stop.max_time_s - (self.clock() - self.t0)
            if left <= 0:
                return None
            changes["max_time_s"] = left
        config = self.config.replace(**changes)
        streams = self.problem.stream is not None and config.execution.executor == "serial"
        most = STREAMED_BATCH if streams else max(1, UNSTREAMED_BATCH // max(1, self.problem.n_objects))
        first = min(FIRST_BATCH, self.cap, most)
        plain = monte_carlo(self.problem, first, self.config.weights_until_failure, first_stage=self._last_stage + 1)
        plain.rng = np.random.default_rng([self.config.seed, STREAM])
        return PrecisionTarget(plain, config, self.clock, max_batch=most)

    def observe(self, batch: RolloutBatch, failed: np.ndarray, robustness: np.ndarray | None) -> np.ndarray:
        return (self.inner if self.plain is None else self.plain).observe(batch, failed, robustness)

    def finish(self) -> StageOutcome:
        return (self.inner if self.plain is None else self.plain).finish()

    def result(self) -> tuple[Estimate, tuple[int, ...]]:
        if self.plain is not None and self.used_plain:
            return self.plain.result()
        return self.inner.result()

    # -- what the engine reads besides the interface (pemviz.estimators.extras) ----------------------------------

    @property
    def answering(self) -> Any:
        """The estimator whose answer :meth:`result` gives."""
        return self.plain if self.plain is not None and self.used_plain else self.inner

    @property
    def stages(self) -> Any:
        """The per-stage rollouts of the answering estimator (the severity curve, the failures' shares)."""
        return getattr(self.answering, "stages", None)

    @property
    def n_simulations(self) -> int | None:
        """Every simulation of the run: the method's (its own count or its rollouts) and the plain rollouts."""
        if self.plain is None:
            return extras(self.inner).n_simulations
        return self._method_simulations() + self.plain.n_simulations

    def _method_simulations(self) -> int:
        """The simulations of the method's stages: its own count (e.g. a stop rule's), else its rollouts."""
        own = extras(self.inner).n_simulations
        return int(own) if own is not None else self._inner_rollouts

    def pooling(self) -> tuple[str, tuple[float, ...]] | None:
        return extras(self.answering).pooling

    @property
    def verdict_cap(self) -> tuple[str, str] | None:
        return extras(self.answering).verdict_cap

    @property
    def decision(self) -> Any:
        return extras(self.answering).decision

    @property
    def prepared(self) -> str | None:
        return extras(self.inner).prepared

    @property
    def needs_chunk_rows(self) -> bool:
        """Whether the stage being drawn needs its chunks' object rows: the method's may, plain Monte Carlo's not
        (it reads the rows of failures only, rebuilt by replay)."""
        return extras(self.inner if self.plain is None else self.plain).needs_chunk_rows

    @property
    def stop(self) -> str | None:
        """Why the run stopped, with the fallback's part: what the method's weights said and what plain Monte Carlo
        gave."""
        own = extras(self.inner).stop
        if self.plain is None or self.before is None:
            return own
        est = self.plain.result()[0]
        said = (
            f"plain Monte Carlo after the stages, whose weights backed no interval ({self.before.verdict}): "
            f"{est.n_failures:,} failures in {est.n:,} rollouts (at most {self.cap:,}: --plain-fallback)"
        )
        if est.n_failures == 0:
            upper = 1.0 - 0.05 ** (1.0 / max(1, est.n))  # one-sided Clopper-Pearson with no failure
            said += f", p < {upper:.2g} (its 95 % upper bound); the answer is the stages'"
        parts = [p for p in (own, said, self.plain.stop) if p]
        return "; ".join(parts) if parts else None
