"""A precision target for any estimator with a final batch: sample until the interval is as narrow as asked.

After the planned stages :class:`PrecisionTarget` asks for more final batches from the same sampler
(:meth:`Extensible.extend`), pooled with the first, until the relative half-width of a backed 95 % interval is the
target or a cap is hit. The final proposal is fixed before any added batch, so each added rollout is an unbiased term
of the same mean; the coverage kept under this optional stopping is measured by ``benchmarks/honest_numbers.py``."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from pemviz.config import ExperimentConfig
from pemviz.core.estimate import KHAT_UNRELIABLE, Estimate, format_probability
from pemviz.core.plan import RunPlan
from pemviz.core.requirement import Decision, decide, parse_requirement
from pemviz.core.rollouts import RolloutBatch
from pemviz.estimators.base import StageOutcome, StagePlan
from pemviz.estimators.extras import extras
from pemviz.settings import DEFAULT_MAX_SIMS

GROWTH = 4.0
"""An added batch is at most this many times the final rollouts so far: the interval's width is itself noisy, so the
run grows in steps and looks again rather than trusting one extrapolation."""
MARGIN = 1.2
"""An added batch aims at this many times the rollouts the 1 / sqrt(n) law says the target needs."""
MIN_BATCH = 100
"""The fewest rollouts of an added batch."""
HEAVY_LOOKS = 2
"""Looks in a row at which the weights' Pareto k-hat exceeds :data:`~pemviz.core.estimate.KHAT_UNRELIABLE` before the
run holds that more batches of the same sampler cannot back an interval (:func:`cannot_back`): one reading of k-hat
is noisy, two from a growing pool are the tail's."""


def default_cap_words(max_sims: int) -> str:
    """The words for the default cap of ``max_sims`` simulations a run with a stop rule but no ``--max-sims`` has."""
    return f"the default cap of {max_sims:,} simulations (--max-sims)"


def cannot_back(est: Estimate, cap: tuple[str, str] | None, heavy_looks: int) -> str | None:
    """Why more final batches from the sampler that drew ``est`` cannot back its interval, or None where they may:
    they come from the same fixed proposal, so they cannot lift a verdict the sampler caps (``cap``) nor a weight
    tail with k-hat above :data:`~pemviz.core.estimate.KHAT_UNRELIABLE` for :data:`HEAVY_LOOKS` looks running
    (``heavy_looks``), whose variance is in practice infinite (Vehtari, Simpson, Gelman, Yao, Gabry, "Pareto
    smoothed importance sampling", JMLR 25(72), 2024, Sec. 3). Returns one clause, e.g. ``k-hat above 0.7 at 2 looks
    running (2.54 now): ...``, or None."""
    if cap is not None and cap[0] != "reliable":
        return f"the sampler caps their verdict at {cap[0]} ({cap[1]})"
    if heavy_looks >= HEAVY_LOOKS:
        return (
            f"k-hat above {KHAT_UNRELIABLE} at {heavy_looks} looks running ({est.khat:.2f} now): their weights' tail "
            "is heavy, and more weights of the same tail back no interval"
        )
    return None


class Extensible(Protocol):
    """An estimator whose final batch can grow: :meth:`extend` plans ``n`` more rollouts from the final sampler,
    drawn as a new stage (the next stage number, kind ``final``) and pooled with the final batch in :meth:`result`."""

    rng: np.random.Generator

    def plan(self) -> RunPlan: ...

    def next_stage(self) -> StagePlan | None: ...

    def observe(self, batch: RolloutBatch, failed: np.ndarray, robustness: np.ndarray | None) -> np.ndarray: ...

    def finish(self) -> StageOutcome: ...

    def result(self) -> tuple[Estimate, tuple[int, ...]]: ...

    def extend(self, n: int) -> StagePlan: ...

    def final_rollouts(self) -> int: ...

    def simulations_counted(self) -> int | None:
        """The rollout-equivalents the estimator counts itself (the tilt's look-aheads included), or None: the
        rollouts planned are its simulations."""


def added_batch_size(est: Estimate, n_final: int, target: float) -> int:
    """Rollouts of the next added batch: enough, by the 1 / sqrt(n) law, for the interval's relative half-width to
    fall from ``est.rel_half_width`` to ``target`` (times :data:`MARGIN`), as many again as the final rollouts so far
    where it is unknown (no failure yet), between :data:`MIN_BATCH` and :data:`GROWTH` times ``n_final``."""
    width = est.rel_half_width
    if not math.isfinite(width):
        need = n_final
    else:
        need = math.ceil(n_final * ((width / target) ** 2 - 1.0) * MARGIN)
    return int(min(max(need, MIN_BATCH), max(GROWTH * n_final, MIN_BATCH)))


def decision_batch_size(est: Estimate, n_final: int, log_threshold: float) -> int:
    """Rollouts of the next added batch for a requirement: enough, by the 1 / sqrt(n) law, for the interval's relative
    half-width to fall below the estimate's relative distance to the threshold (two thirds of it: the interval of the
    next look is wider), within the bounds of :func:`added_batch_size`."""
    distance = abs(math.expm1(log_threshold - est.log_mu_hat)) if math.isfinite(est.log_mu_hat) else math.nan
    return added_batch_size(est, n_final, max(distance / 1.5, 1e-3) if math.isfinite(distance) else 1.0)


class PrecisionTarget:
    """Runs ``inner`` as planned, then adds final batches until the relative half-width is at most ``rel_error``, a
    requirement ``require`` is decided (:func:`pemviz.core.requirement.decide`), ``max_sims`` simulations (default
    :data:`pemviz.settings.DEFAULT_MAX_SIMS`) or ``max_time_s`` seconds are reached, or no added batch can reach the
    target (:func:`cannot_back`). :attr:`stop` says why in one line; :attr:`decision` is the last look's
    :class:`pemviz.core.requirement.Decision`.

    Args:
        inner: the estimator (:class:`Extensible`).
        config: the run's settings (``rel_error`` set).
        clock: seconds, monotonic (tests pass their own).
        max_batch: the most rollouts of one added batch (None: as many as the target asks).
        cap_words: what the stop line calls the simulations cap (None: ``--max-sims N``, or
            :func:`default_cap_words`).
    Raises:
        ValueError: ``rel_error`` is None."""

    def __init__(
        self,
        inner: Extensible,
        config: ExperimentConfig,
        clock: Callable[[], float] = time.perf_counter,
        max_batch: int | None = None,
        cap_words: str | None = None,
    ) -> None:
        if config.stop_rule is None:
            raise ValueError("PrecisionTarget: the config has neither rel_error nor require")
        self.inner, self.config, self.clock, self.max_batch = inner, config, clock, max_batch
        self.rng = inner.rng
        self.max_sims = int(config.most_simulations or DEFAULT_MAX_SIMS)  # a stop rule's run has a cap
        self.cap_words = cap_words or (
            f"--max-sims {self.max_sims:,}" if config.stop.max_sims is not None else default_cap_words(self.max_sims)
        )
        self.t0 = clock()
        self.n_simulations = 0
        """Rollouts drawn so far (rollout-equivalents where the inner estimator counts them: ``tilt``'s look-aheads)."""
        self.stop: str | None = None
        self.requirement = None if config.stop.require is None else parse_requirement(config.stop.require)
        self.decision: Decision | None = None
        """With a requirement: the last look's decision (None before the first look)."""
        self._planned = True
        self._current: StagePlan | None = None
        self._heavy = 0
        """Looks in a row at which the estimate backed no interval and its k-hat was above KHAT_UNRELIABLE."""

    def __getattr__(self, name: str):  # the inner estimator's other attributes (its proposal, its stages, pooling)
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def plan(self) -> RunPlan:
        """The inner plan, open-ended: added batches follow until the target or a cap."""
        inner = self.inner.plan()
        return RunPlan(inner.stages, open_ended=True)

    def next_stage(self) -> StagePlan | None:
        if self._planned:
            plan = self.inner.next_stage()
            if plan is not None:
                self._current = plan
                return plan
            self._planned = False
        if self.stop is not None:
            return None
        est, _ = self.inner.result()
        elapsed = self.clock() - self.t0
        self._heavy = self._heavy + 1 if not est.interval_backed and est.khat > KHAT_UNRELIABLE else 0
        unbacked = None if est.interval_backed else cannot_back(est, extras(self.inner).verdict_cap, self._heavy)
        if self.requirement is not None:
            look = 1 if self.decision is None else self.decision.look + 1
            self.decision = decide(est, self.requirement, look, plain_mc=self.config.method_record.plain)
            if self.decision.outcome != "undecided":
                self.stop = (
                    f"requirement {self.decision.outcome}: {self.decision.why}, after "
                    f"{self.n_simulations:,} simulations"
                )
                return None
            if unbacked is not None and not est.log_mu_hat >= self.requirement.log_threshold:
                # no interval to come, and a lower bound below the estimate: nothing these batches add decides it
                self.stop = (
                    f"requirement undecided: the stages cannot decide {self.requirement}: {unbacked}, and their "
                    f"estimate {format_probability(est.log_mu_hat, 3)} lies below the threshold, so their lower "
                    f"bound cannot reach it ({self.decision.why}, after {self.n_simulations:,} simulations)"
                )
                return None
            want = decision_batch_size(est, self.inner.final_rollouts(), self.requirement.log_threshold)
        else:
            target, width = self.config.stop.rel_error, est.rel_half_width
            assert target is not None  # the stop rule is rel_error without a requirement (__init__)
            if width <= target and est.interval_backed:  # a narrow interval the weights do not back is no target
                self.stop = (
                    f"target reached: the interval's relative half-width {width:.3g} <= {target:g} after "
                    f"{self.n_simulations:,} simulations"
                )
                return None
            if unbacked is not None:
                self.stop = (
                    f"stopped short of the target: the stages cannot back an interval: {unbacked} (after "
                    f"{self.n_simulations:,} simulations)"
                )
                return None
            want = added_batch_size(est, self.inner.final_rollouts(), target)
        if not est.interval_backed:  # a width the weights do not back: as many rollouts again
            want = max(want, self.inner.final_rollouts())
        left = self.max_sims - self.n_simulations
        per = self.simulations_per_rollout()
        n = min(want, math.floor(left / per), self.max_batch or want)
        cap = None
        if n <= 0:
            cap = f"{self.cap_words} reached"
        elif self.config.stop.max_time_s is not None:
            time_left = self.config.stop.max_time_s - elapsed
            rate = self.n_simulations / elapsed if elapsed > 0 else math.inf
            if time_left <= 0 or rate * time_left < 1:
                cap = f"--max-time {self.config.stop.max_time_s:g} s reached"
            else:
                n = int(min(n, max(1, math.floor(rate * time_left / per))))
        if cap is not None:
            self.stop = self._capped(cap, est)
            return None
        self._current = self.inner.extend(int(n))
        return self._current

    def _capped(self, cap: str, est: Estimate) -> str:
        """The stop line of a run that hit ``cap`` (its words) before its requirement or target, at ``est``."""
        if self.decision is not None:
            return (
                f"requirement undecided within budget: {cap} ({self.decision.why}, after "
                f"{self.n_simulations:,} simulations)"
            )
        target, width = self.config.stop.rel_error, est.rel_half_width
        assert target is not None  # no decision, so no requirement: the target is rel_error's
        shown = (
            "no failure yet"
            if not math.isfinite(width)
            else f"relative half-width {width:.3g} > {target:g}"
            if width > target
            else f"the estimate is {est.verdict}: its weights back no interval"
        )
        return f"stopped at a cap, not at the target: {cap} ({shown} after {self.n_simulations:,} simulations)"

    def simulations_per_rollout(self) -> float:
        """What an added rollout costs in simulations: 1, or for an estimator that counts its own (a tilted
        proposal's look-aheads) its count so far over its final rollouts, its solve included (an over-estimate, so
        the added batches stay under ``max_sims``)."""
        own = self.inner.simulations_counted()
        return 1.0 if own is None else max(1.0, own / max(1, self.inner.final_rollouts()))

    def observe(self, batch: RolloutBatch, failed: np.ndarray, robustness: np.ndarray | None) -> np.ndarray:
        return self.inner.observe(batch, failed, robustness)

    def finish(self) -> StageOutcome:
        if self._current is not None:
            self.n_simulations += self._current.n
        own = self.inner.simulations_counted()
        if own is not None:
            self.n_simulations = own
        return self.inner.finish()

    def result(self) -> tuple[Estimate, tuple[int, ...]]:
        return self.inner.result()
