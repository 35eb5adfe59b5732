"""The zero-variance importance sampler q* of a Markov chain, built from an exact value function, the value functions
known in closed form (the toy's, the latched-brake scenario's) and the relative variance that measures how far another
sampler is from q*: research that pemviz does not ship, tested by ``research/tests/test_zero_variance.py`` and used by
``benchmarks/rarity_sweep.py`` (docs/validation.md, "The zero-variance sampler").

With V(s) = P(failure | s), the proposal q*(a | s) = p(a | s) V(s'_a) / V(s) draws only failing rollouts, each of
weight exactly V(s_0) = mu (L'Ecuyer, Mandjes & Tuffin, "Importance sampling in rare event simulation", in Rubino &
Tuffin (eds.), Rare Event Simulation using Monte Carlo Methods, Wiley 2009, Sec. 2.3). For a detector:

    logit q*(detect | s) = logit p(detect | s) + log V(s'_detect) - log V(s'_miss).

V is known in closed form only on small problems (:class:`ToyValue`, :class:`LatchedValue`); elsewhere q* is the
limit a learned proposal approaches (:func:`relative_variance`)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from pemviz.core.detectors import Detector, GapModel
from pemviz.core.estimate import Estimate
from pemviz.core.problems import Problem
from pemviz.estimators.fixed import FixedSampler
from pemviz.scenarios.braking.batched import replay
from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.scenarios.braking.truth_latched import LogitFn, _latched_path
from pemviz.scenarios.toy.simulator import ToyParams
from scipy.special import log_expit

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


@dataclass(frozen=True)
class ShiftedPEM:
    """A PEM whose detection logit is moved by ``shift`` (nats) at every distance: ``logit p'(detect | d) = logit
    p(detect | d) + shift``, so that p'(miss) ~ exp(-shift) p(miss) where misses are rare. A problem with it is as rare
    as wanted, and where the PEM's exact answer is known by enumeration over ``logit_at_gap`` (e.g. the braking
    scenario's, e.g. :mod:`pemviz.scenarios.braking.truth`), so is the shifted one's."""

    pem: GapModel
    shift: float

    def logit_at_gap(self, distance: np.ndarray) -> np.ndarray:
        """logit p'(detect | distance), float64 of the shape of ``distance`` (metres)."""
        return np.asarray(self.pem.logit_at_gap(distance), dtype=np.float64) + self.shift


@dataclass(frozen=True)
class ToyValue:
    """V of the toy in closed form, the zero-variance proposal's value: a moving car at distance d >= safe fails
    with ``V(d) = prod_{k=safe}^{min(d, braking)} (1 - p(k))`` (1 when d < safe); a stopped car never fails (V = 0)."""

    params: ToyParams
    log_v_moving: np.ndarray = field(init=False, repr=False)
    """log V(d, moving) at d = 0..total, float64 [total + 1] (nats)."""

    def __post_init__(self) -> None:
        p = self.params
        d = np.arange(p.total + 1, dtype=np.float64)
        inside = (d >= p.safe) & (d <= p.braking)
        log_miss = np.where(inside, log_expit(-p.detect_logit(d)), 0.0)
        log_miss[d < p.safe] = 0.0
        object.__setattr__(self, "log_v_moving", np.cumsum(log_miss))  # sum over k = safe..min(d, braking)

    def log_value_next(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(log V after a detection, log V after a miss), float64 [N] each, for observations [N, 2] (distance,
        stopped) of :data:`OBSERVATION_NAMES`.

        Raises:
            ValueError: a distance that is not an integer in [0, total]."""
        p = self.params
        obs = np.asarray(obs, dtype=np.float64)
        d = np.rint(obs[:, 0]).astype(np.int64)
        if np.any(np.abs(obs[:, 0] - d) > 1e-9) or np.any((d < 0) | (d > p.total)):
            raise ValueError(f"ToyValue: distances must be integers in [0, {p.total}]")
        stopped = obs[:, 1] > 0.5
        crashed = d < p.safe  # observed below the safe distance: failed, whatever comes next
        miss = np.where(stopped, -np.inf, self.log_v_moving[np.maximum(d - 1, 0)])
        miss = np.where(d - 1 < p.safe, 0.0, miss)
        miss = np.where(stopped & ~crashed, -np.inf, miss)
        detect = np.where((d >= p.safe) & (d <= p.braking), -np.inf, miss)
        return np.where(crashed, 0.0, detect), np.where(crashed, 0.0, miss)


@dataclass(frozen=True)
class LatchedValue:
    """V of the latched-brake scenario along its all-miss path: a detection at effective step t latches the brake, so V
    = crash(t) in {0, 1} after it, and on the path ``V_t = p_t crash(t) + (1 - p_t) V_{t+1}`` at effective steps,
    ``V_{t+1}`` elsewhere, 1 from the path's crash step on; ``V_0`` is :func:`latched_log_failure_probability`. A
    state is on the path when its observation is within ``tolerance`` of the all-miss rollout's
    (:func:`latched_value` checks that q* read from the observation stays zero-variance one step after a detection).

    Attributes:
        observations: the all-miss rollout's observations, float64 [T, F] (gap m, ego speed m/s, lead speed m/s).
        log_v_detect, log_v_miss: log V after a detection / a miss at step t of the all-miss path, [T] (nats).
        log_v0: log V at the start (= log p_fail).
        tolerance: the largest difference per column that still counts as the same state."""

    observations: np.ndarray = field(repr=False)
    log_v_detect: np.ndarray = field(repr=False)
    log_v_miss: np.ndarray = field(repr=False)
    log_v0: float
    tolerance: float = 1e-9

    def path_step(self, obs: np.ndarray) -> np.ndarray:
        """The all-miss step whose observation each row equals (within ``tolerance``), int [N] (-1: off the path)."""
        obs = np.asarray(obs, dtype=np.float64)
        same = np.all(np.abs(obs[:, None, :] - self.observations[None, :, :]) <= self.tolerance, axis=2)  # [N, T]
        return np.where(same.any(axis=1), np.argmax(same, axis=1), -1)

    def log_value_next(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(log V after a detection, log V after a miss), float64 [N] each, for observations [N, F]; equal (0, 0)
        off the all-miss path, where the action changes nothing."""
        k = self.path_step(obs)
        on = k >= 0
        kk = np.maximum(k, 0)
        return np.where(on, self.log_v_detect[kk], 0.0), np.where(on, self.log_v_miss[kk], 0.0)


def latched_value(logit_at_gap: LogitFn, params: BrakingParams | None = None) -> LatchedValue:
    """:class:`LatchedValue` of the latched-brake scenario with ``logit_at_gap`` as the detector.

    Raises:
        ValueError: if two steps of the all-miss path look the same but have different V, or if a state one step
            after a detection that q* can draw looks like an all-miss state where q* differs from p (then the
            observation does not carry enough state for q*)."""
    p = BrakingParams(latched_brake=True) if params is None else dataclasses.replace(params, latched_brake=True)
    T = p.n_steps
    path = _latched_path(p)
    c = path.crash_step
    logit = np.asarray(logit_at_gap(path.gaps), dtype=np.float64)
    log_v = np.zeros(T + 1)  # V before the action of step t; V = 1 from the crash step on
    end = c if c is not None else T - 1
    log_v[end:] = 0.0 if c is not None else -math.inf
    crash_after = dict(zip(path.effective, path.crash_after, strict=False))
    log_v_detect = np.empty(T)
    for t in range(T - 1, -1, -1):
        if t >= end or t not in crash_after:
            log_v_detect[t] = log_v[t + 1] if t < end else log_v[t]
            log_v[t] = log_v[t + 1] if t < end else log_v[t]
            continue
        log_v_detect[t] = 0.0 if crash_after[t] else -math.inf
        if log_v_detect[t] == log_v[t + 1]:  # both actions lead to the same V (exactly, not p + (1 - p) rounded)
            log_v[t] = log_v[t + 1]
        else:
            log_v[t] = np.logaddexp(log_expit(logit[t]) + log_v_detect[t], log_expit(-logit[t]) + log_v[t + 1])
    log_v_miss = np.where(np.arange(T) < end, log_v[1:], log_v[:T])
    value = LatchedValue(replay(p, np.zeros((1, T), bool))[0], log_v_detect, log_v_miss, float(log_v[0]))
    same_v = (log_v_detect == log_v_miss) | (np.isneginf(log_v_detect) & np.isneginf(log_v_miss))
    k = value.path_step(value.observations)
    if np.any((log_v_detect != log_v_detect[k]) | (log_v_miss != log_v_miss[k])):
        raise ValueError("latched_value: two states of the all-miss path look alike but have different V")
    if p.actuation_lag_steps == 1:
        reachable = [t for t in path.effective if crash_after[t] and logit[t] > -np.inf]  # q*(detect at t) > 0
        if any(t + 1 < T and not same_v[t + 1] for t in reachable):
            raise ValueError(
                "latched_value: a state one step after a detection looks like an all-miss state where "
                "q* differs from p: the observation does not show the pending brake q* needs"
            )
    return value
