"""The built-in scenarios' problems: each scenario as a :class:`pemviz.core.problems.Problem`.

The braking scenario of Innes & Ramamoorthy (2022) (:func:`braking_problem`, its safety formula
:func:`braking_formula`), the toy (:func:`toy_problem`), the crowd toy (:func:`crowd_problem`) and the cut-in
(:func:`cut_in_problem` at a named setting :func:`cut_in_params`); the named problems with a known exact answer
(:data:`PROBLEMS`, :data:`TOY_PROBLEMS`, :data:`CROWD_PROBLEMS`, built by :func:`build_problem`), the problem a run of
a config estimates (:func:`problem_for`) and its alternative targets (:func:`with_alternatives`, :data:`PEM_SHIFTS`).
The scene-neutral :class:`~pemviz.core.problems.Problem` and :func:`~pemviz.core.problems.rollout_functions` are in
:mod:`pemviz.core.problems`.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import TYPE_CHECKING, Any

import numpy as np

from pemviz import stl
from pemviz.core.detectors import Detector
from pemviz.core.estimate import Reference
from pemviz.core.problem_view import Thresholds
from pemviz.core.problems import Problem, rollout_functions
from pemviz.core.reweight import AlternativeTarget
from pemviz.core.severity import SeverityScale
from pemviz.pem import DEFAULT_PEM_NAME, load_pem
from pemviz.scenarios.braking.problem import (  # noqa: F401 (re-exported: importable from here as before)
    BRAKING_SEVERITY_LEVELS_M as BRAKING_SEVERITY_LEVELS_M,
    braking_formula as braking_formula,
    braking_problem,
)
from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.scenarios.braking.truth import known_log_failure_probability
from pemviz.scenarios.crowd import BatchedCrowd, CrowdDetector, CrowdParams, crowd_log_failure_probability
from pemviz.scenarios.toy import ToyDetector, ToyParams, branch_toy, simulate_toy, toy_log_failure_probability

if TYPE_CHECKING:
    from pemviz.scenarios.cut_in import CutInParams


def toy_problem(params: ToyParams | None = None, name: str | None = None) -> Problem:
    """The toy as a :class:`Problem`: failure = classic robustness of
    ``G[0,T-1](d >= safe)`` below 0; the proposal sees h(s) = distance / total (as the authors'
    ``FFPolicy`` norm); curves are reported at the integer distances ``safe - 1 .. total``.
    """
    p = params or ToyParams()
    formula = stl.parse(f"G[0,{p.steps - 1}](d >= {p.safe})")

    def run(n: int, sampler: Detector, target: Detector, rng: np.random.Generator):
        return simulate_toy(p, n, sampler, target, rng)

    def branch(parents, parent, at, target: Detector, rng: np.random.Generator):
        return branch_toy(p, parents, parent, at, target, rng)

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
        description=(f"toy braking: {p.total} steps from the obstacle, braking possible within {p.braking}, failure "
                     f"closer than {p.safe}; detection probability {p_label}"),
    )


def crowd_problem(params: CrowdParams | None = None, name: str | None = None) -> Problem:
    """The crowd toy (:mod:`pemviz.scenarios.crowd`) as a :class:`Problem`: M obstacles, each detected and mislocated
    per step; failure = classic robustness of ``G[0,T-1](d >= safe)`` below 0 on the nearest distance; the proposal
    reads each obstacle's row (distance first, scaled by ``total``) inside the window where a detection can stop the
    car; the exact answer is :func:`pemviz.scenarios.crowd.crowd_log_failure_probability`."""
    p = params or CrowdParams()

    def make(n: int) -> BatchedCrowd:
        return BatchedCrowd(p, n)

    run, stream, resume = rollout_functions(make, p.steps)

    far = p.total + max(p.offsets)
    return Problem(
        name or f"crowd({p.total},{p.braking},{p.safe},{p.p_detect:g},{len(p.offsets)} obstacles,sd {p.noise_sd:g})",
        run, CrowdDetector(p), stl.parse(f"G[0,{p.steps - 1}](d >= {p.safe})"), signals={"d": "gap_m"},
        units={"d": "units"}, signal_ranges={"d": (0.0, float(p.total))}, h_scale=float(p.total),
        curve_grid=np.arange(0.0, far + 1.0), window=p.window, stream=stream, branch=resume,
        exact_log_p=crowd_log_failure_probability(p), n_objects=len(p.offsets), n_steps=p.steps,
        thresholds=Thresholds(float(p.safe), float(p.braking), "units", "failure below", "braking within"),
        description=(f"toy braking toward {len(p.offsets)} obstacles, each detected with probability {p.p_detect:g} "
                     f"and its distance measured with an N(0, {p.noise_sd:g}^2) error; braking when one is measured "
                     f"within {p.braking}, failure closer than {p.safe} to the nearest"),
    )  # fmt: skip


CUT_IN_WINDOW_M = 40.0
"""The cut-in problem's window on an object's range (metres): the proposal replaces the PEMs for the cars nearer
than this. The ACC of the cut-in scenario reacts within about 2 s at 25 m/s, so a car further away can be seen in
time whatever the camera does; outside the window, a rollout's objects are drawn from the PEMs themselves."""

CUT_IN_SIGNALS = {"margin": "safe_margin_m", "grace": "cut_in_recent", "clearance": "clearance_m"}
"""STL signal name -> cut-in rollout observation column (:data:`pemviz.scenarios.cut_in.OBSERVATION_NAMES`)."""

CUT_IN_FORMULA = "G((margin + 1000 * grace >= 0) & (clearance >= 0))"
"""The cut-in failure over :data:`CUT_IN_SIGNALS`: R_G1 of Maierhofer et al. 2020, waived after a cut-in, and no
collision; robustness in metres. Under classic semantics it is :data:`pemviz.scenarios.cut_in.FAILURE_FORMULA`
(``G a & G b`` = ``G (a & b)``), written as one safety formula ``G(state predicate)``, whose first violation stops the
importance weights and which adaptive multilevel splitting needs."""


CUT_IN_SEVERITY_LEVELS_M = (2.0, 1.0, 0.0)
"""Clearances (metres, bumper to bumper) of the cut-in's exceedance curve: failures that also come this close; 0 is a
collision."""


def cut_in_params(setting: str) -> CutInParams:
    """The cut-in scenario at a named rarity setting (:data:`pemviz.scenarios.cut_in.RARITY_SETTINGS`: ``moderate``,
    ``rare``).

    Raises:
        ValueError: an unknown setting.
    """
    from pemviz.scenarios.cut_in import RARITY_SETTINGS, CutInParams  # the cut-in's modules: for its runs only

    if setting not in RARITY_SETTINGS:
        raise ValueError(f"unknown cut-in setting {setting!r}; use one of {', '.join(RARITY_SETTINGS)}")
    return CutInParams(**RARITY_SETTINGS[setting])


def cut_in_problem(pem: object, params: CutInParams | None = None, noise: object | None = None,
                   name: str = "cut-in") -> Problem:  # fmt: skip
    """The cut-in scenario (:mod:`pemviz.scenarios.cut_in`) as a :class:`Problem` on its batched twin
    (:class:`~pemviz.scenarios.cut_in_batched.BatchedCutIn`): M cars, each detected by ``pem`` from its 11 KITTI
    salient variables and, when detected, mislocated in range and laterally by the noise PEM ``noise``
    (:class:`pemviz.pem.perception.SalientDetector`); a car the camera cannot see is never detected. The failure is
    a negative classic robustness of :data:`CUT_IN_FORMULA` (Innes & Ramamoorthy, "Adaptive Splitting of Reusable
    Temporal Monitors for Rare Traffic Violations", arXiv 2405.15771: a cut-in, the rule R_G1). The proposal reads
    each car's object row (its range first, scaled by 50 m) within :data:`CUT_IN_WINDOW_M`. No exact answer is
    known; plain Monte Carlo of the same twin gives the reference (``benchmarks/cut_in_mc.py``).

    Args:
        pem: the detection PEM (``pemviz.pem.load_pem()``).
        params: the scenario (default: the ``moderate`` setting, about 9e-5).
        noise: the noise PEM (default: the shipped ``hetero-t``).
    """
    from pemviz.pem.perception import SalientDetector
    from pemviz.pem.store import load_noise_pem
    from pemviz.scenarios.cut_in import NOISE_NAMES, OBJECT_NAMES, SALIENT_COLUMNS
    from pemviz.scenarios.cut_in_batched import BatchedCutIn, cached_trajectory
    from pemviz.scenarios.cut_in_drawing import CutInDrawing

    p = params if params is not None else cut_in_params("moderate")
    cached_trajectory(p)
    detector = SalientDetector(pem, SALIENT_COLUMNS, load_noise_pem("hetero-t") if noise is None else noise,
                               NOISE_NAMES, OBJECT_NAMES.index("visible"))  # fmt: skip

    def make(n: int) -> BatchedCutIn:
        return BatchedCutIn(p, n)

    ahead = _car_ahead_row(make(1), p)

    def curve_rows(grid: np.ndarray) -> np.ndarray:
        """The cut-in car straight ahead in the ego's lane, unoccluded, at each range of ``grid`` (metres)."""
        rows = np.tile(ahead, (np.size(grid), 1))
        scale = np.asarray(grid, dtype=np.float64) / ahead[0]
        for column in ("loc_x", "loc_z", "range_m"):
            rows[:, OBJECT_NAMES.index(column)] *= scale
        return rows

    run, stream, resume = rollout_functions(make, p.n_steps)

    return Problem(
        name, run, detector, stl.parse(CUT_IN_FORMULA), signals=dict(CUT_IN_SIGNALS),
        units={"margin": "m", "grace": "", "clearance": "m"},
        signal_ranges={"margin": (-60.0, 200.0), "grace": (0.0, 1.0), "clearance": (-10.0, 200.0)},
        severity=SeverityScale("clearance", "clearance", "m", CUT_IN_SEVERITY_LEVELS_M),
        h_scale=50.0, curve_grid=np.arange(0.0, CUT_IN_WINDOW_M + 10.5, 0.5), window=CUT_IN_WINDOW_M,
        stream=stream, branch=resume, curve_rows=curve_rows, objects_xy=("loc_x", "loc_z"), dt_s=p.dt_s,
        n_objects=p.n_objects, n_steps=p.n_steps, drawing=CutInDrawing(p),
        noise_xy=(NOISE_NAMES.index("lateral_error_m"), NOISE_NAMES.index("range_error_m")),
        description=(f"ACC on a tracker, {p.n_objects} cars on a 3-lane highway, one cutting in {p.cut_in_gap_m:g} m "
                     f"ahead at {p.cut_in_speed_mps:g} m/s; failure: a collision or the safe distance of R_G1"),
    )  # fmt: skip


def _car_ahead_row(sim: object, p: CutInParams) -> np.ndarray:
    """Object 0's row [G] once it has cut in (every car detected exactly): the cut-in car ahead in the ego's lane."""
    from pemviz.scenarios.cut_in import OBJECT_NAMES

    lane = OBJECT_NAMES.index("in_ego_lane")
    for _ in range(p.n_steps):
        row = sim.objects()[0, 0]
        if row[lane] > 0.5 and sim.t > p.cut_in_step + round(p.cut_in_lateral_time_s / p.dt_s):
            break
        sim.step(np.ones((1, p.n_objects), bool), np.zeros((1, p.n_objects, 2)))
    return np.array(row, dtype=np.float64)


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
"""The crowd toys of :data:`PROBLEMS` (several obstacles, mislocated: :class:`~pemviz.scenarios.crowd.CrowdParams`)."""


@functools.cache
def build_problem(name: str, pem_path: str | None = None) -> Problem:
    """The :class:`Problem` named ``name`` in :data:`PROBLEMS` (built once per process and argument pair).

    ``pem_path``: the PEM of the braking problems (``latched``, ``main``; None: the shipped default), run on the
    ``batched`` simulator.

    Raises:
        ValueError: an unknown name (allowed: :data:`PROBLEMS`).
    """
    if name in TOY_PROBLEMS:
        return toy_problem(TOY_PROBLEMS[name], name=name)
    if name in CROWD_PROBLEMS:
        return crowd_problem(CROWD_PROBLEMS[name], name=name)
    if name in ("latched", "main"):
        return braking_problem(load_pem(pem_path), BrakingParams(latched_brake=name == "latched"), sim="batched")
    raise ValueError(f"unknown problem {name!r}; use one of {', '.join(PROBLEMS)}")


def problem_for(config: Any) -> Problem:
    """The problem a run of ``config`` estimates: the scenario ``config.scenario`` (:data:`pemviz.config.SCENARIOS`)
    with its parameters ``config.scenario_params`` (:mod:`pemviz.scenarios.parameters`; the braking scenario's crash
    gap also ``config.margin``) and the PEM ``config.pem`` (None: the shipped one); the braking scenario on the
    simulator ``config.sim``. Loads the PEM on every call (a changed file is read again). A cut-in setting with a plain
    Monte Carlo reference (:data:`pemviz.scenarios.cut_in.MONTE_CARLO_REFERENCE`) carries it as its
    :attr:`Problem.reference` only when it runs the shipped PEMs at the setting's own parameters, under which the
    reference was drawn; the braking scenario's exact answer is known for its default parameters (or another crash
    gap, or the latched brake) only (:func:`pemviz.scenarios.braking.truth.known_log_failure_probability`).

    Raises:
        pemviz.pem.network.PemFormatError, OSError: a PEM file that cannot be read.
        ValueError: parameters the scenario's dataclass refuses (the config checks them first).
    """
    overrides = dict(config.scenario_params)
    if config.scenario == "braking":
        if config.margin is not None:
            overrides["crash_gap_m"] = float(config.margin)
        params = BrakingParams(**overrides) if overrides else None
        return with_alternatives(braking_problem(load_pem(config.pem), params, sim=config.sim), config)
    from pemviz.scenarios.cut_in import MONTE_CARLO_REFERENCE
    from pemviz.scenarios.parameters import CUT_IN_SETTINGS, apply_parameters

    setting = CUT_IN_SETTINGS[config.scenario]
    params = apply_parameters(config.scenario, overrides)
    problem = cut_in_problem(load_pem(config.pem), params, name=config.scenario)
    own = params == cut_in_params(setting)  # the reference holds for the setting's own scene only
    if config.pem in (None, DEFAULT_PEM_NAME) and setting in MONTE_CARLO_REFERENCE and own:
        failures, n = MONTE_CARLO_REFERENCE[setting]
        problem = dataclasses.replace(problem, reference=Reference(failures, n, "plain Monte Carlo, shipped PEMs"))
    return with_alternatives(problem, config)


PEM_SHIFTS = (-1.0, -0.5, 0.5, 1.0)
"""The logit shifts (log-odds) ``--pem-uncertainty`` sweeps besides the ensemble: a camera that misses more often
(negative) or less often than the PEM says."""


def with_alternatives(problem: Problem, config: Any) -> Problem:
    """``problem`` with the alternative targets ``config`` asks for (:mod:`pemviz.core.reweight`): with
    ``pem_uncertainty`` every member of the PEM's ensemble (:func:`pemviz.pem.ensemble.ensemble_for`) and the shifts
    :data:`PEM_SHIFTS`, and ``pem_shift`` D; each with its exact answer where the truth knows it (the braking
    scenario's PEM fingerprints, :func:`pemviz.scenarios.braking.truth.known_log_failure_probability`).

    Raises:
        FileNotFoundError, pemviz.pem.network.PemFormatError: no ensemble for the PEM, or a damaged one.
    """
    from pemviz.core.reweight import ShiftedDetector, with_pem

    shifts = list(PEM_SHIFTS) if config.pem_uncertainty else []
    if config.pem_shift is not None and config.pem_shift not in shifts:
        shifts.append(float(config.pem_shift))
    if not shifts and not config.pem_uncertainty:
        return problem
    target = problem.target
    scene = problem.drawing.params if problem.name == "braking" else None

    def exact(logit_at_gap) -> float | None:
        return known_log_failure_probability(logit_at_gap, scene) if scene is not None else None

    alternatives, source = [], ""
    if config.pem_uncertainty:
        from pemviz.pem.ensemble import ensemble_for, load_ensemble

        path = ensemble_for(config.pem)
        members = load_ensemble(path)
        source = path.name
        for k, member in enumerate(members):
            alternatives.append(AlternativeTarget("member", f"member {k}", with_pem(target, member),
                                                  exact(member.logit_at_gap)))  # fmt: skip
    pem = getattr(target, "pem", None)
    for d in sorted(shifts):
        known = None
        if pem is not None:
            known = exact(lambda g, d=d: np.asarray(pem.logit_at_gap(g), dtype=np.float64) + d)
        alternatives.append(AlternativeTarget("shift", f"{d:+g}", ShiftedDetector(target, d), known))
    return dataclasses.replace(problem, alternatives=tuple(alternatives), alternatives_source=source)
