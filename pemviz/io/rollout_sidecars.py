"""The sidecars (:class:`pemviz.io.rollout_format.RolloutMeta`) of a scene's rollout files: the braking scenario's
(:func:`braking_meta`) and any other problem's (:func:`problem_meta`); :func:`pemviz.io.run_rollouts.run_meta`
chooses."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from pemviz.io.rollout_format import RolloutMeta
from pemviz.scenarios.braking.problem import braking_formula
from pemviz.scenarios.braking.simulator import BRAKING_SIGNAL_RANGES, BRAKING_SIGNALS, OBSERVATION_NAMES, BrakingParams

if TYPE_CHECKING:
    from pemviz.core.problems import Problem

SALIENT_UNITS = {
    "alpha": "rad",
    "rot_y": "rad",
    "dim_w": "m",
    "dim_l": "m",
    "dim_h": "m",
    "loc_x": "m",
    "loc_y": "m",
    "loc_z": "m",
}

BRAKING_UNITS = {
    "gap_m": "m",
    "ego_speed_mps": "m/s",
    "lead_speed_mps": "m/s",
    "log_p": "nats",
    "log_q": "nats",
    **{f"salient_{k}": u for k, u in SALIENT_UNITS.items()},
}


def braking_meta(
    formula: str | None = None,
    *,
    pem: str | None = None,
    proposal: str | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> RolloutMeta:
    """The sidecar of braking-scenario rollouts (Innes & Ramamoorthy 2022): dt 0.05 s, signals d / v / vl, units.

    ``formula`` defaults to ``G[0,T-1](d >= 2)`` of :func:`pemviz.scenarios.braking.problem.braking_formula`."""
    p = BrakingParams()
    return RolloutMeta(
        formula=formula or str(braking_formula(p)),
        dt_s=p.dt_s,
        signals=dict(BRAKING_SIGNALS),
        signal_ranges=dict(BRAKING_SIGNAL_RANGES),
        observation_columns=tuple(OBSERVATION_NAMES),
        units=dict(BRAKING_UNITS),
        pem=pem,
        proposal=proposal,
        window_m=p.braking_distance_m,
        provenance=dict(provenance or {}),
    )


def problem_meta(
    problem: Problem,
    formula: str | None = None,
    *,
    pem: str | None = None,
    proposal: str | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> RolloutMeta:
    """The sidecar of a problem's rollouts: its formula, signals, signal ranges, units and step (``dt_s = 1`` with
    ``dt_s_unknown`` in the provenance where the problem knows none: only a failure's impact speed reads it); the
    writer fills in objects and errors."""
    provenance = dict(provenance or {})
    if problem.dt_s is None:
        provenance["dt_s_unknown"] = f"{problem.name} gave no step: dt_s = 1 stands for one step"
    units = {problem.signals[k]: u for k, u in problem.units.items() if k in problem.signals}
    extra: dict[str, Any] = {"window_m": float(problem.window)} if math.isfinite(problem.window) else {}
    dt_s = 1.0 if problem.dt_s is None else float(problem.dt_s)
    odd = getattr(problem, "odd", None)
    if odd is not None:
        extra["odd_parameters"] = tuple(odd.names)
    return RolloutMeta(
        formula=formula or str(problem.formula),
        dt_s=dt_s,
        signals=dict(problem.signals),
        signal_ranges=dict(problem.signal_ranges),
        units={**units, "log_p": "nats", "log_q": "nats"},
        pem=pem,
        proposal=proposal,
        provenance=provenance,
        **extra,
    )
