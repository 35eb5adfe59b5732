"""The failure population of a finished run as the panel lists it: every failure of the final estimate with the
share of p it carries, as :class:`pemviz.app.runs.Trajectory` rows, grouped by the decisive events they share
(:func:`pemviz.sinks.population.group_failures`). No viser here.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from pemviz.app.runs import Trajectory, trajectory
from pemviz.core.population import FailureShares
from pemviz.engine.events import RolloutsSampled
from pemviz.sinks.population import FailureGrouping, group_failures


@dataclass(frozen=True)
class Population:
    """Every failure of a run's final estimate, largest share first.

    Attributes:
        grouping: the failures, where each lies in the kept batches, their groups.
        rollouts: per rank, the failure as a :class:`Trajectory`, or None where its stage kept only a sample.
    """

    grouping: FailureGrouping
    rollouts: tuple[Trajectory | None, ...]

    @property
    def shares(self) -> FailureShares:
        return self.grouping.shares

    @property
    def groups(self):
        return self.grouping.groups

    @property
    def basis(self) -> str:
        return self.grouping.basis

    def group_label(self, rank: int) -> str:
        return self.grouping.group_label(rank)


def population_of(shares: FailureShares | None, sampled: Mapping[int, RolloutsSampled], scene: object,
                  problem: object = None) -> Population | None:  # fmt: skip
    """The panel's :class:`Population` of a run (arguments as :func:`pemviz.sinks.population.group_failures`); None
    when ``shares`` is None (the estimator keeps no per-stage rollouts)."""
    if shares is None:
        return None
    g = group_failures(shares, sampled, scene, problem)
    return Population(g, tuple(trajectory(*f) if f is not None else None for f in g.found))
