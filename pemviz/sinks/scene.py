"""Where the two cars of the braking scenario are, rebuilt from a rollout's observations: one function for the
recording's top-down scene (:mod:`pemviz.sinks.recording`) and the panel's 3D scene (:mod:`pemviz.app`)."""

from __future__ import annotations

import numpy as np

from pemviz.scenarios.braking import BrakingParams


def car_positions(
    gap_m: np.ndarray, ego_speed_mps: np.ndarray, params: BrakingParams | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Centre x of the ego and of the lead at every step, float64 [T] each (metres along the road; ego starts at 0).

    The ego moves by explicit Euler on its recorded speed, as highway-env's ``Vehicle.step`` does
    (``x[t+1] = x[t] + v[t] * dt``, a speed of NaN counts as 0); the lead's rear is the camera
    (``camera_offset_m`` ahead of the ego's centre) plus the gap, so
    ``lead = ego + camera_offset_m + gap_m + lead_length_m / 2`` (:class:`pemviz.scenarios.braking.BrakingScenario`).

    Args:
        gap_m: float64 [T] gaps (metres).
        ego_speed_mps: float64 [T] ego speeds (m/s).
        params: the scenario's constants (default :class:`~pemviz.scenarios.braking.BrakingParams`).
    """
    p = params or BrakingParams()
    v = np.nan_to_num(np.asarray(ego_speed_mps, dtype=np.float64), nan=0.0)
    ego_x = p.dt_s * np.concatenate([[0.0], np.cumsum(v[:-1])])
    lead_x = ego_x + p.camera_offset_m + gap_m + p.lead_length_m / 2
    return ego_x, lead_x
