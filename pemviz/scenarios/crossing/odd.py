"""The crossing scenario over an operating design domain: each rollout's AEB trigger and deceleration (``brake_ttc_s``,
``brake_mps2``) drawn from distributions (``pemviz run --scenario crossing --param "brake_ttc_s~uniform(1.3,
1.5)"``), the batched scene braking by each rollout's own (:data:`pemviz.scenarios.crossing.scene.PER_ROLLOUT`); the
problem is the crossing's without its reference."""

from __future__ import annotations

from typing import Any

import numpy as np

from pemviz.core.odd import ODD
from pemviz.core.odd_rollouts import problem_over_odd
from pemviz.core.problems import Problem
from pemviz.scenarios.crossing.scene import PER_ROLLOUT, BatchedCrossing, CrossingParams


def crossing_odd_problem(config: Any, params: CrossingParams | None, odd: ODD) -> Problem:
    """The crossing problem over ``odd`` (parameters of :data:`~pemviz.scenarios.crossing.scene.PER_ROLLOUT`), the
    others at ``params`` (None: the defaults), the PEM ``config.perception.pem`` (None: the shipped one).

    Raises:
        ValueError: another parameter in the ODD."""
    from pemviz.scenarios.crossing.problem import crossing

    p = params or CrossingParams()
    others = [name for name in odd.names if name not in PER_ROLLOUT]
    if others:
        raise ValueError(f"the crossing scenario draws only {', '.join(PER_ROLLOUT)} per rollout, not {others}")
    names = odd.names

    def make(n: int, values: np.ndarray) -> BatchedCrossing:
        return BatchedCrossing(p, n, {name: values[:, j] for j, name in enumerate(names)})

    description = (
        f"emergency brake on a tracker, {p.n_pedestrians} pedestrian(s) stepping onto a crossing {p.crossing_m:g} m "
        f"ahead at {p.ego_speed_mps:g} m/s, the AEB's {odd.text()} per rollout; failure: a collision"
    )
    return problem_over_odd(crossing(config, p), make, odd, p.n_steps, description=description)
