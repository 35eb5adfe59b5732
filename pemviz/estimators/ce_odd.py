"""The cross-entropy fit of a proposal over an ODD's parameters (:class:`pemviz.core.odd_proposal.ParameterProposal`)
beside the perception's: the CE stages' samplers draw each rollout's parameters from it, and after each stage it
moves toward the cells of the stage's elites (from the failure level on, of every failure since), weighted as the
perception's fit weighs them. The target's share of a stage's mixture draws its parameters from the ODD itself, so
every weight stays bounded by the target's share, as without a parameter proposal."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pemviz.core.odd_proposal import ParameterProposal

if TYPE_CHECKING:
    from pemviz.core.detectors import StageSamplers
    from pemviz.core.problems import Problem
    from pemviz.core.rollouts import RolloutBatch

RATE = 0.7
"""How far a stage's fit moves q(theta) toward its elites' cells (1: all the way)."""

DEFENSIVE = 0.2
"""The ODD's share in q(theta): no parameter weight exceeds 1 / DEFENSIVE."""


class ParameterFit:
    """The elites' parameters and weights of the CE stages of one run, and the proposal over the ODD fitted to them.

    Args:
        problem: the run's problem; without an ODD (or with one too fine to grid: :meth:`ParameterProposal.of`) there
            is no proposal and every method is a no-op."""

    def __init__(self, problem: Problem) -> None:
        self.proposal = ParameterProposal.of(problem.odd) if problem.odd is not None else None
        self._values: list[np.ndarray] = []
        self._log_w: list[np.ndarray] = []

    def add(self, elites: RolloutBatch, log_w: np.ndarray) -> None:
        """Elite rollouts (their parameters read from the first step's columns) with their smoothed log-weights [K]
        (nats)."""
        if self.proposal is None or elites.n == 0:
            return
        cols = [tuple(elites.observation_names).index(name) for name in self.proposal.odd.names]
        self._values.append(elites.observations[:, 0][:, cols])
        self._log_w.append(np.asarray(log_w, dtype=np.float64))

    def refit(self, keep: bool, samplers: StageSamplers | None) -> None:
        """The proposal moved toward the elites added so far (:meth:`ParameterProposal.refit`), given to
        ``samplers`` (None: none draws from it) to draw the next stage's parameters; ``keep``: hold the elites for
        the next stages' fits too (the failure pool), else forget them."""
        if self.proposal is None:
            return
        if self._values:
            values, log_w = np.concatenate(self._values), np.concatenate(self._log_w)
            self.proposal = self.proposal.refit(values, log_w, RATE, DEFENSIVE)
        if not keep:
            self._values, self._log_w = [], []
        if samplers is not None:
            samplers.parameter_proposal = self.proposal
