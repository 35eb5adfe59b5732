"""Importance weights of logged rollouts: the two weight conventions, the per-step density of a mixture over whole
rollouts, and the mean-weight check of a logged sampling density.

Conventions (Owen 2013, "Monte Carlo theory, methods and examples", ch. 9; Innes & Ramamoorthy 2022, eq. 6 and
Algorithm 1); the last action changes nothing, so neither weighs it:

- ``full``: w = prod_{t < T-1} p(a_t | s_t) / q(a_t | .), the paper's product over the whole trajectory;
- ``to-failure``: the same product stopped at the failure step t_f (the first violation of the ``G[a,b]`` formula),
  pemviz's default. Unbiased too: the partial products are a q-martingale of mean 1 and t_f a bounded stopping time
  (optional stopping), so E_q[1{fail} W_{t_f}] = P_p(fail) with less variance.

Weights are formed in float64 log space throughout."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pemviz.core import libm
from pemviz.core.detectors import Detector, action_log_prob, errors_log_density, reads_state
from pemviz.core.features import FeaturesFn, with_state
from pemviz.core.odd_proposal import parameter_log_ratio

CONVENTIONS = ("to-failure", "full")
"""The weight conventions: ``to-failure`` (stopped at the failure step) and ``full`` (every step but the last)."""

CHECK_Z = 4.0
"""Standard errors beyond which the mean importance weight is called far from 1 (a correct log q: probability
< 1e-4 under a normal approximation of the mean)."""


def convention(weights_until_failure: bool) -> str:
    """The name of the convention an :class:`~pemviz.config.ExperimentConfig` weighs with."""
    return "to-failure" if weights_until_failure else "full"


def mixture_step_log_q(
    log_q: np.ndarray,
    shares: Sequence[float] | np.ndarray,
    densities: bool = False,
    log_start: np.ndarray | None = None,
) -> np.ndarray:
    """Per-step log density of a mixture over whole rollouts, float64 [N, T] (nats): q_mix(a_t | .) = M_t - M_{t-1}
    with M_t = logsumexp_k (log c_k + sum_{s <= t} log q_k) and M_{-1} = 0 (the balance heuristic, Veach & Guibas
    1995, step by step), so its sum over any first k steps is log sum_k c_k prod_{s < k} q_k.

    Args:
        log_q: float64 [K, N, T], log q_k(a_t | s_t) of each component (nats).
        shares: c_k > 0, [K], summing to 1.
        densities: the steps hold log densities (may be positive); else probabilities, whose conditionals are
            clipped at 0.
        log_start: None, or float64 [K, N]: each component's log-density of what was drawn before the first step
            relative to the target's (over an ODD); then M_{-1} = logsumexp_k (log c_k + log_start_k)
            (:func:`stage_log_q_params`).
    Returns:
        float64 [N, T], each entry <= 0 unless ``densities``.
    Raises:
        ValueError: shapes that do not match, or shares not positive."""
    log_q = np.asarray(log_q, dtype=np.float64)
    c = np.asarray(shares, dtype=np.float64)
    if log_q.ndim != 3 or c.shape != (log_q.shape[0],) or not (c > 0).all():
        raise ValueError(
            f"mixture_step_log_q: log_q must be [K, N, T] and shares [K] > 0, got {log_q.shape}, " f"{c.shape}"
        )
    start = np.zeros(log_q.shape[:2]) if log_start is None else np.asarray(log_start, dtype=np.float64)
    running = libm.logsumexp(libm.log(c)[:, None, None] + start[:, :, None] + np.cumsum(log_q, axis=2), axis=0)  # M_t
    first = np.zeros((running.shape[0], 1)) if log_start is None else stage_log_q_params(start, c)[:, None]
    before = np.concatenate([first, running[:, :-1]], axis=1)
    step = running - before
    return step if densities else np.minimum(step, 0.0)  # a conditional probability: <= 0 up to rounding


def stage_log_q_params(log_start: np.ndarray, shares: Sequence[float] | np.ndarray) -> np.ndarray:
    """log sum_k c_k q_k(theta) / p_ODD(theta), float64 [N] (nats): the parameters' term of a mixture's log density
    (:attr:`pemviz.core.rollouts.RolloutBatch.log_q_params`), from each component's ``log_start`` [K, N] (0 for one
    drawing them from the ODD) and shares c_k [K]."""
    return libm.logsumexp(libm.log(np.asarray(shares, dtype=np.float64))[:, None] + log_start, axis=0)


def component_of(start: int, n: int, sizes: Sequence[int]) -> np.ndarray:
    """int64 [n]: the mixture component of rollouts ``start .. start + n - 1`` of a stage drawn component by
    component, ``sizes[k]`` rollouts from component k, in order."""
    edges = np.cumsum(sizes)
    return np.searchsorted(edges, np.arange(start, start + n), side="right").astype(np.int64)


def stage_log_q(
    batch: Any,
    parts: Sequence[tuple[int, Detector]],
    target: Detector | None,
    start: int = 0,
    features: FeaturesFn | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The per-step log density the rollouts of a stage were weighed with, and each rollout's component.

    Args:
        batch: rollouts ``start .. start + n - 1`` of the stage (a :class:`~pemviz.core.rollouts.RolloutBatch`, [n, T]).
        parts: the stage's samplers in the order drawn, ``(rollouts, detector)`` each (one: no mixture).
        target: the target detector (its component's density is ``batch.log_p``), or None.
        start: the number of the batch's first rollout in the stage.
        features: the problem's state features (:attr:`pemviz.core.problems.Problem.features`): a sampler that reads
            them (:func:`pemviz.core.detectors.reads_state`) is asked about the rows with them
            (:func:`pemviz.core.features.with_state`, replayed).
    Returns:
        (log q float64 [n, T] in nats: ``batch.log_q`` for one sampler, else :func:`mixture_step_log_q` of every
        sampler's density of the logged actions, the measurement errors' included (:func:`errors_log_density`);
        component int64 [n]; over an ODD whose parameters a sampler drew from a proposal of its own, their term of
        each rollout's log q, float64 [n] (:attr:`~pemviz.core.rollouts.RolloutBatch.log_q_params`), else None)."""
    sizes = [k for k, _ in parts] or [batch.n]
    component = component_of(start, batch.n, sizes)
    if len(parts) <= 1:
        return np.asarray(batch.log_q, dtype=np.float64), component, batch.log_q_params
    state = None
    if features is not None and any(reads_state(d) for _, d in parts):
        replayed = features(batch, None)
        state = None if replayed is None else with_state(batch, replayed)

    def density(d: Detector) -> np.ndarray:
        b = state if state is not None and reads_state(d) else batch
        rows = b.object_rows.reshape(-1, b.object_rows.shape[-1])
        log_q = action_log_prob(d.detect_logit(rows).reshape(b.detected.shape), b.detected).sum(axis=2)
        return log_q + (0.0 if b.noise is None else errors_log_density(b, d, target))

    log_q = [batch.log_p if d is target else density(d) for _, d in parts]
    shares = np.asarray(sizes, dtype=np.float64) / sum(sizes)
    ratios = [None if d is target else parameter_log_ratio(d, batch) for _, d in parts]
    log_start = None  # over an ODD, each component's parameter term (0 for one drawing from the ODD itself)
    if any(r is not None for r in ratios):
        log_start = np.stack([np.zeros(batch.n) if r is None else r for r in ratios])
    step = mixture_step_log_q(np.stack(log_q), shares, densities=batch.noise is not None, log_start=log_start)
    return step, component, None if log_start is None else stage_log_q_params(log_start, shares)


@dataclass(frozen=True)
class MeanWeight:
    """The mean importance weight of N rollouts, a check of the density that drew them (expectation 1).

    Attributes:
        log_mean: log of the mean weight (nats).
        se: its standard error, sd(w) / sqrt(N) (inf when the weights overflow float64).
        n: N.
        bound_se: the largest standard error of the mean a correct density allows, sqrt(sum_i (B_i - 1)) / N, when
            every weight is bounded by a known B_i (a share of the stage drawn from the target itself); else None.
        over_bound: rollouts whose weight exceeds its bound B_i (impossible under the declared density)."""

    log_mean: float
    se: float
    n: int
    bound_se: float | None = None
    over_bound: int = 0

    @property
    def mean(self) -> float:
        return math.exp(self.log_mean) if self.log_mean < 709.0 else math.inf

    @property
    def z(self) -> float:
        """(mean - 1) in standard errors: of the bound when known, else of the sample (checked above 1 only)."""
        scale = self.bound_se if self.bound_se is not None else self.se
        if not scale > 0.0:
            return 0.0 if self.mean == 1.0 else math.copysign(math.inf, self.mean - 1.0)
        return (self.mean - 1.0) / scale

    @property
    def far(self) -> bool:
        """Whether log q is not the density that drew the rollouts: the mean is more than :data:`CHECK_Z` standard
        errors from 1 (below 1 only when the weights are bounded: unbounded weights of a proposal aimed at the
        failures average far below 1 as a rule, their mass lying in rollouts it rarely draws), or a weight exceeds
        its bound."""
        if self.over_bound:
            return True
        return abs(self.z) > CHECK_Z if self.bound_se is not None else self.z > CHECK_Z

    def line(self) -> str:
        """``logged-density check: mean importance weight 0.998 (SE 0.031) over 1800 rollouts; ...``."""
        head = (
            f"logged-density check: mean importance weight {_number(self.mean)} (SE {_number(self.se)}) over "
            f"{self.n} rollouts, expected 1"
        )
        if self.bound_se is not None:
            return f"{head} +- {_number(CHECK_Z * self.bound_se)} here (every weight bounded by the target's share)"
        return f"{head}; checked above 1 only (unbounded weights: a mean below 1 is usual)"

    def warning(self) -> str | None:
        """One line when :attr:`far`, else None."""
        if not self.far:
            return None
        why = (
            f"{self.over_bound} weight(s) above the bound the sidecar's mixture allows"
            if self.over_bound
            else f"{abs(self.z):.1f} standard errors from 1"
        )
        return (
            f"warning: mean importance weight {_number(self.mean)} is {why}: log_q is not the density that drew "
            "these rollouts (e.g. one mixture component's instead of the mixture's): do not trust the estimate "
            "below"
        )


def _number(x: float) -> str:
    return f"{x:.3g}" if math.isfinite(x) else "inf"


def mean_weight(log_w: np.ndarray, bound: np.ndarray | None = None) -> MeanWeight:
    """:class:`MeanWeight` of importance log-weights [N] (nats), ``bound``: B_i >= 1 per rollout [N] (nan: unknown),
    or None. E_q[w] = 1 when q drew the rollouts (Owen 2013, sec. 9.1); with a defensive share c of the target in
    the mixture every w <= 1 / c (Hesterberg 1995; Owen & Zhou 2000), so Var(w) <= E[w^2] - 1 <= B - 1."""
    log_w = np.asarray(log_w, dtype=np.float64)
    n = log_w.size
    top = float(np.max(log_w))
    scaled = libm.exp(log_w - top)
    log_mean = top + math.log(float(scaled.mean()))
    sd = float(scaled.std(ddof=1)) if n > 1 else 0.0
    se = sd / math.sqrt(n) * math.exp(top) if top < 709.0 else math.inf
    bound_se, over = None, 0
    if bound is not None and np.isfinite(bound).all():
        b = np.asarray(bound, dtype=np.float64)
        bound_se = math.sqrt(float(np.sum(b - 1.0))) / n
        over = int(np.count_nonzero(log_w > libm.log(b) + 1e-9))
    return MeanWeight(log_mean, se, n, bound_se, over)
