"""The braking scenario's tilted proposal (``method = "tilt"`` on a problem from :func:`tilted_problem`): each
detection of the lead drawn in proportion to its probability under the PEM times an approximate committor V (the
probability of a crash after it), mixed defensively with the PEM, every weight p / q exact. Research that pemviz does
not ship (its braking default is the cross-entropy sampler): a comparator of docs/validation.md ("How far from the
limit", the estimators' matrix), used by ``benchmarks/braking_committor.py`` and ``benchmarks/honest_numbers.py``,
tested by ``research/tests/test_braking_tilt.py``.

V solves the backward equation V_t(s) = sum_a p(a | s) V_{t+1}(s'_a), V = 1 below the crash gap, V_T = 0 (Kollman,
Baggerly, Cox & Picard 1999, Ann. Appl. Probab. 9(2)); :func:`solve_committor` solves it on a (gap, speed) grid per
step and pending flag, log V interpolated bilinearly, the PID integral at its steady value
(:func:`steady_integral`), so V is approximate (``benchmarks/braking_committor.py``). A detection is drawn with
probability p V(s'_detect) / (p V(s'_detect) + (1 - p) V(s'_miss)) (L'Ecuyer & Tuffin 2008, "Approximate
zero-variance simulation", WSC), mixed with a share :data:`TILT_EPS` of the PEM (Hesterberg 1995, Technometrics
37(2)), so each step's weight is at most 1 / :data:`TILT_EPS` and the estimate stays unbiased whatever V's errors.
The solve is reused within a process (:func:`solved_committor`); each rollout adds one look-ahead step per step
inside the braking distance.

Units: metres, m/s, seconds; log-probabilities in nats."""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from pemviz.core.detectors import Detector, PEMDetector
from pemviz.core.lockstep import DEFAULT_CHUNK_SIZE, simulate_rollouts
from pemviz.core.problems import Problem, StateScore
from pemviz.core.rollouts import RolloutBatch
from pemviz.scenarios.braking.batched import BatchedBraking
from pemviz.scenarios.braking.simulator import BrakingParams, braking_step, lead_speeds
from pemviz.scenarios.braking.truth import branching_start
from pemviz.scenarios.braking.truth_known import pem_fingerprint
from scipy.special import log_expit

LogitFn = Callable[[np.ndarray], np.ndarray]

TILT_GAPS = 200
"""Gap nodes of the committor's grid, from the crash gap to 1 m past the braking distance."""
TILT_SPEEDS = 40
"""Speed nodes of the committor's grid, from 0 to 1 m/s above the faster of the ego's start and target speeds."""
TILT_EPS = 0.05
"""The PEM's share of each step's proposal (each step's importance weight is at most 1 / eps)."""

LOG_V_FLOOR = -700.0
"""log V where no crash can follow (nats): finite, so that log V interpolates; read as V = 0."""
SOLVED_KEPT = 4
"""How many solved committors a process keeps (each 10 MB with the default grid)."""

_SOLVED: dict[tuple, GridCommittor] = {}


def steady_integral(params: BrakingParams, speed_mps: np.ndarray) -> np.ndarray:
    """The PID integral (km/h s) a constant speed leaves: (target - 3.6 v) dt / (1 - leak), float64 like
    ``speed_mps`` (m/s)."""
    p = params
    return (p.target_speed_kmh - 3.6 * np.asarray(speed_mps, dtype=np.float64)) * p.dt_s / (1.0 - p.integral_leak)


def _cell(axis: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the node below each x [N] on an increasing ``axis`` [K], int [N], and x's fraction of the way to the next
    node, float64 [N]), x clamped to the axis."""
    x = np.clip(x, axis[0], axis[-1])
    i = np.clip(np.searchsorted(axis, x, side="right") - 1, 0, axis.size - 2)
    return i, (x - axis[i]) / (axis[i + 1] - axis[i])


@dataclass(frozen=True)
class GridCommittor:
    """An approximate committor of the braking scene: log V on a (gap, speed) grid per step and pending flag.

    Attributes:
        params: the scene.
        gap_axis: float64 [G] (metres), uniform, from the crash gap up.
        speed_axis: float64 [S] (m/s), uniform, from 0 up.
        log_v: float64 [T + 1, 2, G, S] log V (nats) at the nodes, per step 0..T and pending flag (0, 1);
            :data:`LOG_V_FLOOR` before the first step solved, at step T and where no crash can follow.
        first_step: the first step solved (the branching start: the gap first below the braking distance).
        steps: the steps of the scene's dynamics the solve evaluated."""

    params: BrakingParams
    gap_axis: np.ndarray = field(repr=False)
    speed_axis: np.ndarray = field(repr=False)
    log_v: np.ndarray = field(repr=False)
    first_step: int
    steps: int
    lead_speeds_mps: np.ndarray = field(init=False, repr=False)
    """The lead's speed at steps 0..T (m/s; :func:`~pemviz.scenarios.braking.simulator.lead_speeds`), once a
    committor."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "lead_speeds_mps", lead_speeds(self.params))

    def log_value(self, step: int, gap_m: np.ndarray, speed_mps: np.ndarray, pending: np.ndarray) -> np.ndarray:
        """log V (nats) of states at ``step``, float64 [N]: 0 where the gap [N] (metres) is below the crash gap (the
        failure is seen at that step), else log V interpolated bilinearly between the grid's nodes (clamped at its
        edges); :data:`LOG_V_FLOOR` at step T (nothing is seen after the last step)."""
        g = np.asarray(gap_m, dtype=np.float64)
        if step >= self.params.n_steps:
            return np.full(g.shape, LOG_V_FLOOR)
        i, dx = _cell(self.gap_axis, g)
        j, dy = _cell(self.speed_axis, np.asarray(speed_mps, dtype=np.float64))
        table, b = self.log_v[step], np.asarray(pending, dtype=bool).astype(np.int64)
        value = (
            (1 - dx) * (1 - dy) * table[b, i, j]
            + dx * (1 - dy) * table[b, i + 1, j]
            + (1 - dx) * dy * table[b, i, j + 1]
            + dx * dy * table[b, i + 1, j + 1]
        )
        return np.where(g < self.params.crash_gap_m, 0.0, value)

    def next_log_values(
        self, step: int, gap_m: np.ndarray, speed_mps: np.ndarray, integral: np.ndarray, pending: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """(log V after a detection [N], log V after a miss [N], the look-ahead steps evaluated) of states [N] at
        ``step`` (gap m, speed m/s, PID integral km/h s, pending brake): each outcome's next state by
        :func:`~pemviz.scenarios.braking.simulator.braking_step`, once when the actuation lag makes both share it."""
        p = self.params
        vl = float(self.lead_speeds_mps[step])
        n = np.size(gap_m)
        miss = np.zeros(n, dtype=bool)
        g2, v2, _, b_miss = braking_step(p, vl, gap_m, speed_mps, integral, pending, miss)
        if p.actuation_lag_steps == 1:  # the brake acts a step later: a detection changes the pending flag only
            b_det = b_miss | (np.asarray(gap_m) < p.braking_distance_m)
            g2d, v2d, steps = g2, v2, n
        else:
            g2d, v2d, _, b_det = braking_step(p, vl, gap_m, speed_mps, integral, pending, ~miss)
            steps = 2 * n
        return (self.log_value(step + 1, g2d, v2d, b_det), self.log_value(step + 1, g2, v2, b_miss), steps)


def grid_axes(params: BrakingParams, n_gap: int, n_speed: int) -> tuple[np.ndarray, np.ndarray]:
    """The committor's default grid: ``n_gap`` gaps evenly from the crash gap to 1 m past the braking distance and
    ``n_speed`` speeds evenly from 0 to 1 m/s above the faster of the ego's start and target speeds (float64, metres
    and m/s)."""
    p = params
    return (
        np.linspace(p.crash_gap_m, p.braking_distance_m + 1.0, n_gap),
        np.linspace(0.0, max(p.ego_speed0_mps, p.target_speed_kmh / 3.6) + 1.0, n_speed),
    )


def solve_committor(
    params: BrakingParams, logit_at_gap: LogitFn, n_gap: int = TILT_GAPS, n_speed: int = TILT_SPEEDS
) -> GridCommittor:
    """The braking scene's approximate committor by backward dynamic programming on a grid (module docstring).

    Args:
        params: the scene.
        logit_at_gap: logit p_PEM(detect | gap), float64 [K] for gaps [K] (metres), e.g. ``pem.logit_at_gap``.
        n_gap: the grid's nodes along the gap (>= 2).
        n_speed: the grid's nodes along the ego's speed (>= 2).
    Raises:
        ValueError: fewer than 2 nodes on an axis; a scene whose gap never drops below the braking distance
            (:func:`~pemviz.scenarios.braking.truth.branching_start`: nothing is random)."""
    if not (isinstance(n_gap, int) and isinstance(n_speed, int) and n_gap >= 2 and n_speed >= 2):
        raise ValueError(
            f"the braking committor's grid needs at least 2 gap and 2 speed nodes, got {n_gap!r} x " f"{n_speed!r}"
        )
    p = params
    first = branching_start(p).step
    gaps, speeds = grid_axes(p, n_gap, n_speed)
    log_v = np.full((p.n_steps + 1, 2, n_gap, n_speed), LOG_V_FLOOR)
    committor = GridCommittor(p, gaps, speeds, log_v, first, 0)
    g, v = (x.ravel() for x in np.meshgrid(gaps, speeds, indexing="ij"))
    integral = steady_integral(p, v)
    logit = np.asarray(logit_at_gap(g), dtype=np.float64)
    inside = g < p.braking_distance_m
    log_miss = np.where(inside, log_expit(-logit), 0.0)
    log_detect = np.where(inside, log_expit(logit), -np.inf)
    steps = 0
    for t in range(p.n_steps - 1, first - 1, -1):
        for b in (0, 1):
            after_detect, after_miss, k = committor.next_log_values(t, g, v, integral, np.full(g.size, bool(b)))
            steps += k
            log_v[t, b] = np.logaddexp(log_miss + after_miss, log_detect + after_detect).reshape(n_gap, n_speed)
    np.maximum(log_v, LOG_V_FLOOR, out=log_v)
    return GridCommittor(p, gaps, speeds, log_v, first, steps)


def solved_committor(
    params: BrakingParams, logit_at_gap: LogitFn, n_gap: int = TILT_GAPS, n_speed: int = TILT_SPEEDS
) -> tuple[GridCommittor, bool]:
    """(:func:`solve_committor`'s committor, whether it was reused): the one this process solved before for the same
    scene, PEM (:func:`~pemviz.scenarios.braking.truth_known.pem_fingerprint`: its detection curve) and grid, else a
    new one, kept for the next run (the last :data:`SOLVED_KEPT`)."""
    key = (params, pem_fingerprint(logit_at_gap), n_gap, n_speed)
    found = _SOLVED.get(key)
    if found is not None:
        return found, True
    committor = solve_committor(params, logit_at_gap, n_gap, n_speed)
    while len(_SOLVED) >= SOLVED_KEPT:
        _SOLVED.pop(next(iter(_SOLVED)))
    _SOLVED[key] = committor
    return committor, False


@dataclass
class BrakingTiltDetector:
    """q(detect | state) of the braking tilt (module docstring): inside the braking distance, q = (1 - eps) q* + eps
    p with q* the detection's share of p V(s'_detect) + (1 - p) V(s'_miss); elsewhere p. The step and PID integral
    are read off the simulator that asked (:attr:`sim`)."""

    committor: GridCommittor
    logit_at_gap: LogitFn
    eps: float = TILT_EPS
    sim: BatchedBraking | None = None
    steps: int = 0
    """Look-ahead steps evaluated so far."""

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        """logit q(detect | obs), float64 [N] for observations [N, 4] (gap m, ego speed m/s, lead speed m/s,
        pending brake)."""
        obs = np.asarray(obs, dtype=np.float64)
        logit = np.asarray(self.logit_at_gap(obs[:, 0]), dtype=np.float64)
        sim, c, p = self.sim, self.committor, self.committor.params
        if sim is None or sim.t < c.first_step:
            return logit
        inside = np.flatnonzero(obs[:, 0] < p.braking_distance_m)
        if inside.size == 0:
            return logit
        ctrl = sim.controller
        after_detect, after_miss, k = c.next_log_values(
            sim.t, obs[inside, 0], obs[inside, 1], ctrl.integral_kmh_s[inside], ctrl.pending_brake[inside]
        )
        self.steps += k
        lp_det, lp_miss = log_expit(logit[inside]), log_expit(-logit[inside])
        a_det, a_miss = lp_det + after_detect, lp_miss + after_miss
        total = np.logaddexp(a_det, a_miss)
        doomed = np.maximum(after_detect, after_miss) <= LOG_V_FLOOR  # no crash can follow: q* = p
        star_det = np.where(doomed, lp_det, a_det - total)
        star_miss = np.where(doomed, lp_miss, a_miss - total)
        keep, mix = np.log1p(-self.eps) if self.eps < 1.0 else -np.inf, np.log(self.eps)
        q_det = np.logaddexp(keep + star_det, mix + lp_det)
        q_miss = np.logaddexp(keep + star_miss, mix + lp_miss)
        out = logit.copy()
        out[inside] = q_det - q_miss
        return out


class _Watched(BatchedBraking):
    """The batched twin that tells its detector which simulator asks (for the step and the controller's memory)."""

    def __init__(self, params: BrakingParams, n: int, detector: BrakingTiltDetector) -> None:
        self.detector = detector
        super().__init__(params, n)

    def observation(self, out: np.ndarray | None = None) -> np.ndarray:
        self.detector.sim = self
        return super().observation(out)


def draw_tilted(
    detector: BrakingTiltDetector,
    target: Detector,
    n: int,
    rng: np.random.Generator,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> RolloutBatch:
    """``n`` rollouts of the batched twin with detections drawn from ``detector`` and scored under ``target`` (the
    PEM), the stream of :func:`pemviz.scenarios.braking.batched.simulate_batched`: the same rollouts for any
    ``chunk_size``."""
    p = detector.committor.params
    return simulate_rollouts(
        lambda m: _Watched(p, m, detector), n, p.n_steps, detector, target, rng, chunk_size=chunk_size
    )


class BrakingTilt:
    """The braking scene's :class:`pemviz.core.problems.TiltSampler` (module docstring).

    Args:
        params: the scene.
        logit_at_gap: the PEM's detection logit at a gap (``pem.logit_at_gap``).
        target: the PEM as a detector (the rollouts' p).
        n_gap, n_speed: the committor's grid (:data:`TILT_GAPS`, :data:`TILT_SPEEDS`).
        eps: the PEM's share of each step's proposal, in (0, 1].
    Raises:
        ValueError: ``eps`` outside (0, 1]."""

    def __init__(
        self,
        params: BrakingParams,
        logit_at_gap: LogitFn,
        target: Detector,
        n_gap: int = TILT_GAPS,
        n_speed: int = TILT_SPEEDS,
        eps: float = TILT_EPS,
    ) -> None:
        if not 0.0 < eps <= 1.0:
            raise ValueError(f"the braking tilt's eps (the PEM's share) must be in (0, 1], got {eps!r}")
        self.params, self.logit_at_gap, self.target = params, logit_at_gap, target
        self.n_gap, self.n_speed, self.eps = n_gap, n_speed, eps
        self.committor: GridCommittor | None = None

    def solve(self) -> int | None:
        """Solve the committor (:func:`solved_committor`); the steps it evaluated, or None when it was reused."""
        if self.committor is not None:
            return None
        self.committor, reused = solved_committor(self.params, self.logit_at_gap, self.n_gap, self.n_speed)
        return None if reused else self.committor.steps

    def draw(self, n: int, rng: np.random.Generator) -> tuple[RolloutBatch, int]:
        """``n`` rollouts of the tilted proposal and the look-ahead steps they evaluated."""
        if self.committor is None:
            self.solve()
        assert self.committor is not None
        detector = BrakingTiltDetector(self.committor, self.logit_at_gap, self.eps)
        return draw_tilted(detector, self.target, n, rng), detector.steps

    def splitting_score(self, problem: Problem) -> BrakingCommittorScore:
        """-log V as the score of adaptive multilevel splitting (``ams_score = "committor"``), for ``problem`` (the
        braking problem of the same scene and PEM)."""
        solved = self.solve()
        assert self.committor is not None
        return BrakingCommittorScore(self.committor, problem, solved or 0)


class BrakingCommittorScore(StateScore):
    """-log V of the grid committor at every step as a graded AMS score (:class:`pemviz.core.problems.StateScore`):
    the rollouts are the problem's own (``simulate`` / ``branch`` under the PEM); V is read off each step's
    observation (gap, speed, pending brake), no look-ahead.

    Args:
        committor: the solved committor.
        problem: the braking problem of the same scene and PEM.
        steps: the steps of the committor's solve when this run solved it (0: reused), the run's cost besides its
            rollouts (:attr:`steps`)."""

    def __init__(self, committor: GridCommittor, problem: Problem, steps: int = 0) -> None:
        self.committor, self.problem, self.steps = committor, problem, steps

    def graded(self, batch: RolloutBatch) -> np.ndarray:
        """-log V of every rollout's state at every step, float64 [n, T] (nats; +inf before the committor's first
        step, 700 where no crash can follow)."""
        obs = batch.observations
        out = np.full(obs.shape[:2], np.inf)
        for t in range(self.committor.first_step, obs.shape[1]):
            out[:, t] = -self.committor.log_value(t, obs[:, t, 0], obs[:, t, 1], obs[:, t, 3] > 0.5)
        return out


def tilted_problem(problem: Problem, pem, params: BrakingParams | None = None) -> Problem:
    """``problem`` (the braking problem of ``pem`` and ``params`` on its batched twin, e.g.
    ``pemviz.scenarios.problems.problem_for(config)``) with this tilted proposal as its ``tilt``, so that
    ``method = "tilt"`` and ``ams_score = "committor"`` run on it (``Experiment(config, problem=...)``).

    Raises:
        ValueError: a problem not on the batched twin (the tilt reads its controller state: ``--sim batched``)."""
    if problem.stream is None:
        raise ValueError("the braking tilt runs on the batched twin only (sim = 'batched')")
    tilt = functools.partial(BrakingTilt, params or BrakingParams(), pem.logit_at_gap, PEMDetector(pem))
    return dataclasses.replace(problem, tilt=tilt)
