"""The crowd toy's problem: :func:`crowd_problem`, the crowd toy as a :class:`pemviz.core.problems.Problem`
(:mod:`pemviz.scenarios.problems` builds it by name)."""

from __future__ import annotations

import numpy as np

from pemviz import stl
from pemviz.core.problem_view import Thresholds
from pemviz.core.problems import Problem, rollout_functions
from pemviz.scenarios.crowd.simulator import BatchedCrowd, CrowdDetector, CrowdParams, crowd_log_failure_probability


def crowd_problem(params: CrowdParams | None = None, name: str | None = None) -> Problem:
    """The crowd toy (:mod:`pemviz.scenarios.crowd`) as a :class:`Problem`: M obstacles, each detected and mislocated
    per step; failure = classic robustness of ``G[0,T-1](d >= safe)`` below 0 on the nearest distance; the proposal
    reads each obstacle's row (distance first, scaled by ``total``) inside the window where a detection can stop the
    car; the exact answer is :func:`pemviz.scenarios.crowd.simulator.crowd_log_failure_probability`."""
    p = params or CrowdParams()

    def make(n: int) -> BatchedCrowd:
        return BatchedCrowd(p, n)

    run, stream, resume = rollout_functions(make, p.steps)

    far = p.total + max(p.offsets)
    return Problem(
        name or f"crowd({p.total},{p.braking},{p.safe},{p.p_detect:g},{len(p.offsets)} obstacles,sd {p.noise_sd:g})",
        run,
        CrowdDetector(p),
        stl.parse(f"G[0,{p.steps - 1}](d >= {p.safe})"),
        signals={"d": "gap_m"},
        units={"d": "units"},
        signal_ranges={"d": (0.0, float(p.total))},
        h_scale=float(p.total),
        curve_grid=np.arange(0.0, far + 1.0),
        window=p.window,
        stream=stream,
        branch=resume,
        exact_log_p=crowd_log_failure_probability(p),
        n_objects=len(p.offsets),
        n_steps=p.steps,
        thresholds=Thresholds(float(p.safe), float(p.braking), "units", "failure below", "braking within"),
        description=(
            f"toy braking toward {len(p.offsets)} obstacles, each detected with probability {p.p_detect:g} "
            f"and its distance measured with an N(0, {p.noise_sd:g}^2) error; braking when one is measured "
            f"within {p.braking}, failure closer than {p.safe} to the nearest"
        ),
    )
