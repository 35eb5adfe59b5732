"""The zero-variance importance sampler q* of a Markov chain, built from an exact value function, and the relative
variance that measures how far another sampler is from it.

With V(s) = P(failure | s), the proposal q*(a | s) = p(a | s) V(s'_a) / V(s) draws only failing rollouts, each of
weight exactly V(s_0) = mu (L'Ecuyer, Mandjes & Tuffin, "Importance sampling in rare event simulation", in Rubino &
Tuffin (eds.), Rare Event Simulation using Monte Carlo Methods, Wiley 2009, Sec. 2.3). For a detector:

    logit q*(detect | s) = logit p(detect | s) + log V(s'_detect) - log V(s'_miss).

V is known in closed form only on small problems (for example :class:`pemviz.scenarios.toy.ToyValue`,
:class:`pemviz.scenarios.braking.truth_latched.LatchedValue`, for example); elsewhere q* is the limit a learned
proposal approaches (:func:`relative_variance`)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pemviz.core.detectors import Detector
from pemviz.core.estimate import Estimate
from pemviz.core.problems import Problem
from pemviz.estimators.fixed import FixedSampler

LogValueNext = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
"""``log_value_next(obs [N, F]) -> (log V after a detection [N], log V after a miss [N])``, float64 nats
(``-inf`` where failure has become impossible)."""


@dataclass(frozen=True)
class ZeroVarianceDetector:
    """q* as a :class:`~pemviz.core.detectors.Detector`: ``logit q* = logit p + log V(s'_detect) - log V(s'_miss)``.

    Where both actions give the same V (the action changes nothing, or failure is already certain or
    impossible) q* is p itself.

    Attributes:
        target: p, the detector the failure probability is defined under.
        log_value_next: the exact V after each action (:data:`LogValueNext`), e.g. ``ToyValue(params).log_value_next``.
    """

    target: Detector
    log_value_next: LogValueNext

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """logit q*(detect | obs), float64 [N] (``-inf`` / ``+inf`` where one action cannot end in a failure)."""
        logit = np.asarray(self.target.detect_logit(obs), dtype=np.float64)
        log_v_detect, log_v_miss = self.log_value_next(obs)
        with np.errstate(invalid="ignore"):  # inf - inf where both are -inf: handled by the equality
            shift = np.where(log_v_detect == log_v_miss, 0.0, log_v_detect - log_v_miss)
        return logit + shift


@dataclass(frozen=True)
class Draw:
    """One batch from a fixed sampler, weighted: the estimate and the per-rollout numbers behind it.

    Attributes:
        estimate: mu_hat with its diagnostics.
        log_weight: importance log-weights [N] (nats).
        failed: bool [N]."""

    estimate: Estimate
    log_weight: np.ndarray
    failed: np.ndarray


def draw_fixed(problem: Problem, sampler: Detector, n: int, seed: int = 0, weights_until_failure: bool = True) -> Draw:
    """``n`` rollouts of ``problem`` from ``sampler`` through the ``mc`` / ``naive50`` baselines' estimator
    (:class:`~pemviz.estimators.fixed.FixedSampler`), in the engine's order of calls."""
    est = FixedSampler(problem, sampler, n, weights_until_failure, seed)
    plan = est.next_stage()
    assert plan is not None
    batch = problem.simulate(plan.n, plan.sampler, problem.target, est.rng)
    est.observe(batch, problem.failed(batch), None)
    estimate = est.finish().estimate
    log_w, failed, _ = est.stages[plan.stage].arrays()
    return Draw(estimate, log_w, failed)


def relative_variance(log_weight: np.ndarray, failed: np.ndarray, log_mu: float) -> float:
    """Var(w 1[fail]) / mu^2 per rollout, estimated as mean((w 1[fail] / mu - 1)^2) with the exact mu.

    0 for q*; (1 - mu) / mu for plain Monte Carlo. A sampler needs about ``relative_variance / r^2`` rollouts
    for a relative standard error r (Owen, "Monte Carlo theory, methods and examples", 2013, Ch. 9).

    Args:
        log_weight: importance log-weights [N] (nats).
        failed: bool [N] the failures.
        log_mu: the exact log p_fail (nats).
    Raises:
        ValueError: on arrays of different shapes or N = 0."""
    log_weight = np.asarray(log_weight, dtype=np.float64)
    failed = np.asarray(failed, dtype=bool)
    if log_weight.size == 0 or log_weight.shape != failed.shape:
        raise ValueError(
            f"relative_variance: need log_weight and failed of one shape, N >= 1; got "
            f"{log_weight.shape}, {failed.shape}"
        )
    ratio = np.where(failed, np.exp(np.where(failed, log_weight, 0.0) - log_mu), 0.0)
    return float(np.mean(np.square(ratio - 1.0)))


def rollouts_for(rel_error: float, n: int, target: float = 0.1) -> float:
    """Rollouts a method needs for relative error ``target`` if it scales as 1 / sqrt(N): ``n (rel_error / target)^2``
    (0 for a method already exact, inf for one that found nothing)."""
    if not math.isfinite(rel_error):
        return math.inf
    return n * (rel_error / target) ** 2
