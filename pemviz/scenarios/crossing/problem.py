"""The crossing scenario's problem: :func:`crossing_problem` (the scene of :mod:`pemviz.scenarios.crossing.scene` as a
:class:`pemviz.core.problems.Problem`, with the shipped PEMs as its detector) and the registry's factory
:func:`crossing`, which carries the plain Monte Carlo reference :data:`MONTE_CARLO_REFERENCE` where it holds."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from pemviz import stl
from pemviz.core.estimate import Reference
from pemviz.core.problems import Problem, rollout_functions
from pemviz.scenarios.crossing.scene import OBJECT_NAMES, BatchedCrossing, CrossingParams, pedestrian_ahead_rows
from pemviz.settings import setting_of
from pemviz.stack.detector import NOISE_NAMES, camera_detector

CROSSING_FORMULA = "G(clearance >= 0)"
"""No collision with a pedestrian: the signed separation of the boxes (m) stays >= 0; failure = robustness < 0."""

CROSSING_WINDOW_M = 35.0
"""The proposal replaces the PEMs for pedestrians nearer than this (m): at 12 m/s the AEB acts within about 1.3 s
(16 m); a pedestrian further away is seen in time whatever the camera does at that step."""

MONTE_CARLO_REFERENCE: tuple[int, int] = (3_575, 12_000_000)
"""(failures, rollouts) of plain Monte Carlo of the crossing at its defaults under the shipped PEMs: p = 2.98e-4
[2.88e-4, 3.08e-4] (``pemviz run --scenario crossing --method mc --n 2000000 --seed S --no-record``, S = 1..6;
``docs/realistic-stack.md``)."""


def crossing_problem(
    params: CrossingParams | None = None, detect: Any = None, noise: Any = None, name: str = "crossing"
) -> Problem:
    """The crossing scene as a :class:`Problem` on its batched simulator: each pedestrian detected by the detection
    PEM ``detect`` and mislocated by the noise PEM ``noise`` (None: the shipped ones;
    :func:`pemviz.stack.detector.camera_detector`); failure: :data:`CROSSING_FORMULA` violated (a collision)."""
    p = params or CrossingParams()

    def make(n: int) -> BatchedCrossing:
        return BatchedCrossing(p, n)

    run, stream, resume = rollout_functions(make, p.n_steps)
    detector = camera_detector(OBJECT_NAMES, detect, noise)
    return Problem(
        name,
        run,
        detector,
        stl.parse(CROSSING_FORMULA),
        signals={"clearance": "clearance_m"},
        units={"clearance": "m"},
        signal_ranges={"clearance": (-3.0, 100.0)},
        h_scale=40.0,
        curve_grid=np.arange(0.0, CROSSING_WINDOW_M + 10.5, 0.5),
        window=CROSSING_WINDOW_M,
        stream=stream,
        branch=resume,
        curve_rows=lambda grid: pedestrian_ahead_rows(p, grid),
        dt_s=p.dt_s,
        n_objects=p.n_pedestrians,
        n_steps=p.n_steps,
        object_labels=tuple(f"pedestrian {m}" for m in range(p.n_pedestrians)),
        objects_xy=("loc_x", "loc_z"),
        noise_xy=(NOISE_NAMES.index("lateral_error_m"), NOISE_NAMES.index("range_error_m")),
        description=(
            f"emergency brake on a tracker, {p.n_pedestrians} pedestrian(s) stepping onto a crossing "
            f"{p.crossing_m:g} m ahead at {p.ego_speed_mps:g} m/s; failure: a collision"
        ),
    )


def crossing(config: Any = None, params: CrossingParams | None = None) -> Problem:
    """The registry's factory (``pemviz run --scenario crossing``): :func:`crossing_problem` with the config's PEM
    (None: the shipped one), carrying :data:`MONTE_CARLO_REFERENCE` as its reference when it runs the shipped PEMs
    at the default parameters, under which the reference was drawn."""
    from pemviz.pem import load_pem
    from pemviz.pem.recipes import DEFAULT_PEM_NAME

    pem_name = setting_of(config, "pem", None)
    p = params if params is not None else CrossingParams()
    problem = crossing_problem(p, load_pem(pem_name))
    failures, n = MONTE_CARLO_REFERENCE
    if n and pem_name in (None, DEFAULT_PEM_NAME) and p == CrossingParams():
        problem = dataclasses.replace(problem, reference=Reference(failures, n, "plain Monte Carlo, shipped PEMs"))
    return problem
