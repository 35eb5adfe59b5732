"""Detectors: what the scenario asks each step about each object: ``logit p(detect)`` float64 [R] of object rows
float64 [R, G] (the window's column first), so every log-probability is exact (``log_expit(+-logit)``). A
:class:`NoisyDetector` also gives the density of a detected object's measurement error; :func:`draw_step` draws one
step's events and their log-probabilities for every simulator."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol, cast, runtime_checkable

import numpy as np
from scipy.special import expit, log_expit

from pemviz.core import libm
from pemviz.core.detector_noise import (
    ErrorModelOf,
    draw_noise,
    error_model_of,
    noise_log_density,
    noise_names_of,
    noise_quantile,
)
from pemviz.core.rng import RQMC_BLOCK, array_rqmc_uniforms, block_bounds, by_blocks, ranking_key

GAP_COLUMN = 0
"""Index of the window's column (the proposal's input, e.g. a distance in metres) in every observation vector."""


@runtime_checkable
class Detector(Protocol):
    """Anything that gives ``logit p(detect | obs)``, float64 [N], for observations [N, F]."""

    def detect_logit(self, obs: np.ndarray) -> np.ndarray: ...


@runtime_checkable
class NoisyDetector(Detector, Protocol):
    """A detector that also mislocates what it detects: a detected object's error (float64 [D] per row,
    ``noise_names``, e.g. metres) has a location-scale density given the row: ``noise_params(rows) -> (loc [R, D],
    log_scale [R, D])`` of the family ``noise_family`` (:data:`NOISE_FAMILIES`, ``noise_df`` for Student-t),
    independent components; ``noise_from_uniforms(rows, u [R, D])`` draws by inverse CDF and ``noise_log_prob(rows,
    noise) -> [R]`` is the log density (nats)."""

    noise_names: tuple[str, ...]
    noise_family: str
    noise_df: np.ndarray | None

    def noise_params(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def noise_from_uniforms(self, rows: np.ndarray, u: np.ndarray) -> np.ndarray: ...

    def noise_log_prob(self, rows: np.ndarray, noise: np.ndarray) -> np.ndarray: ...


class GapModel(Protocol):
    """A model of ``logit p(detect)`` by the window's gap alone, metres (e.g. :class:`pemviz.pem.PEM`)."""

    def logit_at_gap(self, distance: np.ndarray) -> np.ndarray: ...


class NoiseShifting(Protocol):
    """A proposal with a measurement-error head of its own (:meth:`pemviz.core.sampling.Proposal.noise_shift_of`)."""

    def noise_shift_of(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...


def reads_state(detector: object) -> bool:
    """Whether ``detector`` asks for the step's state features after each object row (``reads_state = True``:
    :func:`draw_step`'s ``state``, :mod:`pemviz.core.features`)."""
    return bool(getattr(detector, "reads_state", False))


def action_log_prob(logit: np.ndarray, detected: np.ndarray) -> np.ndarray:
    """``log p(a | s)`` of the taken actions: log_expit(+logit) if detected else log_expit(-logit).

    Args:
        logit: float64 [...], logit of p(detect).
        detected: bool [...], the taken actions (same shape).
    Returns:
        float64 [...] log-probabilities in nats."""
    sign = np.where(np.asarray(detected, dtype=bool), 1.0, -1.0)
    return log_expit(sign * np.asarray(logit, dtype=np.float64))


def action_log_prob_into(
    logit: np.ndarray, detected: np.ndarray, log_p_detect: np.ndarray | None, out: np.ndarray
) -> np.ndarray:
    """:func:`action_log_prob` into ``out``, bit for bit, reusing ``log_expit(logit)`` when given (``log_p_detect``).

    ``log_expit(+logit)`` where detected, ``log_expit(-logit) = -logaddexp(0, logit)`` elsewhere, evaluated only where
    missed. A hot path, so written out (numpy's ``logaddexp(..., where=missed)``, faster than ``log_expit`` on every
    entry); ``scipy.special.log_expit(..., where=...)`` corrupted the heap (scipy 1.17.1: a segfault a few calls
    later)."""
    if log_p_detect is None:
        log_p_detect = log_expit(logit)
    missed = ~detected
    np.copyto(out, log_p_detect)
    np.logaddexp(0.0, logit, out=out, where=missed)
    np.negative(out, out=out, where=missed)
    return out


def logit(p: float) -> float:
    """``log(p / (1 - p))``; raises ValueError unless 0 < p < 1."""
    if not 0.0 < p < 1.0:
        raise ValueError(f"detection probability must be in (0, 1), got {p}")
    return math.log(p) - math.log1p(-p)


@dataclass(frozen=True)
class ConstantDetector:
    """Detects with the same probability at every step (the naive-50 detector when p = 0.5)."""

    p_detect: float = 0.5

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        return np.full(np.shape(obs)[0], logit(self.p_detect))


@dataclass(frozen=True)
class PEMDetector:
    """The perception error model as a detector: ``logit p_PEM(detect | salient variables(gap))``."""

    pem: GapModel  # pemviz.pem.PEM (a protocol: no torch model imported at import time)

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        return np.asarray(self.pem.logit_at_gap(np.asarray(obs)[:, GAP_COLUMN]), dtype=np.float64)


@dataclass(frozen=True)
class WindowDetector:
    """``inside`` when the gap is below ``radius_m`` (and at least ``floor_m``), ``outside`` otherwise (mixed-50:
    50 % inside 10 m)."""

    inside: Detector
    outside: Detector
    radius_m: float = 10.0
    floor_m: float = -math.inf

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """Each detector is asked only about its own rows (a proposal network costs per row)."""
        obs = np.asarray(obs)
        near = window_mask(obs, self.radius_m, self.floor_m)
        out = np.empty(obs.shape[0])
        for rows, detector in ((near, self.inside), (~near, self.outside)):
            if rows.any():
                out[rows] = detector.detect_logit(obs[rows])
        return out


def window_mask(obs: np.ndarray, radius_m: float, floor_m: float = -math.inf) -> np.ndarray:
    """bool [N]: the observations [N, F] whose gap (first column, metres) lies in ``[floor_m, radius_m)``."""
    gap = np.asarray(obs)[:, GAP_COLUMN]
    near = gap < radius_m
    if floor_m > -math.inf:
        near &= gap >= floor_m
    return near


def defensive_logit(q_logit: np.ndarray, eps: float) -> np.ndarray:
    """logit of the defensive mixture (1 - eps) q + eps * 50 % (Hesterberg, "Weighted average importance sampling and
    defensive mixture distributions", Technometrics 1995): log p_mix(detect) - log p_mix(miss), float64 [N] (nats), from
    logit q(detect) [N]; both outcomes keep probability >= eps / 2, so neither logarithm underflows. ``eps`` in
    (0, 1)."""
    q_logit = np.asarray(q_logit, dtype=np.float64)
    # log((1 - eps) q + eps / 2) - log((1 - eps) (1 - q) + eps / 2): each a sum of two positive terms, both >= eps / 2,
    # so to ~1e-16 relative from expit(+-logit) alone (2.7 times as fast as two logaddexp of two log_expit)
    detect, miss = expit(q_logit), expit(-q_logit)
    for a in (detect, miss):
        np.multiply(a, 1.0 - eps, out=a)
        np.add(a, eps / 2.0, out=a)
        libm.log(a, out=a)
    return np.subtract(detect, miss, out=detect)


class StageSamplers:
    """The detectors one proposal gives a cross-entropy stage, evaluated together, once per step.

    The proposal draws only inside the window ``floor_m <= gap < radius_m``, the target elsewhere: :attr:`plain`;
    :attr:`defensive` adds the per-step defensive mixture (:func:`defensive_logit`, ``eps`` > 0). All share one
    evaluation of the target and of the proposal per step, cached for the last observations asked about; call
    :meth:`forget` after a fit. Returned logits are read-only.

    Args:
        proposal: q, asked only about the window's rows.
        target: the target detector p (the PEM), asked about every row.
        radius_m, floor_m: the window on the gap (metres); the defaults, infinite, make it everywhere.
        eps: the defensive share (0: none)."""

    def __init__(
        self,
        proposal: Detector,
        target: Detector,
        radius_m: float = math.inf,
        floor_m: float = -math.inf,
        eps: float = 0.0,
    ) -> None:
        self.proposal, self.target_detector = proposal, target
        self.radius_m, self.floor_m, self.eps = float(radius_m), float(floor_m), float(eps)
        self._obs: np.ndarray | None = None
        self._asked: np.ndarray | None = None
        """The array last asked about itself: a read-only one (:func:`draw_step` hands each step's rows to every
        detector as a new read-only view) is the same rows when asked again, with no comparison."""
        self._window = np.zeros(0, bool)
        """:meth:`window_rows` of the array last asked about."""
        self._logits: tuple[np.ndarray, np.ndarray, np.ndarray] = ()  # type: ignore[assignment]
        self._by_row = bool(getattr(proposal, "logit_by_row", False))
        """Whether the proposal's logit of a row is a function of the row's bits alone (:attr:`_last` is kept)."""
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        """The rows last asked about: (their bits uint64 [N, F], their window mask [N], the plain and defensive
        logits [N]), for a proposal whose logits are row by row."""
        self._noise_obs: np.ndarray | None = None
        self._noise: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self.target, self.plain = SamplerView(self, 0), SamplerView(self, 1)
        self.defensive = SamplerView(self, 2) if self.eps > 0.0 else self.plain
        self.parameter_proposal: Any = None
        """Over an ODD: the proposal the samplers (not the target) draw a rollout's parameters from
        (:class:`pemviz.core.odd_proposal.ParameterProposal`), or None: the ODD itself."""

    def forget(self) -> None:
        """Drop the kept evaluations (the proposal changed)."""
        self._obs = self._noise_obs = self._asked = self._last = None

    @property
    def noisy_target(self) -> NoisyDetector:
        """The target as the :class:`NoisyDetector` it is where errors are drawn or weighed (only asked then)."""
        return cast(NoisyDetector, self.target_detector)

    def logits(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(target, plain, defensive) logit p(detect | obs), float64 [N] each, for observations [N, F]."""
        obs = np.asarray(obs, dtype=np.float64)
        if obs is self._asked and not obs.flags.writeable:  # a read-only array asked about again
            return self._logits
        last = self._obs
        if last is not None and last.shape == obs.shape and np.array_equal(last, obs):
            return self._logits
        p = np.asarray(self.target_detector.detect_logit(obs), dtype=np.float64)
        window = self.window_rows(obs)
        near = window & np.isfinite(p)  # where the target is certain (an unseen object) it decides
        plain = p.copy()
        defensive = plain
        bits = np.ascontiguousarray(obs).view(np.uint64) if self._by_row else None
        if near.any():  # the proposal's logit of each distinct row once, where it says which rows are one
            ask, kept = near, self._unchanged(bits, near)
            if kept is not None:  # rows as they were at the last step keep their logits (e.g. cars at rest)
                ask = near & ~kept
            rows = np.flatnonzero(ask)  # indices: faster than the mask, used three times
            distinct = getattr(self.proposal, "distinct_logit", None)
            z, inverse = distinct(obs[rows]) if distinct is not None else (self.proposal.detect_logit(obs[rows]), None)
            z = np.asarray(z, dtype=np.float64)
            plain[rows] = z if inverse is None else z[inverse]
            if self.eps > 0.0:
                defensive = p.copy()
                d = defensive_logit(z, self.eps)
                defensive[rows] = d if inverse is None else d[inverse]
            if kept is not None and self._last is not None:
                same = np.flatnonzero(kept)
                plain[same] = self._last[2][same]
                if self.eps > 0.0:
                    defensive[same] = self._last[3][same]
        for a in (p, plain, defensive):
            a.flags.writeable = False
        if bits is not None:
            self._last = (bits.copy(), near, plain, defensive)
        # a read-only array is kept itself (no copy: it is recognised by identity only, its base may change later)
        self._obs = obs.copy() if obs.flags.writeable else None
        self._asked, self._window, self._logits = obs, window, (p, plain, defensive)
        return self._logits

    def _unchanged(self, bits: np.ndarray | None, near: np.ndarray) -> np.ndarray | None:
        """bool [N]: the rows (``bits`` uint64 [N, F]) inside the window now and when last asked about, with the same
        bits as then; None where nothing is kept (a proposal whose logits are not row by row, a first ask or rows of
        another shape)."""
        last = self._last
        if bits is None or last is None or last[0].shape != bits.shape:
            return None
        kept = near & last[1]
        for j in range(bits.shape[1]):  # column by column: faster than a reduction along a short axis
            kept &= bits[:, j] == last[0][:, j]
        return kept

    def window_rows(self, obs: np.ndarray) -> np.ndarray:
        """bool [N]: the observations [N, F] inside the window, ``floor_m <= gap < radius_m``, where a detection can
        matter (the proposal draws there unless the target is certain)."""
        if obs is self._asked and not obs.flags.writeable:  # the rows just asked about
            return self._window
        return window_mask(obs, self.radius_m, self.floor_m)

    @property
    def has_noise(self) -> bool:
        """Whether the proposal draws the measurement errors from a model of its own (a noisy target and a proposal
        with an error head, :meth:`pemviz.core.sampling.Proposal.add_noise_head`)."""
        return bool(noise_names_of(self.target_detector)) and getattr(self.proposal, "noise_shift", None) is not None

    def noise_params(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(loc_p, log_scale_p, loc_q, log_scale_q), float64 [N, D] each, at object rows [N, F]: the target's error
        parameters and the proposal's, which shift them inside the window (:class:`pemviz.core.torch_fits.NoiseShift`);
        the last rows' are kept (a step draws the errors, then weighs them)."""
        obs = np.asarray(obs, dtype=np.float64)
        last, kept = self._noise_obs, self._noise
        if last is not None and kept is not None and last.shape == obs.shape and np.array_equal(last, obs):
            return kept
        loc_p, ls_p = (np.asarray(a, dtype=np.float64) for a in self.noisy_target.noise_params(obs))
        loc_q, ls_q = loc_p.copy(), ls_p.copy()
        near = self.window_rows(obs)
        if near.any():
            a, b = cast(NoiseShifting, self.proposal).noise_shift_of(obs[near])  # has_noise: it has an error head
            loc_q[near] += libm.exp(ls_p[near]) * a
            ls_q[near] += b
        self._noise_obs, self._noise = obs.copy(), (loc_p, ls_p, loc_q, ls_q)
        return self._noise

    def noise_from_uniforms(self, index: int, obs: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Errors [N, D] of detector ``index`` (1 plain: q's; 2 defensive: (1 - eps) q + eps p, the component chosen by
        the first uniform, which is then rescaled and reused) from uniforms [N, D]."""
        t = self.noisy_target
        loc_p, ls_p, loc_q, ls_q = self.noise_params(obs)
        u = np.asarray(u, dtype=np.float64)
        if index == 1 or self.eps <= 0.0:
            return noise_quantile(t.noise_family, t.noise_df, loc_q, ls_q, u)
        from_p = u[:, 0] < self.eps
        v = u.copy()
        v[:, 0] = np.where(from_p, u[:, 0] / self.eps, (u[:, 0] - self.eps) / (1.0 - self.eps))
        return np.where(
            from_p[:, None],
            noise_quantile(t.noise_family, t.noise_df, loc_p, ls_p, v),
            noise_quantile(t.noise_family, t.noise_df, loc_q, ls_q, v),
        )

    def noise_log_prob(self, index: int, obs: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """log density [N] (nats) of errors [N, D] under detector ``index`` (:meth:`noise_from_uniforms`)."""
        t = self.noisy_target
        loc_p, ls_p, loc_q, ls_q = self.noise_params(obs)
        lq = noise_log_density(t.noise_family, t.noise_df, loc_q, ls_q, noise)
        if index == 1 or self.eps <= 0.0:
            return lq
        lp = noise_log_density(t.noise_family, t.noise_df, loc_p, ls_p, noise)
        return np.logaddexp(math.log1p(-self.eps) + lq, math.log(self.eps) + lp)

    def describe(self, index: int, proposal: str = "proposal", target: str = "target") -> str:
        """A short name of one of the detectors (0 target, 1 plain, 2 defensive) for the rollout file's sidecar."""
        if index == 0:
            return target
        inside = proposal if index == 1 or self.eps <= 0.0 else f"(1 - {self.eps:g}) {proposal} + {self.eps:g} x 50 %"
        if self.radius_m == math.inf:
            return inside
        return f"{inside} within {self.radius_m:g} m, {target} beyond"


@dataclass(frozen=True, eq=False)
class SamplerView:
    """One of a :class:`StageSamplers`' detectors: 0 the target, 1 the plain sampler, 2 the defensive one."""

    samplers: StageSamplers
    index: int

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """logit p(detect | obs), float64 [N] (read-only), for observations [N, F]."""
        return self.samplers.logits(obs)[self.index]

    @property
    def reads_state(self) -> bool:
        """Whether the proposal reads the state features (:func:`reads_state`): then every view is asked about the
        rows with them (the target view's target reads its own columns)."""
        return reads_state(self.samplers.proposal)

    @property
    def parameter_proposal(self) -> Any:
        """The samplers' proposal over an ODD's parameters (:attr:`StageSamplers.parameter_proposal`); None for the
        target view, which draws them from the ODD."""
        return None if self.index == 0 else self.samplers.parameter_proposal

    def window_rows(self, obs: np.ndarray) -> np.ndarray | None:
        """bool [N]: where a sampler's proposal draws (:meth:`StageSamplers.window_rows`); None for the target view
        (every row is its own)."""
        return None if self.index == 0 else self.samplers.window_rows(obs)

    @property
    def noise_names(self) -> tuple[str, ...]:
        """The target's measurement errors for the target view, and for the samplers when the proposal has an error
        model of its own (:attr:`StageSamplers.has_noise`; else they draw the errors from the target's model)."""
        s = self.samplers
        return noise_names_of(s.target_detector) if self.index == 0 or s.has_noise else ()

    @property
    def noise_family(self) -> str:
        return self.samplers.noisy_target.noise_family

    @property
    def noise_df(self) -> np.ndarray | None:
        return self.samplers.noisy_target.noise_df

    def noise_from_uniforms(self, rows: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Errors [R, D] from uniforms (:class:`NoisyDetector`): the target's, or the proposal's samplers'."""
        if self.index == 0:
            return self.samplers.noisy_target.noise_from_uniforms(rows, u)
        return self.samplers.noise_from_uniforms(self.index, rows, u)

    def noise_log_prob(self, rows: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """Log density [R] (nats) of errors [R, D] (:class:`NoisyDetector`)."""
        if self.index == 0:
            return self.samplers.noisy_target.noise_log_prob(rows, noise)
        return self.samplers.noise_log_prob(self.index, rows, noise)

    def noise_draw(self, rows: np.ndarray, u: np.ndarray, hit: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Errors [H, D] of the rows ``hit`` and their log density [H] (nats) (:func:`draw_noise`)."""
        if self.index == 0:
            return draw_noise(self.samplers.target_detector, rows, u, hit)
        picked = rows[hit]
        errors = np.asarray(self.noise_from_uniforms(picked, u), dtype=np.float64)
        return errors, np.asarray(self.noise_log_prob(picked, errors), dtype=np.float64)


@dataclass(frozen=True)
class ArrayRQMC(ErrorModelOf):
    """``detector``, drawn by Array-RQMC: a simulator stepping rollouts together ranks them by this detector's logit
    at each step and takes their uniforms from :func:`pemviz.core.rng.array_rqmc_uniforms` (:func:`step_uniforms`).
    Every rollout still follows ``detector`` exactly; a simulator that does not look at ``array_rqmc`` draws i.i.d.
    uniforms, with the same expectations."""

    detector: Detector
    array_rqmc: bool = True

    _error_model_of = "detector"

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """``detector``'s logit p(detect | obs), float64 [N], for observations [N, F]."""
        return self.detector.detect_logit(obs)

    @property
    def reads_state(self) -> bool:
        return reads_state(self.detector)


def step_uniforms(
    u: np.ndarray, sampler: Detector, q_logit: np.ndarray, obs: np.ndarray, block: int = RQMC_BLOCK
) -> np.ndarray:
    """The uniforms a simulator compares with ``sampler``'s detection probabilities at one step: ``u`` (float64 [n],
    i.i.d. U(0, 1)) as drawn, or for an :class:`ArrayRQMC` sampler the Array-RQMC uniforms of the chains ranked by
    ``q_logit`` (to float32), then the first column of ``obs`` [n, G], then the rows
    (:func:`pemviz.core.rng.ranking_key`, :func:`pemviz.core.rng.array_rqmc_uniforms`), within each block of
    ``block`` rows. Only the chains inside the sampler's window (``window_rows(obs)``) are coupled; the others keep
    their i.i.d. uniforms. Each chain's uniform stays U(0, 1) given the past."""
    if not getattr(sampler, "array_rqmc", False) or u.size <= 1:
        return u
    window_rows = getattr(getattr(sampler, "detector", None), "window_rows", None)
    coupled = None if window_rows is None else window_rows(obs)
    if coupled is None:
        coupled = np.ones(u.size, bool)
    out = u.copy()
    for a, b in block_bounds(u.size, block):
        idx = np.flatnonzero(coupled[a:b]) + a
        if idx.size > 1:
            rows = obs[idx]
            out[idx] = array_rqmc_uniforms(u[idx], ranking_key(q_logit[idx], rows[:, GAP_COLUMN]), rows)
    return out


@dataclass(frozen=True)
class StepDraw:
    """One step's perception events of R object rows and their log-probabilities (nats).

    Attributes:
        detected: bool [R].
        noise: float64 [R, D] measurement errors (0 where missed), or None (the detectors only detect).
        log_q: float64 [R] log q(event | row) under the sampler.
        log_p: float64 [R] log p(event | row) under the target."""

    detected: np.ndarray
    noise: np.ndarray | None
    log_q: np.ndarray
    log_p: np.ndarray


def draw_step(
    sampler: Detector,
    target: Detector,
    rows: np.ndarray,
    u: np.ndarray,
    block: int = RQMC_BLOCK,
    forced: tuple[np.ndarray, np.ndarray | None, np.ndarray] | None = None,
    n_objects: int = 1,
    state: np.ndarray | None = None,
) -> StepDraw:
    """Draw one step's perception events for R object rows from ``sampler``, scored under ``target`` (Innes &
    Ramamoorthy 2022, Algorithm 1: detect iff u <= q(detect | s)).

    A row is detected iff ``log u <= log_expit(logit q)``. With errors (a :class:`NoisyDetector` target), a detected
    row's error is drawn by inverse CDF from its other uniforms under the sampler's error model (else the target's)
    and both densities add its log density (:func:`draw_noise`, :func:`error_model_of`); a missed row's error is 0.

    Args:
        sampler: the detector the events are drawn from (q).
        target: the detector they are scored under (p, the PEM).
        rows: float64 [R, G] object rows (each rollout's objects together).
        u: float64 [R, 1 + D] uniforms in [0, 1): column 0 the detection (re-ranked for an :class:`ArrayRQMC`
            sampler, :func:`step_uniforms`), columns 1..D the errors.
        block: rows coupled by Array-RQMC together (one :data:`pemviz.core.rng.RQMC_BLOCK` of rollouts).
        n_objects: M, the rows of one rollout; rollouts of M > 1 objects draw i.i.d. (Array-RQMC couples
            single-object rollouts only).
        forced: optional (detected bool [R], noise [R, D] or None, given bool [R]): events taken where ``given`` (a
            replayed prefix).
        state: optional float64 [R, H] state features (:mod:`pemviz.core.features`), appended for a detector that
            reads them (:func:`reads_state`).
    Returns:
        :class:`StepDraw`.
    Raises:
        ValueError: ``u`` without 1 + D columns for the target's D error components."""
    rows, u = np.asarray(rows, dtype=np.float64).view(), np.asarray(u, dtype=np.float64)
    rows.flags.writeable = False  # a new read-only view: the detectors asked about it in turn may keep their answers
    rows_p = rows  # the target's rows, and the sampler's (with the state features where it reads them)
    if state is not None and (reads_state(sampler) or reads_state(target)):
        with_state = np.concatenate([rows, np.asarray(state, dtype=np.float64)], axis=1)
        with_state.flags.writeable = False
        rows_p = with_state if reads_state(target) else rows
        rows = with_state if reads_state(sampler) else rows
    names = noise_names_of(target)
    if u.ndim != 2 or u.shape != (rows.shape[0], 1 + len(names)):
        raise ValueError(
            f"draw_step: u must be float64 [R, 1 + D] = [{rows.shape[0]}, {1 + len(names)}] for the "
            f"target's errors {names}, got shape {u.shape}"
        )
    q_logit = by_blocks(sampler.detect_logit, rows, block)
    p_logit = q_logit if target is sampler else by_blocks(target.detect_logit, rows_p, block)
    u_detect = np.ascontiguousarray(u[:, 0])
    if n_objects == 1:
        u_detect = step_uniforms(u_detect, sampler, q_logit, rows, block)
    ls_q = log_expit(q_logit)
    # u <= sigmoid(logit) <=> log u <= log_expit(logit); libm's log: the same draw on every CPU
    detected = np.less_equal(libm.log(u_detect, out=u_detect), ls_q)
    if forced is not None:
        np.copyto(detected, forced[0], where=forced[2])
    log_q = action_log_prob_into(q_logit, detected, ls_q, np.empty(rows.shape[0]))
    log_p = log_q.copy()
    if p_logit is not q_logit:  # the target's density where it is not the sampler's (e.g. inside a proposal's window)
        differ = np.flatnonzero(p_logit != q_logit)
        if differ.size:
            log_p[differ] = action_log_prob_into(p_logit[differ], detected[differ], None, np.empty(differ.size))
    if not names:
        return StepDraw(detected, None, log_q, log_p)
    # a sampler without an error model draws p's; both have one where they name errors (``names``, not empty)
    own = noise_names_of(sampler) == names
    source, rows_s = cast(NoisyDetector, sampler if own else target), rows if own else rows_p
    noise = np.zeros((rows.shape[0], len(names)))
    if detected.any():  # only a detected object is measured: its error, drawn (or replayed), and its densities
        hit = detected
        if forced is not None and forced[1] is not None:  # a replayed error's density is at the replayed error
            e = np.asarray(source.noise_from_uniforms(rows_s[hit], u[hit, 1:]), dtype=np.float64)
            e = np.where(forced[2][hit][:, None], forced[1][hit], e)
            lq_noise = np.asarray(source.noise_log_prob(rows_s[hit], e), dtype=np.float64)
        else:  # the error model evaluated once for the draw and its density
            e, lq_noise = draw_noise(source, rows_s, u[hit, 1:], hit)
        noise[hit] = e
        log_q[hit] += lq_noise
        if source is target or error_model_of(source) is error_model_of(target):  # one error model: one density
            log_p[hit] += lq_noise
        else:
            log_p[hit] += np.asarray(cast(NoisyDetector, target).noise_log_prob(rows_p[hit], e), dtype=np.float64)
    return StepDraw(detected, noise, log_q, log_p)


def errors_log_density(batch: Any, detector: Detector, target: Detector | None) -> np.ndarray:
    """Per step, the log density of the detected objects' measurement errors under the sampler ``detector`` (under
    ``target`` when ``detector`` has no error model of its own: its errors were drawn from the target's, as
    :func:`pemviz.core.detectors.draw_step` draws them), float64 [N, T] (nats) for a batch with ``noise``.

    Raises:
        ValueError: ``detector`` without an error model and no ``target``."""
    source = detector if noise_names_of(detector) else target
    if source is None:
        raise ValueError("errors_log_density: a detector without an error model of its own needs the target's")
    rows = batch.object_rows.reshape(-1, batch.object_rows.shape[-1])
    noise = batch.noise.reshape(rows.shape[0], -1)
    log_density = np.asarray(cast(NoisyDetector, source).noise_log_prob(rows, noise), dtype=np.float64)
    return np.where(batch.detected.reshape(-1), log_density, 0.0).reshape(batch.detected.shape).sum(axis=2)
