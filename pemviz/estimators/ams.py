"""Adaptive multilevel splitting (AMS) on STL robustness: rare failures without importance weights.

N particles are rollouts drawn from the target detector (the PEM). A particle's score is its classic robustness
``min_{t in [a, b]} rho(t)`` of the safety formula ``G[a,b](operand)`` (lower = closer to failure; failure: < 0),
and the score of a prefix is the running minimum up to its last step. Each iteration takes the level ``L`` = the
k-th highest score, kills every particle scoring ``>= L`` (all ties at the level, K_j >= k of them) and replaces
each by a copy of a survivor drawn uniformly, branched at the first step where the survivor's operand robustness
drops strictly below ``L`` and continued from there with the target detector (``Problem.branch``: the simulator's
snapshot/restore). The run stops once the level reaches the failure threshold (``L <= 0``), when every particle
ties at the level (extinction: the estimate is 0), or after ``ams_max_iterations``. The estimate is

    p_hat = prod_{j < J} (1 - K_j / N) * (1 / N) sum_i 1[score_i < 0]

Sources: Cerou & Guyader, "Adaptive multilevel splitting for rare event analysis", Stoch. Anal. Appl. 25(2), 2007
(the algorithm and its asymptotic variance); Brehier, Gazeau, Goudenege, Lelievre & Rousset, "Unbiasedness of some
generalized adaptive multilevel splitting algorithms", Ann. Appl. Probab. 26(6), 2016 (killing every tie at the
level and branching where the survivor's path first goes strictly past it make p_hat unbiased for any N >= 2, any
k, and a discrete-time Markov process such as these simulators; the estimator is a martingale over iterations,
so stopping early at a fixed iteration budget keeps it unbiased for the failure event, which lies beyond every
level used); Innes & Ramamoorthy, "Adaptive Splitting of Reusable Temporal Monitors for Rare Traffic Violations",
arXiv 2405.15771, 2024 (AMS with STL robustness as the score, by the authors of the PEM sampler).

A scene-neutral graded score (``ams_score = "lookahead"``, :mod:`pemviz.estimators.lookahead_score`) ranks the
particles by the robustness of their nominal continuation (the PEM's most likely events from the step on), which any
scene with ``branch`` has. A scenario's graded score (``ams_score = "committor"``, :class:`GradedScore`) ranks the
particles by -log of a scenario's learned probability of failure V(s) instead: where a scene's robustness sits on one
plateau in most rollouts (e.g. the cut-in's), its levels tie, and V takes a continuum of values. The failure threshold
stays the robustness's: a prefix scores the running minimum of the graded score at the steps that do not fail (at
least :data:`SCORE_FLOOR`) and of the robustness (< 0) at those that do. Any score that is a function of the state and
the step keeps p_hat unbiased (Brehier et al. 2016 above); a poor one costs variance (more ties, fewer families).

Cost: the N initial rollouts (N T steps) plus, per iteration, the continuations' steps sum_i (T - branch step_i).
``n_simulations`` counts rollout-equivalents, ceil(simulated steps / T), so that budgets compare with the
cross-entropy sampler's rollouts (its default spends 2,100), with a graded score's look-ahead and preparation steps.
Replayed prefixes are not counted: a snapshot restores them without simulation."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from scipy.special import logsumexp, ndtri, stdtrit

from pemviz import stl
from pemviz.config import ExperimentConfig
from pemviz.core.confidence import CI_LEVEL
from pemviz.core.estimate import MIN_FAILURES, Estimate
from pemviz.core.plan import RunPlan
from pemviz.core.problems import Problem, no_branch_message, step_robustness
from pemviz.core.rollouts import RolloutBatch
from pemviz.estimators.ams_pool import PooledRuns, ReplicaRun, pooled_runs
from pemviz.estimators.base import Check, OwnsSettings, StageOutcome, StagePlan, log_p_before_failure
from pemviz.methods import SPLITTING_METHOD
from pemviz.methods.ams import AMS_STAGE
from pemviz.settings import settings_of

REPLICA_STREAM = 10
"""Replica r >= 1 of a run of seed s draws from ``(s, REPLICA_STREAM, r)`` and picks survivors from ``(s,
REPLICA_STREAM + 1, r)``: apart from the first run's ``s`` and ``(s, 1)`` and the learned score's ``(s, 2)``, ``(s,
3)``."""
MIN_REPLICAS = 4
"""The fewest runs whose spread backs a ``reliable`` verdict (:func:`replicas_estimate`)."""
MIN_SPREAD_ESS = 2.0
"""The least effective number of runs (sum p)^2 / sum p^2 for ``reliable``: below it one run carries the mean."""
SCORE_FLOOR = 1e-12
"""The least graded score of a prefix that has not failed: a state whose committor rounds to 1 stays above the failure
threshold 0."""


class GradedScore(Protocol):
    """A graded AMS score that a scenario computes while it simulates, -log of a learned committor V
    (e.g. :class:`pemviz.scenarios.cut_in.splitting.CommittorScore`); ``simulate(n, rng)`` draws n rollouts from the
    target, ``branch(parents, parent, at, rng)`` continues parents' rollouts from the steps ``at`` as
    ``Problem.branch`` does; each returns the rollouts [K, T] and the score at every step, float64 [K, T] (lower =
    closer to failure; +inf at steps not scored, and up to ``at`` for a branch). ``steps`` counts the rollout-steps
    simulated besides the rollouts (its look-aheads, its preparation)."""

    steps: int

    def simulate(self, n: int, rng: np.random.Generator) -> tuple[RolloutBatch, np.ndarray]: ...

    def branch(
        self, parents: RolloutBatch, parent: np.ndarray, at: np.ndarray, rng: np.random.Generator
    ) -> tuple[RolloutBatch, np.ndarray]: ...


def running_score(
    problem: Problem,
    batch: RolloutBatch,
    graded: np.ndarray | None = None,
    prefix: np.ndarray | None = None,
    at: np.ndarray | None = None,
) -> np.ndarray:
    """The score of every prefix, float64 [N, T]: the running minimum over ``t' <= t`` of the operand's classic
    robustness (:func:`step_robustness`), or with ``graded`` [N, T] (a :class:`GradedScore`'s) of the graded score
    (at least :data:`SCORE_FLOOR`) at steps that do not fail and the robustness (< 0) at those that do. The last
    column is below 0 exactly when the rollout fails.

    Args:
        problem: the problem whose formula's operand gives the robustness (metres for a gap).
        batch: the rollouts [N, T].
        graded: a :class:`GradedScore`'s scores float64 [N, T] (lower = closer to failure), or None: the robustness.
        prefix: a branch's parents' running scores float64 [N, T], or None (initial rollouts).
        at: the branch's branching steps int [N]: the score up to and including ``at`` is the parent's (the same
            state).

    Raises:
        ValueError: a formula that is not ``G[a,b](state predicate)``."""
    score = step_robustness(problem, batch)
    if graded is not None:
        score = np.where(score < 0.0, score, np.maximum(graded, SCORE_FLOOR))
    if prefix is not None and at is not None:
        score = np.where(np.arange(score.shape[1])[None, :] <= at[:, None], prefix, score)
    return np.minimum.accumulate(score, axis=1)


def _replaced(batch: RolloutBatch, rows: np.ndarray, new: RolloutBatch) -> RolloutBatch:
    """A copy of ``batch`` whose rollouts ``rows`` [K] are ``new``'s [K] (every per-rollout array)."""
    out = {}
    for name in ("observations", "detected", "log_p", "log_q", "objects", "noise"):
        a = getattr(batch, name)
        if a is not None:
            a = a.copy()
            a[rows] = getattr(new, name)
        out[name] = a
    return dataclasses.replace(batch, log_q_parts=None, **out)


@dataclass
class Splitting:
    """The state of one AMS run (module docstring): the N particles, their scores and genealogy, the product.

    Args:
        problem: needs ``branch`` (snapshot/restore) and a ``G[a,b](state predicate)`` formula.
        killed: k, the particles killed per iteration at least (ties at the level add to it), 1 <= k < N.
        max_iterations: stop after this many iterations even if the level has not reached 0.
        rng: the detections of the continuations; pick_rng: which survivor each killed particle copies.
        scorer: a graded score that simulates the particles itself (None: the robustness, and the problem's
            ``simulate`` / ``branch``)."""

    problem: Problem
    killed: int
    max_iterations: int
    rng: np.random.Generator
    pick_rng: np.random.Generator
    scorer: GradedScore | None = None
    particles: RolloutBatch | None = None
    running: np.ndarray = field(default_factory=lambda: np.empty((0, 0)))
    """float64 [N, T] prefix scores (:func:`running_score`)."""
    eve: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    """int [N]: the initial particle each particle descends from."""
    log_prod: float = 0.0
    """sum_j log(1 - K_j / N) (nats; -inf after an extinction)."""
    ratio_sum: float = 0.0
    """sum_j K_j / (N - K_j), for the asymptotic variance."""
    iterations: int = 0
    level: float = math.inf
    steps: int = 0
    """Simulated steps so far (initial rollouts and continuations)."""
    stop: str = ""
    """Why the run ended (empty while it goes on)."""

    @property
    def n(self) -> int:
        return 0 if self.particles is None else self.particles.n

    @property
    def score(self) -> np.ndarray:
        """Each particle's score, its classic robustness, float64 [N]."""
        return self.running[:, -1]

    @property
    def n_simulations(self) -> int:
        """Rollout-equivalents simulated: ceil(steps / T), the scorer's steps included."""
        if self.particles is None:
            return 0
        steps = self.steps + (self.scorer.steps if self.scorer is not None else 0)
        return -(-steps // max(self.particles.n_steps, 1))

    def start(self, batch: RolloutBatch, graded: np.ndarray | None = None) -> None:
        """Take the N initial rollouts of the target detector (and their graded scores [N, T], with a scorer)."""
        self.particles, self.running = batch, running_score(self.problem, batch, graded)
        self.eve = np.arange(batch.n)
        self.steps += batch.n * batch.n_steps
        self._check_stop()

    def _check_stop(self) -> None:
        s = np.sort(self.score)
        self.level = float(s[-self.killed])
        if self.level <= 0.0:
            self.stop = "the level reached the failure threshold"
        elif self.iterations >= self.max_iterations:
            self.stop = f"stopped after {self.iterations} iterations (ams_max_iterations) at level {self.level:.4g}"
        elif s[0] >= self.level:
            self.stop = f"extinction: every particle ties at level {self.level:.4g}"
            self.log_prod = -math.inf

    def iterate(self) -> int:
        """One iteration: kill the particles at or above the level, branch their replacements; returns K_j."""
        score, n, particles = self.score, self.n, self.particles
        assert particles is not None, "iterate() before start()"
        killed = np.flatnonzero(score >= self.level)
        survivors = np.flatnonzero(score < self.level)
        parent = survivors[self.pick_rng.integers(survivors.size, size=killed.size)]
        at = np.argmax(self.running[parent] < self.level, axis=1)  # first step strictly below the level
        if self.scorer is None:
            branch = self.problem.branch
            assert branch is not None  # AMS needs snapshot/restore (AdaptiveMultilevelSplitting checks it)
            new = branch(particles, parent, at, self.problem.target, self.rng)
            new_running = running_score(self.problem, new)
        else:
            new, graded = self.scorer.branch(particles, parent, at, self.rng)
            new_running = running_score(self.problem, new, graded, self.running[parent], at)
        b = particles
        self.particles = _replaced(b, killed, new)
        self.running = self.running.copy()
        self.running[killed] = new_running
        self.eve = self.eve.copy()
        self.eve[killed] = self.eve[parent]
        k = killed.size
        self.log_prod += math.log1p(-k / n)
        self.ratio_sum += k / (n - k)
        self.iterations += 1
        self.steps += int((b.n_steps - at).sum())
        self._check_stop()
        return k

    def estimate(self) -> Estimate:
        """p_hat with its :data:`CI_LEVEL` interval, diagnostics and verdict (see :func:`ams_estimate`)."""
        assert self.particles is not None, "estimate() before start()"
        return ams_estimate(
            self.problem, self.particles, self.running[:, -1] < 0.0, self.eve, self.log_prod, self.ratio_sum, self.stop
        )


def ams_estimate(
    problem: Problem,
    particles: RolloutBatch,
    failed: np.ndarray,
    eve: np.ndarray,
    log_prod: float,
    ratio_sum: float,
    stop: str,
) -> Estimate:
    """The AMS estimate of the particles now: ``log p_hat = log_prod + log(failures / N)`` (nats).

    Interval: log p_hat -+ z sqrt(v), z the normal quantile of :data:`CI_LEVEL`, v the larger of two relative
    variances: the asymptotic one of the ideal algorithm, ``(sum_j K_j / (N - K_j) + (1 - r) / r) / N`` with r the
    final fraction of failures (Cerou & Guyader 2007, Sec. 4; exact for the ideal score, a lower bound for
    others), and the spread over the genealogy, ``sum_e (c_e / n_f - 1 / N)^2`` with c_e the failures descending
    from initial particle e (the N eves taken as independent; for plain Monte Carlo it is (1 - p) / (N p)); once
    every failure descends from one eve it is ~1, the honest answer when one initial rollout carries the estimate.
    ``ess`` is 1 / v: the failures a Monte Carlo sample of the same relative variance would hold.

    Verdict: ``unreliable`` with no failure (p_hat = 0, after an extinction or with the level above 0);
    ``doubtful`` when stopped before the level reached 0, with fewer than :data:`MIN_FAILURES` failures, or when
    the failures descend from fewer than :data:`MIN_FAILURES` initial particles (the variance then rests on one
    family); else ``reliable``. There are no importance weights (k-hat nan, mean weight 1)."""
    n = particles.n
    nf = int(failed.sum())
    lp = log_p_before_failure(problem, particles)[failed]
    if nf == 0 or log_prod == -math.inf:
        why = stop if log_prod == -math.inf else f"no particle fails ({stop or 'the run goes on'})"
        return Estimate(
            n, nf, -math.inf, math.nan, math.nan, 0.0, (-math.inf, 0.0), math.nan, 0.0, "unreliable", f"AMS: {why}"
        )
    r = nf / n
    v_ideal = (ratio_sum + (1.0 - r) / r) / n
    counts = np.bincount(eve[failed], minlength=n)
    v_eve = float(np.square(counts / nf - 1.0 / n).sum())
    v = max(v_ideal, v_eve)
    log_p = log_prod + math.log(r)
    half = float(ndtri(0.5 + CI_LEVEL / 2.0)) * math.sqrt(v)
    families = int(np.count_nonzero(counts))
    if stop and not stop.startswith("the level reached"):
        verdict, reason = "doubtful", f"AMS {stop}"
    elif nf < MIN_FAILURES:
        verdict, reason = "doubtful", f"only {nf} failing particle{'s' if nf != 1 else ''}"
    elif families < MIN_FAILURES:
        verdict, reason = (
            "doubtful",
            (
                f"AMS: the {nf} failures descend from {families} of {n} initial rollout"
                f"{'s' if families != 1 else ''}"
            ),
        )
    else:
        verdict, reason = "reliable", f"AMS: {nf} failures from {families} initial rollouts"
    return Estimate(
        n,
        nf,
        log_p,
        float(-lp.mean()),
        -(float(logsumexp(lp)) - math.log(nf)),
        1.0 / v,
        (log_p - half, log_p + half),
        math.nan,
        0.0,
        verdict,
        reason,
        markov_logs=(log_p,),
    )  # unbiased, stopped early or not: Markov's bound


def replica_streams(seed: int, r: int) -> tuple[np.random.Generator, np.random.Generator]:
    """Replica r's detection and survivor streams: ``seed`` and ``(seed, 1)`` for r = 0 (the run of one splitting),
    ``(seed, REPLICA_STREAM, r)`` and ``(seed, REPLICA_STREAM + 1, r)`` for r >= 1."""
    if r == 0:
        return np.random.default_rng(seed), np.random.default_rng((seed, 1))
    return np.random.default_rng((seed, REPLICA_STREAM, r)), np.random.default_rng((seed, REPLICA_STREAM + 1, r))


def replicas_interval(p: np.ndarray, v: np.ndarray | None = None) -> tuple[tuple[float, float], str, str]:
    """The :data:`CI_LEVEL` interval of the mean p_bar of R >= 2 independent runs' estimates ``p`` float64 [R] (nats,
    (-inf, 0) when every run is 0), its verdict and why: the delta method on log p_bar, ``log p_bar -+ t_{R-1}
    sqrt(w)``, t Student's quantile with R - 1 degrees of freedom and w p_bar's relative variance, the larger of the
    runs' spread, s^2 / (R p_bar^2) (s their sample standard deviation), and, given each run's own relative variance
    ``v`` float64 [R] (its genealogy's, :func:`ams_estimate`), their sum sum_r p_r^2 v_r / (R p_bar)^2: R runs that
    happen to agree (the mass of p_hat sits in rare large runs) do not make the interval narrower than each run's
    genealogy says.

    Verdict: ``unreliable`` when every run is 0; ``reliable`` with R >= :data:`MIN_REPLICAS`, at most one run 0, a
    positive spread and the runs' effective count (sum p)^2 / sum p^2 >= :data:`MIN_SPREAD_ESS` (the mean not carried
    by one run); else ``doubtful``."""
    r, mean = p.size, float(p.mean())
    if mean == 0.0:
        return (-math.inf, 0.0), "unreliable", f"AMS: no failure in {r} runs"
    rel = float(p.std(ddof=1)) / (math.sqrt(r) * mean)
    if v is not None:
        rel = max(rel, math.sqrt(float(np.square(p) @ np.where(p > 0.0, v, 0.0))) / (r * mean))
    half = float(stdtrit(r - 1, 0.5 + CI_LEVEL / 2.0)) * rel
    spread_ess = mean**2 * r / float(np.square(p).mean())
    zeros = int(np.count_nonzero(p == 0.0))
    ok = r >= MIN_REPLICAS and zeros <= 1 and rel > 0.0 and spread_ess >= MIN_SPREAD_ESS
    why = f"AMS: the mean of {r} runs ({zeros} with no failure), {spread_ess:.1f} effective"
    return (math.log(mean) - half, math.log(mean) + half), "reliable" if ok else "doubtful", why


def replicas_estimate(replicas: list[Estimate]) -> Estimate:
    """The mean p_bar = (1 / R) sum_r p_hat_r of R >= 2 independent splitting runs' estimates ``replicas`` (a run
    with no failure counts 0), unbiased as each p_hat_r is (Brehier et al. 2016), with the interval and verdict of
    :func:`replicas_interval`: a spread that rests on no genealogy (Cerou, Guyader, Lelievre & Pommier, "A multiple
    replica approach to simulate reactive trajectories", J. Chem. Phys. 134, 2011). ``ess`` is 1 / the relative
    variance of p_bar, the failures a Monte Carlo sample of the same relative error would hold; the lower bound is
    Markov's over the runs."""
    p = np.array([math.exp(e.log_mu_hat) for e in replicas])
    n, nf = sum(e.n for e in replicas), sum(e.n_failures for e in replicas)
    (lo, hi), verdict, why = replicas_interval(p, np.array([1.0 / e.ess if e.ess > 0 else 0.0 for e in replicas]))
    if verdict == "unreliable":
        return dataclasses.replace(replicas[0], n=n, n_failures=nf, reason=why)
    failing = [e for e in replicas if e.n_failures]
    w = np.array([e.n_failures for e in failing], dtype=np.float64) / nf
    z = float(stdtrit(p.size - 1, 0.5 + CI_LEVEL / 2.0))
    return Estimate(
        n,
        nf,
        (lo + hi) / 2.0,
        float(w @ [e.nll_mean for e in failing]),
        -float(logsumexp([-e.nll_lme for e in failing], b=w)),
        (2.0 * z / (hi - lo)) ** 2 if hi > lo else math.inf,
        (lo, hi),
        math.nan,
        0.0,
        verdict,
        why,
        markov_logs=tuple(e.log_mu_hat for e in replicas) if np.all(p > 0) else ((lo + hi) / 2.0,),
    )


class AdaptiveMultilevelSplitting(OwnsSettings):
    """AMS (module docstring) as an engine estimator (``method = "ams"``).

    Stage 0 draws the N = ``n_per_stage`` initial particles from the target; each later stage runs iterations until
    about N particles have been resampled (or the run stops) and shows the listeners the N particles after them
    (``StagePlan.draw``). ``gamma`` of a stage is the level reached. Streams from ``config.seed``: the detections
    (:attr:`rng`) and the survivor choice (``(seed, 1)``).

    With ``ams_score = "committor"`` the particles are ranked by the problem's learned committor instead (its tilted
    proposal's :class:`GradedScore`, ``problem.tilt().splitting_score(problem)``), which also simulates them.

    Raises:
        ValueError: a problem without ``branch`` (no snapshot/restore) or without a ``G[a,b](state predicate)``
            formula, or a committor score asked of a problem without one: one line."""

    SETTINGS = settings_of(SPLITTING_METHOD)

    def __init__(self, config: ExperimentConfig, problem: Problem, check: Check | None = None) -> None:
        if problem.branch is None:
            raise ValueError(no_branch_message(problem))
        f = problem.formula
        if not isinstance(f, stl.Always) or f.operand.horizon() != 0:
            raise ValueError(f"method ams needs a safety formula G[a,b](state predicate); {problem.name} has {f}")
        self.config, self.problem = config, problem
        self.check: Check = check or (lambda: None)
        self.replicas: list[tuple[Estimate, int]] = []
        """The finished replicas' estimates and rollout-equivalents."""
        self._start_replica(0)
        self._stage = self._first = -1
        self._initial: list[RolloutBatch] = []
        self._graded: np.ndarray | None = None
        self._pooled: PooledRuns | None = None
        """Replicas 1..R-1 on the run's worker processes (None: here, one after another)."""
        self._showing = False
        """Whether the stage planned is a pooled replica's."""
        self._cpu0 = 0.0
        """This process's CPU seconds when the stage was planned (replica 0's first stage prices the others)."""

    def _start_replica(self, r: int, score: GradedScore | None = None) -> None:
        """Replica r's splitting, drawn from :func:`replica_streams` and ranked by ``score`` (None: ``ams_score``)."""
        cfg = self.config
        self.rng, pick = replica_streams(cfg.seed, r)
        score = score or committor_score(self.problem, cfg.ams.ams_score)
        self.ams = Splitting(self.problem, cfg.ams.ams_killed, cfg.ams.ams_max_iterations, self.rng, pick, score)

    @property
    def n_simulations(self) -> int:
        """Rollout-equivalents simulated (module docstring); the engine reports this, not its count of batches."""
        pooled = self._pooled.n_simulations if self._pooled is not None else 0
        return self.ams.n_simulations + pooled + sum(sims for _, sims in self.replicas)

    @staticmethod
    def run_plan(config: ExperimentConfig) -> RunPlan:
        """Stage 0 the N initial particles, then groups of iterations until the run stops (open-ended)."""
        return RunPlan.of([(0, AMS_STAGE, config.n_per_stage)], open_ended=True)

    def plan(self) -> RunPlan:
        return self.run_plan(self.config)

    def next_stage(self) -> StagePlan | None:
        if self._pooled is not None and self.ams.stop:  # replica 0 shown: the others, as they ran in the pool
            batch = self._pooled.next_batch()
            if batch is None:
                return None
            self._stage, self._showing = self._stage + 1, True
            return StagePlan(self._stage, AMS_STAGE, batch.n, self.problem.target, lambda _: batch)
        self._cpu0 = time.process_time()
        if self._stage >= 0 and self.ams.stop:
            if len(self.replicas) + 1 >= self.config.ams.ams_replicas:
                return None
            self.replicas.append((self.ams.estimate(), self.ams.n_simulations))
            self._start_replica(len(self.replicas))
        self._stage += 1
        if self.ams.particles is None:
            self._first = self._stage
        n = self.config.n_per_stage
        first = None if self.ams.scorer is None else self._initial_scored
        return StagePlan(self._stage, AMS_STAGE, n, self.problem.target, first if self._is_first else self._iterate)

    @property
    def _is_first(self) -> bool:
        """Whether this stage draws a replica's initial particles."""
        return self._stage == self._first

    def _initial_scored(self, rng: np.random.Generator) -> RolloutBatch:
        """The N initial particles drawn by the graded score (their scores kept for :meth:`finish`)."""
        assert self.ams.scorer is not None
        batch, self._graded = self.ams.scorer.simulate(self.config.n_per_stage, rng)
        return batch

    def _iterate(self, rng: np.random.Generator) -> RolloutBatch:
        """Iterations until N particles were resampled or the run stops; the particles after them [N, T]."""
        resampled = 0
        while not self.ams.stop and resampled < self.ams.n:
            self.check()
            resampled += self.ams.iterate()
        assert self.ams.particles is not None  # started by stage 0's finish()
        return self.ams.particles

    def observe(self, batch: RolloutBatch, failed: np.ndarray, robustness: np.ndarray | None) -> np.ndarray:
        if self._is_first and not self._showing:  # the initial particles, possibly in chunks (a streamed stage)
            self._initial.append(batch)
        return np.zeros(batch.n)  # drawn from the target itself: every importance weight is 1

    def finish(self) -> StageOutcome:
        if self._showing:
            return self._pooled.finish()  # type: ignore[union-attr]  # showing: pooled
        if self._is_first:
            self.ams.start(
                RolloutBatch.concatenate(self._initial) if len(self._initial) > 1 else self._initial[0], self._graded
            )
            self._initial, self._graded = [], None
            if self._stage == 0 and self.config.ams.ams_score != "committor":  # one committor, solved once, for all
                cpu = time.process_time() - self._cpu0  # replica 0's initial particles: less than a whole replica
                self._pooled = pooled_runs(self.config, run_replica, self.problem, self.check, cpu)
        nan = np.full(self.problem.curve_grid.size, np.nan)
        failed = self.ams.score < 0.0
        return StageOutcome(self.ams.level, int(failed.sum()), self.ams.estimate(), nan, nan)

    def result(self) -> tuple[Estimate, tuple[int, ...]]:
        """The run's estimate: its one splitting's, or the mean of ``ams_replicas`` (:func:`replicas_estimate`)."""
        if self._pooled is not None:
            return replicas_estimate([self.ams.estimate(), *(e for e, _ in self._pooled.done)]), (self._stage,)
        last = self.ams.estimate()
        return (replicas_estimate([*(e for e, _ in self.replicas), last]) if self.replicas else last), (self._stage,)


def run_replica(problem: Problem, config: ExperimentConfig, r: int) -> ReplicaRun:
    """Replica r of ``config``'s splitting run (:func:`replica_streams`) alone, each stage drawn as the engine draws
    it (the initial particles by ``problem.simulate``: the same bits as on any executor), for a worker process
    (:mod:`pemviz.estimators.ams_pool`): the same bits as one process running the replicas in turn."""
    est = AdaptiveMultilevelSplitting(config.replace(ams_replicas=1), problem)
    est._start_replica(r)
    stages: list[tuple[RolloutBatch, StageOutcome, int]] = []
    while not stages or not est.ams.stop:
        plan = est.next_stage()
        assert plan is not None  # the replica goes on
        batch = plan.draw(est.rng) if plan.draw else problem.simulate(plan.n, plan.sampler, problem.target, est.rng)
        est.observe(batch, np.zeros(batch.n, bool), None)
        stages.append((batch, est.finish(), est.ams.n_simulations))
    return ReplicaRun(tuple(stages), est.ams.estimate(), est.ams.n_simulations)


def committor_score(problem: Problem, score: str) -> GradedScore | None:
    """The graded score ``ams_score`` names: None for ``robustness``; for ``lookahead`` the scene-neutral nominal
    look-ahead (:class:`pemviz.estimators.lookahead_score.LookAheadScore`); for ``committor`` the problem's tilted
    proposal's (solved, or reused from an earlier run of the process).

    Raises:
        ValueError: ``committor`` for a problem whose scenario has no learned committor: one line."""
    if score == "robustness":
        return None
    if score == "lookahead":
        from pemviz.estimators.lookahead_score import LookAheadScore

        return LookAheadScore(problem)
    tilt = problem.tilt() if problem.tilt is not None else None
    if tilt is None or not hasattr(tilt, "splitting_score"):
        raise ValueError(
            f"ams_score committor needs a scenario with a learned committor; "
            f"{problem.name} has none: use ams_score robustness"
        )
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1, user_api="blas"):
        return tilt.splitting_score(problem)


def run_ams(
    problem: Problem,
    n: int,
    killed: int,
    seed: int = 0,
    max_iterations: int = 100_000,
    score: str | GradedScore = "robustness",
    replica: int = 0,
) -> Splitting:
    """One whole AMS run without the engine (for studies and tests): N particles from ``problem.target``, seeded
    like ``method = "ams"`` with ``seed`` (replica ``replica`` of it: :func:`replica_streams`) and ranked by ``score``
    (an ``ams_score`` name, or a study's own :class:`GradedScore`, which then draws the particles); returns the
    finished :class:`Splitting` (``.estimate()``, ``.n_simulations``).

    Raises:
        ValueError: as :class:`AdaptiveMultilevelSplitting`."""
    cfg = ExperimentConfig.of(
        method=SPLITTING_METHOD,
        n_per_stage=n,
        ams_killed=killed,
        ams_max_iterations=max_iterations,
        seed=seed,
        ams_score=score if isinstance(score, str) else "robustness",
    )
    est = AdaptiveMultilevelSplitting(cfg, problem)
    if replica or not isinstance(score, str):  # another replica's streams, or a study's own score
        est._start_replica(replica, None if isinstance(score, str) else score)
    if est.ams.scorer is not None:
        est.ams.start(*est.ams.scorer.simulate(n, est.rng))
    else:
        est.ams.start(problem.simulate(n, problem.target, problem.target, est.rng))
    while not est.ams.stop:
        est.ams.iterate()
    return est.ams
