"""The cut-in scenario's problem: :func:`cut_in_problem` (the scenario as a :class:`pemviz.core.problems.Problem` on
its batched twin) at a named rarity setting :func:`cut_in_params`, its failure formula :data:`CUT_IN_FORMULA` over
:data:`CUT_IN_SIGNALS` and its window :data:`CUT_IN_WINDOW_M` (:mod:`pemviz.scenarios.problems` imports this module
for a cut-in run alone, so that a run of another scenario loads none of the cut-in's modules)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from pemviz import stl
from pemviz.core.problems import Problem, rollout_functions
from pemviz.core.severity import SeverityScale
from pemviz.scenarios.cut_in.batched import BatchedCutIn, cached_trajectory
from pemviz.scenarios.cut_in.drawing import CutInDrawing
from pemviz.scenarios.cut_in.scenario import OBJECT_NAMES, RARITY_SETTINGS, SALIENT_COLUMNS, CutInParams
from pemviz.scenarios.cut_in.story import car_labels
from pemviz.stack.detector import NOISE_NAMES

if TYPE_CHECKING:
    from pemviz.pem.noise import NoiseModel
    from pemviz.scenarios.cut_in.tilt import CutInTilt


CUT_IN_WINDOW_M = 40.0
"""The cut-in problem's window on an object's range (metres): the proposal replaces the PEMs for the cars nearer
than this. The ACC of the cut-in scenario reacts within about 2 s at 25 m/s, so a car further away can be seen in
time whatever the camera does; outside the window, a rollout's objects are drawn from the PEMs themselves."""

CUT_IN_SIGNALS = {"margin": "safe_margin_m", "grace": "cut_in_recent", "clearance": "clearance_m"}
"""STL signal name -> cut-in rollout observation column (:data:`pemviz.scenarios.cut_in.scenario.OBSERVATION_NAMES`)."""

CUT_IN_FORMULA = "G((margin + 1000 * grace >= 0) & (clearance >= 0))"
"""The cut-in failure over :data:`CUT_IN_SIGNALS`: R_G1 of Maierhofer et al. 2020, waived after a cut-in, and no
collision (metres); classically :data:`pemviz.scenarios.cut_in.scenario.FAILURE_FORMULA` written as one ``G(state
predicate)``, which the weights' stop and splitting need."""


CUT_IN_SEVERITY_LEVELS_M = (2.0, 1.0, 0.0)
"""Clearances (metres, bumper to bumper) of the cut-in's exceedance curve: failures that also come this close; 0 is a
collision."""


def cut_in_params(setting: str) -> CutInParams:
    """The cut-in scenario at a named rarity setting (:data:`pemviz.scenarios.cut_in.scenario.RARITY_SETTINGS`:
    ``moderate``, ``rare``).

    Raises:
        ValueError: an unknown setting."""
    if setting not in RARITY_SETTINGS:
        raise ValueError(f"unknown cut-in setting {setting!r}; use one of {', '.join(RARITY_SETTINGS)}")
    return CutInParams(**RARITY_SETTINGS[setting])


def cut_in_problem(
    pem: object, params: CutInParams | None = None, noise: NoiseModel | None = None, name: str = "cut-in"
) -> Problem:
    """The cut-in scenario as a :class:`Problem` on its batched twin
    (:class:`~pemviz.scenarios.cut_in.batched.BatchedCutIn`): M cars, each detected by ``pem`` and mislocated by the
    noise PEM ``noise`` (:class:`pemviz.pem.perception.SalientDetector`), failing on :data:`CUT_IN_FORMULA` (Innes &
    Ramamoorthy, "Adaptive Splitting of Reusable Temporal Monitors for Rare Traffic Violations", arXiv 2405.15771);
    the proposal reads each car's row (range first, scaled by 50 m) within :data:`CUT_IN_WINDOW_M`. The reference is
    plain Monte Carlo of the same twin (``benchmarks/cut_in_mc.py``).

    Args:
        pem: the detection PEM (``pemviz.pem.load_pem()``).
        params: the scenario (default: the ``moderate`` setting, about 9e-5).
        noise: the noise PEM (default: the shipped ``hetero-t``).
        name: the problem's name (the scenario's registered name)."""
    from pemviz.pem.perception import SalientDetector
    from pemviz.pem.store import load_noise_pem

    p = params if params is not None else cut_in_params("moderate")
    cached_trajectory(p)
    detector = SalientDetector(
        pem,
        SALIENT_COLUMNS,
        load_noise_pem("hetero-t") if noise is None else noise,
        NOISE_NAMES,
        OBJECT_NAMES.index("visible"),
    )

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

    def tilt() -> CutInTilt:
        from pemviz.scenarios.cut_in.tilt import solved_tilt

        return solved_tilt(p, detector)

    return Problem(
        name,
        run,
        detector,
        stl.parse(CUT_IN_FORMULA),
        signals=dict(CUT_IN_SIGNALS),
        units={"margin": "m", "grace": "", "clearance": "m"},
        signal_ranges={"margin": (-60.0, 200.0), "grace": (0.0, 1.0), "clearance": (-10.0, 200.0)},
        severity=SeverityScale("clearance", "clearance", "m", CUT_IN_SEVERITY_LEVELS_M),
        h_scale=50.0,
        curve_grid=np.arange(0.0, CUT_IN_WINDOW_M + 10.5, 0.5),
        window=CUT_IN_WINDOW_M,
        stream=stream,
        branch=resume,
        curve_rows=curve_rows,
        objects_xy=("loc_x", "loc_z"),
        dt_s=p.dt_s,
        n_objects=p.n_objects,
        n_steps=p.n_steps,
        drawing=CutInDrawing(p),
        object_labels=car_labels(p.n_objects),
        noise_xy=(NOISE_NAMES.index("lateral_error_m"), NOISE_NAMES.index("range_error_m")),
        tilt=tilt,
        description=(
            f"ACC on a tracker, {p.n_objects} cars on a 3-lane highway, one cutting in {p.cut_in_gap_m:g} m "
            f"ahead at {p.cut_in_speed_mps:g} m/s; failure: a collision or the safe distance of R_G1"
        ),
    )


def _car_ahead_row(sim: BatchedCutIn, p: CutInParams) -> np.ndarray:
    """Object 0's row [G] once it has cut in (every car detected exactly): the cut-in car ahead in the ego's lane."""
    lane = OBJECT_NAMES.index("in_ego_lane")
    for _ in range(p.n_steps):
        row = sim.objects()[0, 0]
        if row[lane] > 0.5 and sim.t > p.cut_in_step + round(p.cut_in_lateral_time_s / p.dt_s):
            break
        sim.step(np.ones((1, p.n_objects), bool), np.zeros((1, p.n_objects, 2)))
    return np.array(row, dtype=np.float64)
