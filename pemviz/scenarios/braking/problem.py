"""The braking scenario's problem: :func:`braking_problem` (the scenario as a :class:`pemviz.core.problems.Problem`
on its batched twin or on highway-env vehicles) and its safety formula :func:`braking_formula`
(:mod:`pemviz.scenarios.problems` builds the problem by name and for a run's config)."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator

import numpy as np

from pemviz import stl
from pemviz.core.detectors import Detector, GapModel, PEMDetector
from pemviz.core.lockstep import DEFAULT_CHUNK_SIZE, branch, branch_rollouts, simulate
from pemviz.core.problem_view import Thresholds
from pemviz.core.problems import Problem
from pemviz.core.rollouts import RolloutBatch
from pemviz.core.severity import SeverityScale
from pemviz.scenarios.braking.batched import BatchedBraking, iter_batched, replay, simulate_batched
from pemviz.scenarios.braking.drawing import BrakingDrawing
from pemviz.scenarios.braking.lookahead import LOOK_AHEAD_ROLLOUT_S, braking_look_ahead
from pemviz.scenarios.braking.simulator import (
    BRAKING_SIGNAL_RANGES,
    BRAKING_SIGNALS,
    BRAKING_UNITS,
    OBSERVATION_NAMES,
    BrakingParams,
    BrakingScenario,
)
from pemviz.scenarios.braking.truth_known import known_log_failure_probability
from pemviz.settings import SIMULATORS


def braking_formula(params: BrakingParams | None = None) -> stl.Formula:
    """``G[0,T-1](d >= 2)``: the gap never drops below the crash gap (Innes & Ramamoorthy (2022))."""
    p = params or BrakingParams()
    return stl.parse(f"G[0,{p.n_steps - 1}](d >= {p.crash_gap_m:g})")


BRAKING_SEVERITY_LEVELS_M = (1.5, 1.0, 0.5, 0.0)
"""Gaps (metres) of the braking scenario's exceedance curve below its crash gap, down to 0 m (contact is a gap at or
below ``BrakingParams.contact_gap_m``, 0.7 m: the severity scale's ``contact``)."""


def never_detected_min_gap_m(params: BrakingParams) -> float:
    """The smallest gap (metres) of the rollout whose detector never sees the lead (every step a miss): 0.08 m with
    the default constants, the ego stopped by the scene at its contact gap (0.7 m) and carried on by its last step."""
    obs = replay(params, np.zeros((1, params.n_steps), dtype=bool))
    return float(obs[0, :, OBSERVATION_NAMES.index("gap_m")].min())


def verdict_cap(params: BrakingParams) -> tuple[str, str] | None:
    """("doubtful", why) when the crash gap lies below :func:`never_detected_min_gap_m` (e.g. contact, 0 m), else
    None: there a failure needs detections that bring the ego to the contact gap at full speed, which the proposal
    draws before the exact look-ahead (:mod:`pemviz.scenarios.braking.lookahead`) takes over, and its weights can
    look reliable while the interval misses (docs/validation.md)."""
    floor = never_detected_min_gap_m(params)
    if params.crash_gap_m >= floor:
        return None
    return "doubtful", (
        f"a gap below {floor:.2f} m (where the ego ends when it never detects the lead) needs "
        "detections at the right steps before the enumerated ones, which the proposal draws only in "
        "part: 2 of 10 runs whose weights looked reliable missed the exact answer"
    )


def braking_problem(pem: GapModel, params: BrakingParams | None = None, sim: str = "batched") -> Problem:
    """The automated-braking scenario of Innes & Ramamoorthy (2022) with the given PEM as target detector.

    Raises:
        ValueError: for an unknown ``sim`` (allowed: :data:`SIMULATORS`)."""
    p = params or BrakingParams()
    if sim not in SIMULATORS:
        raise ValueError(f"unknown simulator {sim!r}; use one of {', '.join(SIMULATORS)}")

    def run(n: int, sampler: Detector, target: Detector, rng: np.random.Generator) -> RolloutBatch:
        if sim == "batched":
            return simulate_batched(p, n, sampler, target, rng)
        return simulate(lambda: BrakingScenario(p), n, sampler, target, rng, p.n_steps)

    def stream(
        n: int, sampler: Detector, target: Detector, rng: np.random.Generator, chunk_size: int = DEFAULT_CHUNK_SIZE
    ) -> Iterator[RolloutBatch]:
        return iter_batched(p, n, sampler, target, rng, chunk_size=chunk_size)

    def resume(
        parents: RolloutBatch, parent: np.ndarray, at: np.ndarray, target: Detector, rng: np.random.Generator
    ) -> RolloutBatch:
        if sim == "batched":
            return branch_rollouts(lambda m: BatchedBraking(p, m), parents, parent, at, target, rng)
        return branch(lambda: BrakingScenario(p), parents, parent, at, target, rng)

    scale = SeverityScale(
        "d",
        "gap",
        "m",
        tuple(x for x in BRAKING_SEVERITY_LEVELS_M if x < p.crash_gap_m),
        margin=p.crash_gap_m,
        target_flag="margin",
        contact=p.contact_gap_m,
    )
    exact = {}
    if hasattr(pem, "logit_at_gap"):
        known = {
            x: known_log_failure_probability(pem.logit_at_gap, dataclasses.replace(p, crash_gap_m=x))
            for x in scale.levels
        }
        exact = {x: v for x, v in known.items() if v is not None}
    look_ahead = None
    if hasattr(pem, "logit_at_gap") and p.crash_gap_m < never_detected_min_gap_m(p):
        look_ahead = braking_look_ahead(p, pem.logit_at_gap)
    return Problem(
        "braking",
        run,
        PEMDetector(pem),
        braking_formula(p),
        signals=dict(BRAKING_SIGNALS),
        verdict_cap=verdict_cap(p),
        look_ahead=look_ahead,
        look_ahead_s=LOOK_AHEAD_ROLLOUT_S if look_ahead is not None else 0.0,
        signal_ranges=dict(BRAKING_SIGNAL_RANGES),
        units=dict(BRAKING_UNITS),
        window=p.braking_distance_m,
        decided_below=p.crash_gap_m,
        severity=scale,
        severity_exact=exact,
        stream=stream if sim == "batched" else None,
        branch=resume,
        exact_log_p=known_log_failure_probability(pem.logit_at_gap, p) if hasattr(pem, "logit_at_gap") else None,
        thresholds=Thresholds(p.crash_gap_m, p.braking_distance_m, "m", "crash gap", "braking distance"),
        drawing=BrakingDrawing(p),
        array_rqmc=True,  # its intervals hold coupled: 199 of 200 seeds (Validation page)
        n_steps=p.n_steps,
        dt_s=p.dt_s,
        description=(
            f"automated braking behind a lead car {p.gap0_m:.1f} m ahead, the PEM as the camera's detector, "
            f"{p.n_steps} steps of {p.dt_s:g} s{', latched brake' if p.latched_brake else ''}; failure: "
            f"the gap drops below {p.crash_gap_m:g} m"
        ),
    )
