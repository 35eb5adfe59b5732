"""The braking scenario over an operating design domain: each rollout's start gap and ego speed (``gap0_m``,
``ego_speed0_mps``) drawn from distributions (``pemviz run --param gap0_m~uniform(10, 14)``), the batched twin
starting each rollout there (``starts``); the problem is the braking one without the exact answer and the
look-ahead."""

from __future__ import annotations

from typing import Any

import numpy as np

from pemviz.core.odd import ODD
from pemviz.core.odd_rollouts import problem_over_odd
from pemviz.core.problems import Problem
from pemviz.scenarios.braking.batched import BatchedBraking
from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.settings import setting_of


def braking_odd_problem(config: Any, params: BrakingParams | None, odd: ODD) -> Problem:
    """The braking problem over ``odd`` (parameters ``gap0_m`` and / or ``ego_speed0_mps``), the others at ``params``
    (None: the defaults), the PEM ``config.perception.pem`` (None: the shipped one).

    Raises:
        ValueError: another parameter in the ODD, or the highway-env back-end (``config.sim``), which starts every
            rollout alike."""
    from pemviz.pem import load_pem
    from pemviz.scenarios.braking.problem import braking_problem

    p = params or BrakingParams()
    others = [name for name in odd.names if name not in ("gap0_m", "ego_speed0_mps")]
    if others:
        raise ValueError(f"the braking scenario draws only gap0_m and ego_speed0_mps per rollout, not {others}")
    if config is not None and getattr(config, "sim", "batched") != "batched":
        raise ValueError(
            "--param NAME~DIST: an operating design domain runs on the batched twin only; use --sim batched"
        )
    names = odd.names

    def make(n: int, values: np.ndarray) -> BatchedBraking:
        return BatchedBraking(p, n, starts={name: values[:, j] for j, name in enumerate(names)})

    base = braking_problem(load_pem(setting_of(config, "pem", None)), p, sim="batched")
    description = (
        f"automated braking behind a lead car, its start drawn per rollout ({odd.text()}), the PEM as "
        f"the camera's detector; failure: the gap drops below {p.crash_gap_m:g} m"
    )
    return problem_over_odd(base, make, odd, p.n_steps, description=description)
