"""The cut-in scenario over an operating design domain: each rollout's start gap to the cut-in vehicle
(``cut_in_gap_m``) drawn from a distribution (``pemviz run --scenario cut-in --param
"cut_in_gap_m~uniform(19.5,21.5)"``), the other parameters fixed.

The cut-in vehicle's trajectory from another start gap is the same trajectory moved along the road, so the batched
twin moves it per rollout (``gap_shift_m``) and the rollouts share one traffic trajectory;
:func:`cut_in_odd_problem` checks that at five points of the support
(:func:`pemviz.scenarios.cut_in.batched.translation_error`) and refuses an ODD where it fails. The problem has no
tilted proposal, look-ahead or reference (each made for one gap): over an ODD the cut-in runs plain Monte Carlo."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from pemviz.core.odd import ODD
from pemviz.core.odd_rollouts import problem_over_odd
from pemviz.core.problems import Problem
from pemviz.scenarios.cut_in.batched import BatchedCutIn, translation_error
from pemviz.scenarios.cut_in.scenario import CutInParams
from pemviz.settings import setting_of

RANDOM_PARAMS = ("cut_in_gap_m",)
"""The cut-in's parameters an ODD may draw per rollout."""

TRANSLATION_TOLERANCE_M = 1e-9
"""The most the traffic from another start gap may differ from the moved one (metres) for the ODD to be accepted."""


def cut_in_odd_problem(config: Any, params: CutInParams | None, odd: ODD) -> Problem:
    """The cut-in problem over ``odd`` (parameter ``cut_in_gap_m``, metres), the others at ``params`` (None: the
    defaults), the PEMs ``config.perception.pem`` (None: the shipped ones).

    Raises:
        ValueError: another parameter in the ODD; a support where the cut-in vehicle's trajectory is not the moved one
            (it would meet the other traffic: say which end and by how much)."""
    from pemviz.pem import load_pem
    from pemviz.scenarios.cut_in.problem import cut_in_problem

    p = params or CutInParams()
    others = [name for name in odd.names if name not in RANDOM_PARAMS]
    if others:
        raise ValueError(f"the cut-in scenario draws only cut_in_gap_m per rollout, not {others}")
    (law,) = (law for name, law in odd.parameters if name == "cut_in_gap_m")
    lo, hi = law.support()
    for gap in np.linspace(lo, hi, 5):
        err = translation_error(p, gap)
        if not err <= TRANSLATION_TOLERANCE_M:
            how = f"by {err:.3g} m" if math.isfinite(err) else "in its lane, speed or who hides whom"
            raise ValueError(
                f"cut_in_gap_m~{law.text}: from a start gap of {gap:g} m the traffic is not the one from "
                f"{p.cut_in_gap_m:g} m with the cut-in vehicle moved along the road (it differs {how}); draw the gap "
                "over a narrower range"
            )

    def make(n: int, values: np.ndarray) -> BatchedCutIn:
        return BatchedCutIn(p, n, gap_shift_m=values[:, 0] - p.cut_in_gap_m)

    base = cut_in_problem(load_pem(setting_of(config, "pem", None)), p, name=getattr(config, "scenario", "cut-in"))
    return problem_over_odd(
        base,
        make,
        odd,
        p.n_steps,
        description=(
            f"ACC on a tracker, {p.n_objects} cars on a 3-lane highway, one cutting in at {p.cut_in_speed_mps:g} m/s, "
            f"its start gap drawn per rollout ({odd.text()}); failure: a collision or the safe distance of R_G1"
        ),
    )
