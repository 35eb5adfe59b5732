"""The toy's problem: :func:`toy_problem`, the toy braking model as a :class:`pemviz.core.problems.Problem`
(:mod:`pemviz.scenarios.problems` builds it by name)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pemviz import stl
from pemviz.core.detectors import Detector
from pemviz.core.features import feature_replay
from pemviz.core.lockstep import branch_rollouts
from pemviz.core.problem_view import Thresholds
from pemviz.core.problems import Problem
from pemviz.scenarios.toy.simulator import (
    BatchedToy,
    ToyDetector,
    ToyParams,
    simulate_toy,
    toy_log_failure_probability,
)

if TYPE_CHECKING:
    from pemviz.scenarios.toy.tilt import ToyTilt


def toy_problem(params: ToyParams | None = None, name: str | None = None) -> Problem:
    """The toy as a :class:`Problem`: failure = classic robustness of
    ``G[0,T-1](d >= safe)`` below 0; the proposal sees h(s) = distance / total (as the authors'
    ``FFPolicy`` norm); curves are reported at the integer distances ``safe - 1 .. total``."""
    p = params or ToyParams()
    formula = stl.parse(f"G[0,{p.steps - 1}](d >= {p.safe})")

    def run(n: int, sampler: Detector, target: Detector, rng: np.random.Generator):
        return simulate_toy(p, n, sampler, target, rng)

    def branch(parents, parent, at, target: Detector, rng: np.random.Generator):
        return branch_rollouts(lambda m: BatchedToy(p, m), parents, parent, at, target, rng)

    def tilt() -> ToyTilt:
        from pemviz.scenarios.toy.tilt import ToyTilt

        return ToyTilt(p)

    p_label = f"{p.p_detect:g}" if not callable(p.p_detect) else "p(d)"
    return Problem(
        name or f"toy({p.total},{p.braking},{p.safe},{p_label})",
        run,
        ToyDetector(p),
        formula,
        signals={"d": "gap_m"},
        units={"d": "units"},
        thresholds=Thresholds(float(p.safe), float(p.braking), "units", "failure below", "braking within"),
        signal_ranges={"d": (0.0, float(p.total))},
        h_scale=float(p.total),
        curve_grid=np.arange(max(p.safe - 1, 0), p.total + 1, dtype=np.float64),
        window=float(p.braking) + 0.5,
        n_steps=p.steps,
        exact_log_p=toy_log_failure_probability(p),
        branch=branch,
        tilt=tilt,
        features=feature_replay(lambda n: BatchedToy(p, n)),
        array_rqmc=True,  # its state is the row: ranked by it, the coupling keeps the estimate's mean
        description=(
            f"toy braking: {p.total} steps from the obstacle, braking possible within {p.braking}, failure "
            f"closer than {p.safe}; detection probability {p_label}"
        ),
    )
