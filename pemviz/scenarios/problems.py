"""The built-in scenarios' problems, each a :class:`pemviz.core.problems.Problem`: the named problems with a known exact
answer, the problem a run of a config estimates (:func:`problem_for`) and its alternative targets. Each problem lives
in its scenario's package; the cut-in's modules are imported by a cut-in run alone."""

from __future__ import annotations

import dataclasses
import functools
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from pemviz.core.estimate import Reference
from pemviz.core.problems import Problem
from pemviz.core.reweight import AlternativeTarget
from pemviz.pem import load_pem
from pemviz.pem.recipes import DEFAULT_PEM_NAME
from pemviz.scenarios.braking.problem import braking_problem
from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.scenarios.braking.truth_known import known_log_failure_probability
from pemviz.scenarios.crowd.problem import crowd_problem
from pemviz.scenarios.crowd.simulator import CrowdParams
from pemviz.scenarios.toy.problem import toy_problem
from pemviz.scenarios.toy.simulator import ToyParams

if TYPE_CHECKING:
    from pemviz.scenarios.braking.drawing import BrakingDrawing

# -- named problems -----------------------------------------------------------------------------------------------

PROBLEMS: dict[str, str] = {
    "toy": "toy braking (100, 50, 30, p = 0.9): exact 1e-21",
    "toy-1e-30": "toy braking (100, 39, 30, p = 0.999), braking window 10: exact 1e-30",
    "latched": "braking scenario with a latched brake: exact from the deterministic simulator",
    "main": "braking scenario: exact enumeration of detection sequences",
    "toy-1e-3": "toy braking (10, 5, 3, p = 0.9): exact 1e-3 (small; for CI)",
    "crowd": "toy braking toward 3 obstacles, each detected (p = 0.6) and mislocated (sd 1): exact 3.4e-5",
    "crowd-1e-12": "the crowd toy from 30 units, braking within 12, p = 0.7: exact 9.6e-13",
}
"""Named problems with a known exact failure probability (``pemviz validate``, ``pemviz tables``): name ->
description."""

TOY_PROBLEMS: dict[str, ToyParams] = {
    "toy": ToyParams(100, 50, 30, 0.9),
    "toy-1e-30": ToyParams(100, 39, 30, 0.999),
    "toy-1e-3": ToyParams(10, 5, 3, 0.9),
}
"""The toys of :data:`PROBLEMS` (:class:`~pemviz.scenarios.toy.ToyParams`: total, braking, safe, p_detect)."""

CROWD_PROBLEMS: dict[str, CrowdParams] = {
    "crowd": CrowdParams(),
    "crowd-1e-12": CrowdParams(total=30, braking=12, safe=3, p_detect=0.7),
}
"""The crowd toys of :data:`PROBLEMS` (several obstacles, mislocated:
:class:`~pemviz.scenarios.crowd.simulator.CrowdParams`)."""


@functools.cache
def build_problem(name: str, pem_path: str | None = None) -> Problem:
    """The :class:`Problem` named ``name`` in :data:`PROBLEMS` (built once per process and argument pair),
    ``pem_path`` the braking problems' PEM (None: the shipped default).

    Raises:
        ValueError: an unknown name (allowed: :data:`PROBLEMS`)."""
    if name in TOY_PROBLEMS:
        return toy_problem(TOY_PROBLEMS[name], name=name)
    if name in CROWD_PROBLEMS:
        return crowd_problem(CROWD_PROBLEMS[name], name=name)
    if name in ("latched", "main"):
        return braking_problem(load_pem(pem_path), BrakingParams(latched_brake=name == "latched"), sim="batched")
    raise ValueError(f"unknown problem {name!r}; use one of {', '.join(PROBLEMS)}")


def problem_for(config: Any) -> Problem:
    """The problem a run of ``config`` estimates: its scenario's registry factory called with the config
    (:attr:`pemviz.scenarios.registry.Scenario.factory`), which reads ``config.scenario_params`` and the PEM ``pem``
    (loaded on every call).

    Raises:
        pemviz.pem.network.PemFormatError, OSError: a PEM file that cannot be read.
        ValueError: parameters the scenario's dataclass refuses (the config checks them first)."""
    from pemviz.scenarios.registry import problem_for as registered

    return cast(Problem, registered(config))


def braking_run_problem(config: Any, params: BrakingParams | None = None) -> Problem:
    """The braking scenario's problem (the registry's factory of ``braking``) at ``params`` (None: the defaults), its
    crash gap ``config.margin`` where given, the PEM ``pem`` on the simulator ``config.sim`` (``config`` None:
    the shipped PEM on the batched twin), with the config's alternative targets (:func:`with_alternatives`)."""
    margin = None if config is None else config.margin
    scene = params
    if margin is not None:
        scene = dataclasses.replace(scene or BrakingParams(), crash_gap_m=float(margin))
    pem, sim = (None, "batched") if config is None else (config.value("pem"), config.sim)
    problem = braking_problem(load_pem(pem), scene, sim=sim)
    return with_alternatives(problem, config) if config is not None else problem


def cut_in_run_problem(config: Any, params: Any = None) -> Problem:
    """A cut-in scenario's problem (the factory of ``cut-in`` and ``cut-in-rare``) at ``params`` (None: the
    ``moderate`` setting), named after ``config.scenario``, with the PEMs ``pem`` and, for a rarity setting's own
    scene under the shipped PEMs, its plain Monte Carlo reference."""
    from pemviz.scenarios.cut_in.problem import cut_in_params, cut_in_problem
    from pemviz.scenarios.cut_in.scenario import MONTE_CARLO_REFERENCE, RARITY_SETTINGS, CutInParams

    scene = params if params is not None else cut_in_params("moderate")
    assert isinstance(scene, CutInParams)  # a cut-in scenario's own dataclass
    pem, name = (None, "cut-in") if config is None else (config.value("pem"), config.scenario)
    problem = cut_in_problem(load_pem(pem), scene, name=name)
    own = [name for name in RARITY_SETTINGS if scene == cut_in_params(name)]  # the references hold for these only
    if pem in (None, DEFAULT_PEM_NAME) and own and own[0] in MONTE_CARLO_REFERENCE:
        failures, n = MONTE_CARLO_REFERENCE[own[0]]
        problem = dataclasses.replace(problem, reference=Reference(failures, n, "plain Monte Carlo, shipped PEMs"))
    return with_alternatives(problem, config) if config is not None else problem


PEM_SHIFTS = (-1.0, -0.5, 0.5, 1.0)
"""The logit shifts (log-odds) ``--pem-uncertainty`` sweeps besides the ensemble: a camera that misses more often
(negative) or less often than the PEM says."""


def with_alternatives(problem: Problem, config: Any) -> Problem:
    """``problem`` with the alternative targets ``config`` asks for (:mod:`pemviz.core.reweight`): the PEM
    ensemble's members and :data:`PEM_SHIFTS` with ``pem_uncertainty``, the shift ``pem_shift``; each with its exact
    answer where known (:func:`pemviz.scenarios.braking.truth_known.known_log_failure_probability`).

    Raises:
        FileNotFoundError, pemviz.pem.network.PemFormatError: no ensemble for the PEM, or a damaged one."""
    from pemviz.core.reweight import ShiftedDetector, with_pem

    shifts = list(PEM_SHIFTS) if config.perception.pem_uncertainty else []
    if config.perception.pem_shift is not None and config.perception.pem_shift not in shifts:
        shifts.append(float(config.perception.pem_shift))
    if not shifts and not config.perception.pem_uncertainty:
        return problem
    target = problem.target
    # a braking problem draws with its BrakingDrawing (braking_problem)
    scene = cast("BrakingDrawing", problem.drawing).params if problem.name == "braking" else None

    def exact(logit_at_gap) -> float | None:
        return known_log_failure_probability(logit_at_gap, scene) if scene is not None else None

    alternatives, source = [], ""
    if config.perception.pem_uncertainty:
        from pemviz.pem.ensemble import ensemble_for, load_ensemble

        path = ensemble_for(config.perception.pem)
        members = load_ensemble(path)
        source = path.name
        for k, member in enumerate(members):
            alternatives.append(
                AlternativeTarget("member", f"member {k}", with_pem(target, member), exact(member.logit_at_gap))
            )
    pem = getattr(target, "pem", None)
    for d in sorted(shifts):
        known = None
        if pem is not None:
            known = exact(lambda g, d=d: np.asarray(pem.logit_at_gap(g), dtype=np.float64) + d)
        alternatives.append(AlternativeTarget("shift", f"{d:+g}", ShiftedDetector(target, d), known))
    return dataclasses.replace(problem, alternatives=tuple(alternatives), alternatives_source=source)
