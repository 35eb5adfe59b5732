"""A study, not shipped: a scene-neutral graded score for adaptive multilevel splitting learned from the state the
stack acts on: a logistic regression of "this rollout fails" on each step's state features, fitted on a pilot's
rollouts before the run. Measured on the crossing and its 1e-4 rung (docs/validation.md, "A scene-neutral
sampler"): no ties, but median errors 0.45 and 0.51 and 5 of 20 runs `reliable` outside x2, so pemviz does not
ship it (``--ams-score`` has no ``learned``).

Commands (each seed's run is the engine's ``--method ams`` with this score: :func:`pemviz.estimators.ams.run_ams`)::

    nice -n 10 python research/learned_score.py --scenario crossing --reference 2.98e-4 --seeds 1 2 3 4 5 6 7 8 9 10
    nice -n 10 python research/learned_score.py --scenario crossing --param brake_ttc_s=1.5 --reference 1.294e-4 \
        --seeds 1 2 3 4 5 6 7 8 9 10
    python -m pytest research/tests/test_learned_score.py

The pilot is a splitting run of its own (:data:`PILOT_PARTICLES` particles ranked by the nominal look-ahead,
:mod:`pemviz.estimators.lookahead_score`) from streams of its own (``(seed, 2)`` and ``(seed, 3)``), so the score is
fixed before the run's particles are drawn and is no function of them; where it sees no failure (it died out),
another from ``(seed, 2, a)`` and ``(seed, 3, a)``, a = 1, 2 (:data:`PILOT_ATTEMPTS`), then one ranked by the
robustness (a = 3), until one ends with failures. Every rollout the pilots simulated (their initial particles and
every branch) gives a row per step it had not yet failed at (a branch's from its branching step on: its prefix is its
parent's): every object's row (the columns the PEM reads, e.g. its true range and time to collision), the step's state
features (:attr:`pemviz.core.problems.Problem.features`: the ego's, and each object's, e.g. the library tracker's
confirmed flag, age, misses, position and velocity estimates and their variances and predicted time to collision), the
operand's robustness at the step and its running minimum, and the step over the horizon (:func:`design`); the label
is whether the rollout failed. The fit is scikit-learn's L2-regularised logistic regression on the standardised rows
(float64; ``class_weight="balanced"``: the pilot's failures are a share the splitting set, not p).

The score of a rollout at step t is ``exp(-max_{t' <= t} z(t') / Z_SCALE)``, z the fitted log-odds: splitting reads
only the scores' order, so any falling function of the running maximum gives the same run, and this one keeps log-odds
up to about 880 apart where -log sigmoid(z) rounds to 0 above 37. It is a path functional that only falls as the path
goes on, as splitting's levels need, and a function of the state and the step, which keeps the estimate unbiased for
any fit (Brehier, Gazeau, Goudenege, Lelievre & Rousset, "Unbiasedness of some generalized adaptive multilevel
splitting algorithms", Ann. Appl. Probab. 26(6), 2016); the score sets the variance only (Lopes & Lelievre, "Analysis
of the adaptive multilevel splitting method on the isomerization of alanine dipeptide", J. Comput. Chem. 40(11),
2019, compare reaction coordinates so). Where the pilots saw no failure, or nothing but failures, nothing is fitted and
the score is the robustness (the classic splitting).

Cost (:attr:`LearnedScore.steps`, rollout-steps besides the run's own): the pilot's simulated steps (its look-aheads
included), the replay of every pilot rollout's features, and the replay of each of the run's rollouts (T steps each,
a branch's prefix included: the features are rebuilt from the rollout's events, :func:`pemviz.core.features.
replay_features`).
"""

from __future__ import annotations

import argparse
import math

import numpy as np
from pemviz.core.features import StateFeatures
from pemviz.core.problems import Problem, StateScore, no_branch_message, step_robustness
from pemviz.core.rollouts import RolloutBatch
from pemviz.estimators.ams import Splitting

PILOT_PARTICLES = 100
"""The pilot splitting's particles N (it kills :data:`PILOT_KILLED` per iteration at least)."""
PILOT_KILLED = 10
"""The pilot splitting's k."""
PILOT_ATTEMPTS = 3
"""Look-ahead pilots tried (each from streams of its own) before the robustness's: a pilot of 100 particles ranked by
the look-ahead dies out with no failure now and then (1 crossing seed in 10)."""
PILOT_MAX_ITERATIONS = 1_000
"""The pilot splitting's most iterations."""
CAP = 1e3
Z_SCALE = 32.0
"""Nats of fitted log-odds per e-fold of the score (module docstring): scores stay above the splitting's floor
(:data:`pemviz.estimators.ams.SCORE_FLOOR`) and apart for log-odds up to about 880."""
"""The rows' columns are clipped to +-this (the operand's robustness is +inf outside the formula's window)."""


def design(problem: Problem, batch: RolloutBatch, features: StateFeatures) -> np.ndarray:
    """The regression's rows of every rollout and step, float64 [N, T, D]: every object's row (the columns the PEM
    reads, object by object: e.g. its true range and time to collision), the ego's state features (F), every object's
    (M G, object by object: e.g. its track's), the operand's robustness at the step and its running minimum, and the
    step over the horizon (t / T); each column clipped to +-:data:`CAP`, nan as 0."""
    n, t_end = batch.n, batch.n_steps
    rho = _finite(step_robustness(problem, batch))
    run = np.minimum.accumulate(rho, axis=1)
    step = np.broadcast_to(np.arange(t_end, dtype=np.float64)[None, :] / t_end, (n, t_end))
    rows = [] if batch.objects is None else [_finite(batch.object_rows).reshape(n, t_end, -1)]
    return np.concatenate(
        [*rows, features.ego, features.objects.reshape(n, t_end, -1), rho[..., None], run[..., None], step[..., None]],
        axis=-1,
    )


def _finite(x: np.ndarray) -> np.ndarray:
    """``x`` clipped to +-:data:`CAP`, nan as 0 (an object out of sight may have rows that are not finite)."""
    return np.clip(np.nan_to_num(np.asarray(x, dtype=np.float64), nan=0.0, posinf=CAP, neginf=-CAP), -CAP, CAP)


class _Recorder:
    """A graded score that keeps every rollout another (``inner``) simulates and the step each branch starts at."""

    def __init__(self, inner: object) -> None:
        self.inner = inner
        self.batches: list[RolloutBatch] = []
        self.starts: list[np.ndarray] = []

    @property
    def steps(self) -> int:
        return int(getattr(self.inner, "steps", 0))

    def simulate(self, n: int, rng: np.random.Generator) -> tuple[RolloutBatch, np.ndarray]:
        batch, graded = self.inner.simulate(n, rng)  # type: ignore[attr-defined]
        self.batches.append(batch)
        self.starts.append(np.full(n, -1))
        return batch, graded

    def branch(
        self, parents: RolloutBatch, parent: np.ndarray, at: np.ndarray, rng: np.random.Generator
    ) -> tuple[RolloutBatch, np.ndarray]:
        batch, graded = self.inner.branch(parents, parent, at, rng)  # type: ignore[attr-defined]
        self.batches.append(batch)
        self.starts.append(np.asarray(at))
        return batch, graded


class _Robustness(StateScore):
    """The operand's robustness as a graded score (the pilot's second ranking)."""

    def __init__(self, problem: Problem) -> None:
        self.problem, self.steps = problem, 0

    def graded(self, batch: RolloutBatch) -> np.ndarray:
        return step_robustness(self.problem, batch)


class LearnedScore(StateScore):
    """The learned score (module docstring) as a :class:`pemviz.estimators.ams.GradedScore`: it draws the run's
    particles from the problem's target and scores them.

    Args:
        problem: a problem with ``branch``, state features (:attr:`pemviz.core.problems.Problem.features`) and a
            ``G[a,b](state predicate)`` formula.
        seed: the run's seed; the pilot draws from ``(seed, 2)`` and ``(seed, 3)``.
        pilot_particles, pilot_killed: the pilot splitting's N and k, 1 <= k < N.

    Attributes:
        model: the fitted (scaler, logistic regression), or None: the pilot saw one outcome only (the score is the
            robustness).
        pilot_failures, pilot_rollouts: the pilot's failing rollouts and all its rollouts (its rows' labels).

    Raises:
        ValueError: a problem without ``branch`` or without state features, or a pilot k outside 1..N-1: one line.
    """

    def __init__(
        self,
        problem: Problem,
        seed: int,
        pilot_particles: int = PILOT_PARTICLES,
        pilot_killed: int = PILOT_KILLED,
    ) -> None:
        if problem.branch is None:
            raise ValueError(no_branch_message(problem))
        if problem.features is None:
            raise ValueError(
                f"the learned score needs a scenario that reports its state features; {problem.name} reports none: "
                "use ams_score lookahead or robustness"
            )
        if not 1 <= pilot_killed < pilot_particles:
            raise ValueError(f"LearnedScore: the pilot needs 1 <= k < N, got k = {pilot_killed}, N = {pilot_particles}")
        self.problem, self.steps = problem, 0
        self.model: tuple[object, object] | None = None
        self.pilot_failures = self.pilot_rollouts = 0
        self._fit(seed, pilot_particles, pilot_killed)

    def _replayed(self, batch: RolloutBatch) -> StateFeatures:
        """The batch's state features, their replay counted in :attr:`steps`."""
        assert self.problem.features is not None
        features = self.problem.features(batch, None)
        if features is None:
            raise ValueError(f"the learned score: {self.problem.name}'s simulator reports no state features")
        self.steps += batch.n * batch.n_steps
        return features

    def _pilot(self, seed: int, n: int, k: int) -> list[tuple[RolloutBatch, np.ndarray]]:
        """The pilot splittings (module docstring), each run to its end, until one ends with a failure: every
        rollout they simulated and the step it branched at (-1: an initial one); their cost added to :attr:`steps`."""
        from pemviz.estimators.lookahead_score import LookAheadScore

        pilots = [(LookAheadScore(self.problem), a) for a in range(PILOT_ATTEMPTS)]
        out: list[tuple[RolloutBatch, np.ndarray]] = []
        for inner, attempt in [*pilots, (_Robustness(self.problem), PILOT_ATTEMPTS)]:
            rec = _Recorder(inner)
            tail = (attempt,) if attempt else ()
            sp = Splitting(
                self.problem,
                k,
                PILOT_MAX_ITERATIONS,
                np.random.default_rng((seed, 2, *tail)),
                np.random.default_rng((seed, 3, *tail)),
                rec,
            )
            sp.start(*rec.simulate(n, sp.rng))
            while not sp.stop:
                sp.iterate()
            self.steps += sp.steps + rec.steps
            out.extend(zip(rec.batches, rec.starts, strict=True))
            if sp.log_prod > -math.inf and bool(np.any(sp.score < 0.0)):
                break
        return out

    def _fit(self, seed: int, n: int, k: int) -> None:
        """The pilot, its rows and the logistic regression of each row's rollout failing."""
        from sklearn.linear_model import LogisticRegression
        from sklearn.preprocessing import StandardScaler

        pilot = self._pilot(seed, n, k)
        rows, labels = [], []
        for batch, start in pilot:
            x = design(self.problem, batch, self._replayed(batch))
            rho = step_robustness(self.problem, batch)
            failed = np.min(rho, axis=1) < 0.0
            alive = np.minimum.accumulate(rho, axis=1) >= 0.0
            new = np.arange(batch.n_steps)[None, :] > start[:, None]  # a branch's prefix is its parent's rows
            keep = alive & new
            rows.append(x[keep])
            labels.append(np.broadcast_to(failed[:, None], keep.shape)[keep])
            self.pilot_rollouts += batch.n
            self.pilot_failures += int(failed.sum())
        x, y = np.concatenate(rows), np.concatenate(labels)
        if self.pilot_failures == 0 or self.pilot_failures == self.pilot_rollouts or np.unique(y).size < 2:
            return
        scaler = StandardScaler().fit(x)
        model = LogisticRegression(C=1.0, class_weight="balanced", max_iter=2_000).fit(scaler.transform(x), y)
        self.model = (scaler, model)

    def log_odds(self, x: np.ndarray) -> np.ndarray:
        """The fitted log-odds of failing of rows ``x`` float64 [..., D] (:func:`design`), float64 [...]."""
        assert self.model is not None, "log_odds() of a score that fitted nothing"
        scaler, model = self.model
        flat = x.reshape(-1, x.shape[-1])
        return np.asarray(model.decision_function(scaler.transform(flat)), dtype=np.float64).reshape(x.shape[:-1])  # type: ignore[attr-defined]

    def graded(self, batch: RolloutBatch) -> np.ndarray:
        """The score of every rollout at every step, float64 [N, T] (lower = closer to failure): exp(-z / Z_SCALE) of
        the running maximum z of the fitted log-odds (the robustness where nothing was fitted). Replays the batch's
        state features (counted in :attr:`steps`)."""
        if self.model is None:
            return step_robustness(self.problem, batch)
        z = np.maximum.accumulate(self.log_odds(design(self.problem, batch, self._replayed(batch))), axis=1)
        return np.exp(-z / Z_SCALE)


def problem_of(scenario: str, params: list[str]) -> Problem:
    """The scene's problem at ``--param`` values ``params`` ("name=value"), as ``pemviz run`` builds it."""
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args
    from pemviz.scenarios.registry import problem_for

    flags = [f for p in params for f in ("--param", p)]
    return problem_for(config_from_args(build_parser("run").parse_args(["run", "--scenario", scenario, *flags])))


def main(argv: list[str] | None = None) -> None:
    """Each seed's splitting run ranked by the learned score, then the rows of the Validation page's table: median
    relative error, within x2, intervals printed and holding the reference, `reliable` outside x2, the mean cost in
    rollout-equivalents (the pilot included) and its ratio to plain Monte Carlo's (0.6745 / m)^2 (1 - p) / p."""
    from pemviz.estimators.ams import run_ams

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--scenario", default="crossing")
    ap.add_argument("--param", action="append", default=[], help="the scene's --param name=value")
    ap.add_argument("--reference", type=float, required=True, help="the scene's p (plain Monte Carlo)")
    ap.add_argument("--seeds", type=int, nargs="+", default=list(range(1, 11)))
    ap.add_argument("--n", type=int, default=400, help="particles")
    ap.add_argument("--killed", type=int, default=40, help="particles killed an iteration")
    a = ap.parse_args(argv)
    pb, p = problem_of(a.scenario, a.param), a.reference
    errors, within, printed, holding, wrong, costs = [], 0, 0, 0, 0, []
    for seed in a.seeds:
        run = run_ams(pb, a.n, a.killed, seed=seed, score=LearnedScore(pb, seed))
        e = run.estimate()
        ratio = math.exp(e.log_mu_hat) / p
        errors.append(abs(ratio - 1.0))
        within += 0.5 <= ratio <= 2.0
        has_ci = e.log_ci[0] > -math.inf and e.log_ci[1] < 0.0
        printed += has_ci
        holding += has_ci and e.log_ci[0] <= math.log(p) <= e.log_ci[1]
        wrong += e.verdict == "reliable" and not 0.5 <= ratio <= 2.0
        costs.append(run.n_simulations)
        print(
            f"seed {seed}: p_hat {math.exp(e.log_mu_hat):.3e} (x{ratio:.2f}), {e.verdict}, ESS {e.ess:.1f}, "
            f"{run.n_simulations} rollout-equivalents",
            flush=True,
        )
    m = float(np.median(errors))
    plain = (0.6745 / m) ** 2 * (1.0 - p) / p if m > 0 else math.inf
    print(
        f"median relative error {m:.3f}; within x2 {within}/{len(errors)}; intervals holding {holding}/{printed}; "
        f"reliable outside x2 {wrong}; cost {np.mean(costs):,.0f}; plain MC for that error {plain:,.0f}; "
        f"ratio {np.mean(costs) / plain:.2f}"
    )


if __name__ == "__main__":
    main()
