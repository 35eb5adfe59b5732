"""The toy's tilted proposal (``method = "tilt"``) with a deliberately poor committor: the check that the tilted
estimator is unbiased whatever its V (:func:`pemviz.testing.check_estimator`). :class:`ToyTilt` tilts by a V that is
wrong on purpose (p(detect) guessed as :data:`P_GUESS`, a stopped car's V taken as :data:`STOPPED_V`, not 0), mixed
with a share :data:`EPS` of the PEM (Kollman, Baggerly, Cox & Picard 1999, Ann. Appl. Probab. 9(2); Hesterberg 1995,
Technometrics 37(2)); its exact weights p / q keep its estimates unbiased, only more variable."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pemviz.core.problems import Problem, StateScore
from pemviz.core.rollouts import RolloutBatch
from pemviz.scenarios.toy.simulator import ToyDetector, ToyParams, simulate_toy

P_GUESS = 0.5
"""The poor V's p(detect) at every distance."""
STOPPED_V = 0.05
"""The poor V's probability of failure after a detection that stops the car (the truth: 0)."""
EPS = 0.2
"""The PEM's share of each step's proposal."""
SCORE_STOPPED_V = 0.4
"""The splitting score's V of a stopped car (the truth: 0): above the poor V of a moving car at every distance but
the last one, so a stopped car, which can never fail, ranks as close to failure."""


def poor_committor(params: ToyParams, d: np.ndarray, stopped: np.ndarray, stopped_v: float = STOPPED_V) -> np.ndarray:
    """The poor V, float64 [N]: a moving car at distance ``d`` [N] (units) fails with probability (1 -
    :data:`P_GUESS`)^(min(d, braking) - safe + 1) (1 below ``safe``), a stopped one (``stopped`` bool [N]) with
    ``stopped_v`` (the truths: prod (1 - p(d')) over the distances left in the window, and 0)."""
    moving = (1.0 - P_GUESS) ** np.clip(np.minimum(d, params.braking) - params.safe + 1.0, 0.0, None)
    return np.where(stopped, stopped_v, moving)


@dataclass(frozen=True)
class ToyTiltDetector:
    """q(detect | distance, stopped) of the toy's tilt, a :class:`~pemviz.core.detectors.Detector`: inside the window
    (a moving car at safe <= d <= braking), q(miss) = (1 - eps) (1 - p) V(d - 1) / ((1 - p) V(d - 1) + p
    :data:`STOPPED_V`) + eps (1 - p) with the poor V(d) = (1 - :data:`P_GUESS`)^(min(d, braking) - safe + 1);
    elsewhere the PEM's own p."""

    params: ToyParams

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        p_par = self.params
        d, stopped = np.asarray(obs, dtype=np.float64)[:, 0], np.asarray(obs)[:, 1] > 0.5
        p = p_par.detect_probability(d)
        inside = ~stopped & (d >= p_par.safe) & (d <= p_par.braking)
        miss = (1.0 - p) * poor_committor(p_par, d - 1.0, np.zeros(d.shape, dtype=bool))
        q_miss = (1.0 - EPS) * miss / (miss + p * STOPPED_V) + EPS * (1.0 - p)
        q = np.where(inside, 1.0 - q_miss, p)
        return np.log(q) - np.log1p(-q)


class ToyTilt:
    """The toy's :class:`pemviz.core.problems.TiltSampler`: rollouts from :class:`ToyTiltDetector`, nothing to
    solve, no look-ahead."""

    def __init__(self, params: ToyParams) -> None:
        self.params = params

    def solve(self) -> int:
        """Nothing to prepare: 0 steps."""
        return 0

    def draw(self, n: int, rng: np.random.Generator) -> tuple[RolloutBatch, int]:
        """``n`` rollouts drawn from :class:`ToyTiltDetector`, scored under the toy's PEM; no look-ahead steps."""
        return simulate_toy(self.params, n, ToyTiltDetector(self.params), ToyDetector(self.params), rng), 0

    def splitting_score(self, problem: Problem) -> ToyCommittorScore:
        """The poor V as the score of adaptive multilevel splitting (``ams_score = "committor"``)."""
        return ToyCommittorScore(self.params, problem)


class ToyCommittorScore(StateScore):
    """-log of a poor V (:func:`poor_committor`, a stopped car's :data:`SCORE_STOPPED_V`) at every step as a graded
    AMS score (:class:`pemviz.core.problems.StateScore`): the check that committor-scored splitting is unbiased
    whatever its score (Brehier, Gazeau, Goudenege, Lelievre & Rousset, Ann. Appl. Probab. 26(6), 2016)."""

    def __init__(self, params: ToyParams, problem: Problem) -> None:
        self.params, self.problem = params, problem

    def graded(self, batch: RolloutBatch) -> np.ndarray:
        obs = batch.observations
        v = poor_committor(self.params, obs[..., 0], obs[..., 1] > 0.5, SCORE_STOPPED_V)
        return -np.log(v)
