"""Plain Monte Carlo after a weighted run whose weights back no interval: the cross-entropy sampler's answer on a scene
its proposal family cannot follow.

A proposal learned by cross-entropy can land on a failure region that does not carry the probability: mu_hat may then
be orders of magnitude low by an amount no importance weight can tell; plain Monte Carlo can, at its own cost.
:class:`PlainFallback` first runs the method's stages once more at a larger N (``retry_factor``, :class:`Shifted`), then
draws plain Monte Carlo to the run's precision target or requirement, capped by ``plain_fallback`` times the method's
simulations, :data:`~pemviz.settings.PLAIN_FALLBACK_MOST` and ``max_sims``; skipped only where the cap provably
cannot decide anything (:func:`plain_cannot_decide`). Choosing the answer by the first estimate's verdict, with the
second drawn independently of the first, keeps the second one's coverage (Hesterberg, "Weighted average importance
sampling and defensive mixture distributions", Technometrics 37(2), 1995)."""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, ClassVar

import numpy as np

from pemviz.config import ExperimentConfig
from pemviz.core.estimate import Estimate, format_probability
from pemviz.core.plan import RunPlan
from pemviz.core.problems import Problem
from pemviz.core.requirement import alpha_at_look, parse_requirement
from pemviz.core.rollouts import RolloutBatch
from pemviz.estimators.base import Estimator, StageOutcome, StagePlan
from pemviz.estimators.extras import extras
from pemviz.estimators.fixed import monte_carlo
from pemviz.estimators.precision import PrecisionTarget, default_cap_words
from pemviz.methods import PLAIN_METHOD
from pemviz.settings import FALLBACK, PLAIN_FALLBACK_MOST, plain_fallback_most, settings_of

REL_ERROR = 0.2
"""The relative half-width plain Monte Carlo is drawn to when the run has no precision target of its own."""
FIRST_BATCH = 10_000
"""Plain rollouts of the fallback's first batch (fewer when ``plain_fallback`` is smaller); later batches follow the
precision target's law (:func:`pemviz.estimators.precision.added_batch_size`: as many again while no failure)."""
UNSTREAMED_BATCH = 20_000
"""The most plain rollouts of one batch, divided by the objects a rollout perceives, on a problem that cannot stream
its rollouts chunk by chunk: a batch is then held whole (the engine's own threshold,
:data:`pemviz.engine.experiment.STREAM_ABOVE`)."""
STREAMED_BATCH = 200_000
"""The most plain rollouts of one batch on a problem that streams them: a stage's per-rollout numbers stay bounded."""
MIN_PLAIN = 2
"""The fewest plain rollouts the fallback draws (a run's least N): with fewer left in the run's cap it draws none."""
STREAM = 0x706C61696E
"""Mixed into the seed of the fallback's own stream (``numpy.random.default_rng([seed, STREAM])``)."""
RETRY = 0x7265747279
"""Mixed into the seed of the retry's streams (:func:`retry_seed`)."""


LEAST_EXPECTED_FAILURES = 1.0
"""Plain Monte Carlo is drawn where its cap expects at least this many failures at the largest p the scene states
(:func:`plain_cannot_decide`): it then sees one with probability >= 1 - e^-1 = 63 %, and one failure gives an exact
Clopper-Pearson interval."""
CI_TAIL = 0.05
"""The one-sided level of plain Monte Carlo's bounds in :func:`plain_cannot_decide`: after n rollouts with no failure
p < 1 - CI_TAIL^(1/n), about 3 / n (the rule of three)."""


def rollouts_to_bound(threshold: float) -> int:
    """The fewest plain rollouts whose Clopper-Pearson upper bound with no failure, 1 - 0.05^(1/n), lies below
    ``threshold`` in (0, 1): ln 0.05 / ln(1 - threshold), about 3 / threshold (an int >= 1; Clopper & Pearson,
    Biometrika 26(4), 1934; the rule of three: Hanley & Lippman-Hand, JAMA 249(13), 1983)."""
    return max(1, math.ceil(math.log(CI_TAIL) / math.log1p(-threshold)))


def rollouts_to_decide_below(threshold: float) -> int:
    """The fewest plain rollouts whose first look (:func:`pemviz.core.requirement.decide`, level 1 - alpha_1) can
    decide ``p < threshold`` with no failure: the two-sided Clopper-Pearson upper end 1 - (alpha_1 / 2)^(1/n) below
    ``threshold`` in (0, 1) (an int >= 1)."""
    tail = alpha_at_look(1) / 2.0
    return max(1, math.floor(math.log(tail) / math.log1p(-threshold)) + 1)


def more_budget(spent: int, require: str | None) -> str:
    """What to type where the stages spent the run's whole cap of simulations (``spent``) and left plain Monte Carlo
    none: for ``p < T`` (``<=``) the ``--max-sims`` that leaves it the rollouts which decide it with no failure
    (:func:`rollouts_to_decide_below`), else a larger ``--max-sims``."""
    req = None if require is None else parse_requirement(require)
    if req is None or not req.upper:
        return "a larger --max-sims leaves plain Monte Carlo some"
    need = rollouts_to_decide_below(req.threshold)
    return f"--max-sims {spent + need:,} leaves plain Monte Carlo the {need:,} rollouts that decide {req} if none fails"


def stated_log_p(problem: Any) -> tuple[float, str] | None:
    """The largest p the scene states, as a natural log with its words: its exact answer, else the upper end of its
    reference's interval; None where it states neither. ``problem``: a :class:`~pemviz.core.problems.Problem` or the
    run's :class:`~pemviz.engine.events.RunStarted`."""
    if problem.exact_log_p is not None:
        return float(problem.exact_log_p), "the exact answer"
    if problem.reference is not None:
        return problem.reference.log_ci[1], "the upper end of the reference's interval"
    return None


def plain_cannot_decide(cap: int, stated: tuple[float, str] | None, require: str | None = None) -> str | None:
    """Why plain Monte Carlo of at most ``cap`` rollouts cannot decide the run, or None where it may: without a
    requirement, where the stated p expects fewer than :data:`LEAST_EXPECTED_FAILURES` failures in the cap; with
    one, where neither a bound (:func:`rollouts_to_bound` rollouts) nor failures beyond the threshold can come
    within the cap. No stated p: None.

    Args:
        cap: the most plain rollouts (>= 0).
        stated: :func:`stated_log_p` (natural log of p, its words), or None.
        require: the run's requirement (``"p < 1e-9"``), or None.
    Returns:
        one clause saying why not (e.g. ``p = 8.06e-33 (the exact answer) expects 8.1e-27 failures in 1,000,000
        rollouts``), or None."""
    if cap < 1:
        return "no plain rollout is left in the run's budget"
    if stated is None:
        return None  # nothing rules out a failure
    log_p, words = stated
    said = f"p = {format_probability(log_p, 3)} ({words})"
    sees = math.exp(log_p) * cap
    expects = f"expects {sees:.2g} failures in {cap:,} rollouts"
    if require is None:
        return None if sees >= LEAST_EXPECTED_FAILURES else f"{said} {expects}: it would end with no interval"
    req = parse_requirement(require)
    need = rollouts_to_bound(req.threshold)
    if need <= cap:
        return None  # a bound below T is within the cap: p < T decided met, or p > T refuted
    beyond = log_p > req.log_threshold
    if beyond and sees >= LEAST_EXPECTED_FAILURES:
        return None  # failures beyond T: p < T refuted, or p > T decided met
    side = expects if beyond else "lies below it"
    return (
        f"a bound below {req.threshold:g} needs {need:,} rollouts without a failure, past its cap of {cap:,}, and "
        f"{said} {side}: it could not decide {req}"
    )


def retry_refused(problem: Any) -> str | None:
    """Why the stages of a run on ``problem`` are never run once more, or None where they may be: the scene caps
    every run's verdict below ``reliable`` (:attr:`~pemviz.core.problems.Problem.verdict_cap`)."""
    capped = getattr(problem, "verdict_cap", None)
    if capped is not None and capped[0] != "reliable":
        return f"the scene caps every run of the stages at {capped[0]}"
    return None


def retry_seed(seed: int) -> int:
    """The seed of the retry's stages, from the run's ``seed``: a stream of their own (an int in [0, 2^63))."""
    return int(np.random.default_rng([int(seed), RETRY]).integers(0, 2**63))


def retry_config(config: ExperimentConfig) -> ExperimentConfig | None:
    """The settings of the retry of ``config``'s stages: N times ``retry_factor`` (at most
    :data:`~pemviz.settings.RETRY_MOST_N`, :meth:`pemviz.settings.FallbackSettings.retry_n`) and :func:`retry_seed`;
    None where it has none."""
    n = config.fallback.retry_n(config.n_per_stage, config.stop_rule)
    return None if n is None else config.replace(n_per_stage=n, seed=retry_seed(config.seed))


def with_plain_fallback(estimator: Estimator, config: ExperimentConfig, problem: Problem) -> Estimator:
    """``estimator`` followed by its retry and plain Monte Carlo where its verdict is not ``reliable``
    (:class:`PlainFallback`), or ``estimator`` itself with ``plain_fallback`` = 0 or over an operating design domain
    (whose map is the sampler's)."""
    ratio = int(config.fallback.plain_fallback)
    if ratio <= 0 or getattr(problem, "odd", None) is not None:
        return estimator
    return PlainFallback(estimator, config, problem, ratio)


class _Speaks:
    """What the engine reads of an estimator besides its interface (:mod:`pemviz.estimators.extras`): its pooling, its
    verdict's cap and a requirement's decision, as the estimator :meth:`speaker` names says them."""

    def speaker(self) -> Any:
        raise NotImplementedError

    def pooling(self) -> tuple[str, tuple[float, ...]] | None:
        return extras(self.speaker()).pooling

    @property
    def verdict_cap(self) -> tuple[str, str] | None:
        return extras(self.speaker()).verdict_cap

    @property
    def decision(self) -> Any:
        return extras(self.speaker()).decision


class Shifted(_Speaks):
    """An estimator whose stages are numbered ``offset`` on (a retry's, after the first run's): its plans, the stages
    its result used and its per-stage rollouts carry the shifted numbers; the rest is ``inner``'s.

    Args:
        inner: the estimator.
        offset: added to each of its stage numbers (>= 0)."""

    def __init__(self, inner: Estimator, offset: int) -> None:
        self.inner, self.offset = inner, int(offset)

    @property
    def rng(self) -> np.random.Generator:
        return self.inner.rng

    @rng.setter
    def rng(self, value: np.random.Generator) -> None:
        self.inner.rng = value

    def plan(self) -> RunPlan:
        return RunPlan(tuple(dataclasses.replace(s, stage=s.stage + self.offset) for s in self.inner.plan().stages))

    def next_stage(self) -> StagePlan | None:
        plan = self.inner.next_stage()
        return None if plan is None else dataclasses.replace(plan, stage=plan.stage + self.offset)

    def observe(self, batch: RolloutBatch, failed: np.ndarray, robustness: np.ndarray | None) -> np.ndarray:
        return self.inner.observe(batch, failed, robustness)

    def finish(self) -> StageOutcome:
        return self.inner.finish()

    def result(self) -> tuple[Estimate, tuple[int, ...]]:
        est, used = self.inner.result()
        return est, tuple(k + self.offset for k in used)

    @property
    def stages(self) -> Any:
        own = getattr(self.inner, "stages", None)
        return {k + self.offset: v for k, v in own.items()} if isinstance(own, dict) else own

    def speaker(self) -> Any:
        return self.inner

    @property
    def n_simulations(self) -> int | None:
        return extras(self.inner).n_simulations

    @property
    def needs_chunk_rows(self) -> bool:
        return extras(self.inner).needs_chunk_rows


class PlainFallback(_Speaks):
    """Runs ``inner``; if its interval is not backed (:attr:`Estimate.interval_backed`), its stages once more at a
    larger N (:func:`retry_config`, :class:`Shifted`), and if that is not backed either, plain Monte Carlo rollouts,
    up to ``ratio`` times the simulations of both, as stages of kind ``final`` (module docstring).

    Args:
        inner: the method's estimator (with its stop rule's added batches, if any).
        config: the run's settings: ``seed``, ``weights_until_failure``, ``rel_error`` / ``require``,
            ``max_time_s``, its :attr:`~pemviz.config.ExperimentConfig.fallback`.
        problem: what to estimate.
        ratio: the most plain rollouts per simulation of ``inner`` and its retry (>= 1).
        clock: seconds, monotonic (tests pass their own).
    Raises:
        ValueError: ``ratio`` < 1."""

    SETTINGS: ClassVar[tuple[str, ...]] = settings_of(FALLBACK)
    """The settings it reads, the run's fallback settings (:class:`pemviz.settings.FallbackSettings`), whatever the
    method."""

    def __init__(
        self, inner: Estimator, config: ExperimentConfig, problem: Problem, ratio: int, clock: Any = time.perf_counter
    ) -> None:
        if ratio < 1:
            raise ValueError(f"PlainFallback: ratio must be >= 1, got {ratio}")
        self.inner, self.config, self.problem, self.ratio, self.clock = inner, config, problem, int(ratio), clock
        self.cap = 0
        """The most plain rollouts: ``ratio`` times the method's simulations (set once its stages are done)."""
        self.cap_words = "--plain-fallback"
        """What bounds :attr:`cap`: ``--plain-fallback``, or what the run's cap of simulations leaves."""
        self.t0 = clock()
        self.retry: Shifted | None = None
        """The method's stages once more, once the first run's weights backed no interval."""
        self.plain: PrecisionTarget | None = None
        """The plain Monte Carlo run, once the method's weights backed no interval (nor the retry's)."""
        self.first: Estimate | None = None
        """The method's own estimate, once its first run is done."""
        self.before: Estimate | None = None
        """The estimate plain Monte Carlo follows (the retry's, else the first run's), once the stages are done."""
        self._rollouts = [0, 0]
        """Rollouts of the first run's stages and of the retry's."""
        self.not_retried: str | None = None
        """Why the stages were not run once more although their weights backed no interval, or None."""
        self.not_drawn: str | None = None
        """Why plain Monte Carlo was not drawn although the stages' weights backed no interval
        (:func:`plain_cannot_decide`), or None."""
        self._last_stage = -1

    def __getattr__(self, name: str) -> Any:  # the method's other attributes (its proposal, its settings)
        if name in ("inner", "plain", "retry"):
            raise AttributeError(name)
        return getattr(self.inner, name)

    @property
    def drawing(self) -> Any:
        """The estimator the next batch comes from: the method's, its retry, or plain Monte Carlo."""
        return self.plain if self.plain is not None else self.retry if self.retry is not None else self.inner

    @property
    def rng(self) -> np.random.Generator:
        """The stream the next batch is drawn from: the method's, the retry's, then the fallback's own."""
        return self.drawing.rng

    @rng.setter
    def rng(self, value: np.random.Generator) -> None:
        self.drawing.rng = value

    @property
    def used_plain(self) -> bool:
        """Whether the answer is plain Monte Carlo's: it ran and saw a failure, or neither it nor the stages saw one
        (its rule-of-three bound then says more than stages that bound nothing)."""
        if self.plain is None:
            return False
        stages = self.retry if self.retry is not None else self.inner
        return self.plain.result()[0].n_failures > 0 or stages.result()[0].n_failures == 0

    def plan(self) -> RunPlan:
        """The method's plan: the retry's and the fallback's batches, if any, follow it unplanned."""
        return self.inner.plan()

    def next_stage(self) -> StagePlan | None:
        while self.plain is None:
            stages = self.retry if self.retry is not None else self.inner
            plan = stages.next_stage()
            if plan is not None:
                self._rollouts[self.retry is not None] += plan.n
                self._last_stage = plan.stage
                return plan
            self.before = stages.result()[0]
            if self.retry is None:
                self.first = self.before
                self.retry = self._retry()
                if self.retry is not None:
                    continue
            self.plain = self._start()
            if self.plain is None:
                return None
        return self.plain.next_stage()

    def _retry(self) -> Shifted | None:
        """The method's stages once more (:func:`retry_config`), or None: the first run's interval is backed, it has
        no retry, or no time is left."""
        assert self.first is not None
        config = retry_config(self.config)
        stop = self.config.stop
        if self.first.interval_backed or config is None:
            return None
        self.not_retried = retry_refused(self.problem)
        if self.not_retried is not None:  # the retry's interval could not be backed either
            return None
        if stop.max_time_s is not None and stop.max_time_s - (self.clock() - self.t0) <= 0:
            return None
        check = getattr(self.inner, "check", None)
        return Shifted(config.method_record.builder()(config, self.problem, check), self._last_stage + 1)

    def _start(self) -> PrecisionTarget | None:
        """The plain run, or None: the method's interval is backed, its requirement decided, no time is left, or
        plain Monte Carlo could not decide (:func:`plain_cannot_decide`, the reason kept in :attr:`not_drawn`)."""
        assert self.before is not None
        if self.before.interval_backed:
            return None
        decided = extras(self.drawing).decision
        if decided is not None and decided.outcome != "undecided":
            return None
        stop = self.config.stop
        spent = self._method_simulations()
        most = self.config.most_simulations
        self.cap = plain_fallback_most(self.ratio, spent, most)
        self.cap = 0 if self.cap < MIN_PLAIN else self.cap
        self.cap_words = "--plain-fallback"
        if most is not None and self.cap == most - spent < min(self.ratio * max(1, spent), PLAIN_FALLBACK_MOST):
            whose = f"--max-sims {most:,}" if stop.max_sims is not None else default_cap_words(most)
            self.cap_words = f"what {whose} leaves after the stages' {spent:,}"
        self.not_drawn = plain_cannot_decide(self.cap, stated_log_p(self.problem), stop.require)
        if self.not_drawn is not None:
            if self.cap < 1 and most is not None:  # the stages spent the run's cap: say what would leave some
                self.not_drawn += f" ({self.cap_words}); {more_budget(spent, stop.require)}"
            return None
        changes: dict[str, Any] = {"method": PLAIN_METHOD, "max_sims": self.cap}
        if stop.rel_error is None and stop.require is None:
            changes["rel_error"] = REL_ERROR
        if stop.max_time_s is not None:
            left = stop.max_time_s - (self.clock() - self.t0)
            if left <= 0:
                return None
            changes["max_time_s"] = left
        unstreamed = max(1, UNSTREAMED_BATCH // max(1, self.problem.n_objects))
        batch = STREAMED_BATCH if self.problem.stream is not None else unstreamed
        first = max(MIN_PLAIN, min(FIRST_BATCH, self.cap, batch))
        changes["n_per_stage"] = first  # a cap below the run's N must still hold that first batch
        config = self.config.replace(**changes)
        plain = monte_carlo(self.problem, first, self.config.weights_until_failure, first_stage=self._last_stage + 1)
        plain.rng = np.random.default_rng([self.config.seed, STREAM])
        return PrecisionTarget(plain, config, self.clock, max_batch=batch, cap_words=self.cap_words)

    def observe(self, batch: RolloutBatch, failed: np.ndarray, robustness: np.ndarray | None) -> np.ndarray:
        return self.drawing.observe(batch, failed, robustness)

    def finish(self) -> StageOutcome:
        return self.drawing.finish()

    def result(self) -> tuple[Estimate, tuple[int, ...]]:
        return self.answering.result()

    # -- what the engine reads besides the interface (pemviz.estimators.extras) ----------------------------------

    @property
    def answering(self) -> Any:
        """The estimator whose answer :meth:`result` gives: plain Monte Carlo once it saw a failure or where no
        failure was seen at all (:attr:`used_plain`), else the retry where it ran, else the method's first run."""
        if self.plain is not None and self.used_plain:
            return self.plain
        return self.retry if self.retry is not None else self.inner

    @property
    def stages(self) -> Any:
        """The per-stage rollouts of the answering estimator (the severity curve, the failures' shares)."""
        return getattr(self.answering, "stages", None)

    @property
    def n_simulations(self) -> int | None:
        """Every simulation of the run: the method's (its own count or its rollouts), its retry's and the plain
        rollouts."""
        if self.plain is None and self.retry is None:
            return extras(self.inner).n_simulations
        return self._method_simulations() + (0 if self.plain is None else self.plain.n_simulations)

    def _method_simulations(self) -> int:
        """The simulations of the method's stages and of its retry: each one's own count (e.g. a stop rule's), else
        its rollouts."""
        first = extras(self.inner).n_simulations
        total = int(first) if first is not None else self._rollouts[0]
        if self.retry is not None:
            again = self.retry.n_simulations
            total += int(again) if again is not None else self._rollouts[1]
        return total

    def speaker(self) -> Any:
        return self.answering

    @property
    def decision(self) -> Any:
        """The requirement's decision: plain Monte Carlo's where it decided one (its interval holds p whether or not
        it saw a failure, so a met or violated requirement stands even where the answer is the stages'), else the
        answering estimator's."""
        plain = None if self.plain is None else extras(self.plain).decision
        if plain is not None and plain.outcome != "undecided":
            return plain
        return extras(self.answering).decision

    @property
    def prepared(self) -> str | None:
        return extras(self.inner).prepared

    @property
    def needs_chunk_rows(self) -> bool:
        """Whether the stage being drawn needs its chunks' object rows: the method's may, plain Monte Carlo's not
        (it reads the rows of failures only, rebuilt by replay)."""
        return extras(self.drawing).needs_chunk_rows

    @property
    def stop(self) -> str | None:
        """Why the run stopped, with the fallback's part: what the method's weights said, what its retry gave and
        what plain Monte Carlo gave."""
        own = extras(self.inner).stop
        if self.retry is None and self.plain is None and self.not_retried is None and self.not_drawn is None:
            return own
        parts = [own]
        if self.not_retried is not None and self.first is not None:
            parts.append(
                f"the stages not run once more ({self.first.verdict}): {self.not_retried}, so their retry's weights "
                "could not back an interval either"
            )
        if self.retry is not None and self.first is not None and self.before is not None:
            again = self.retry.inner
            n = getattr(getattr(again, "config", None), "n_per_stage", None)
            parts.append(
                f"the stages once more at N = {n:,} from a stream of their own, the first run's weights backing no "
                f"interval ({self.first.verdict}): {self.before.verdict} (--retry-factor)"
            )
        if self.plain is not None and self.before is not None:
            est = self.plain.result()[0]
            said = (
                f"plain Monte Carlo after the stages, whose weights backed no interval ({self.before.verdict}): "
                f"{est.n_failures:,} failures in {est.n:,} rollouts (at most {self.cap:,}: {self.cap_words})"
            )
            if est.n_failures == 0:
                upper = 1.0 - 0.05 ** (1.0 / max(1, est.n))  # one-sided Clopper-Pearson with no failure
                said += f", p < {upper:.2g} (its 95 % upper bound)" + (
                    "" if self.used_plain else "; the answer is the stages'"
                )
            parts += [said, self.plain.stop]
        if self.not_drawn is not None and self.before is not None:
            bound = self.before.log_lower_bound
            what = (
                f"p >= {format_probability(bound, 2)}, the stages' 95 % lower bound, holds whatever their weights' tail"
                if bound > -math.inf
                else "the stages bound nothing"
            )
            parts.append(
                f"plain Monte Carlo not drawn after the stages, whose weights backed no interval "
                f"({self.before.verdict}): {self.not_drawn} (--plain-fallback); {what}; a larger stage budget or "
                "another method may decide it (next)"
            )
        said_all = [p for p in parts if p]
        return "; ".join(said_all) if said_all else None
