"""The braking scenario's drawing object (:class:`pemviz.core.drawing.Drawing`): what the recording
(:class:`~pemviz.scenarios.braking_recording.BrakingRecording`) and the panel
(:class:`~pemviz.scenarios.braking_panel.BrakingPanel`) draw of its rollouts: two cars on one lane, the ego's
braking distance and crash margin, the outcome in words (:func:`pemviz.scenarios.braking_failures.severity`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from pemviz.scenarios.braking import BrakingParams
from pemviz.scenarios.braking_panel import BrakingPanel
from pemviz.scenarios.braking_recording import BrakingRecording

if TYPE_CHECKING:
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.scenarios.braking_failures import Severity


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


@dataclass(frozen=True)
class BrakingDrawing(BrakingRecording, BrakingPanel):
    """The braking scenario's drawing object.

    Attributes:
        params: the scenario's constants (car sizes, camera offset, thresholds, dt).
    """

    params: BrakingParams = field(default_factory=BrakingParams)

    @property
    def dt_s(self) -> float:
        return float(self.params.dt_s)

    def outcome(self, batch: RolloutBatch, i: int) -> Severity:
        """The :class:`~pemviz.scenarios.braking_failures.Severity` of rollout ``i`` of ``batch`` (from its gaps,
        metres).

        Raises:
            ValueError: the batch has no ``gap_m`` column.
        """
        from pemviz.scenarios.braking_failures import severity

        if "gap_m" not in batch.observation_names:
            raise ValueError(f"BrakingDrawing.outcome: the rollouts have no gap_m column ({batch.observation_names})")
        return severity(batch.signal("gap_m")[i], self.params)

    def failure_keys(self, detected: np.ndarray) -> tuple[str, list[int], dict[int, str]]:
        """Group failures by the last step at which one detection alone still saves the rollout (exact replays on
        the deterministic twin, :func:`pemviz.scenarios.braking_failures.last_saving_steps`).

        Args:
            detected: bool [F, T] the failures' detections.
        Returns:
            (what the groups are, one key per failure (the step; -1: no single detection saves it), key -> label).
        """
        from pemviz.scenarios.braking_failures import last_saving_steps

        keys = last_saving_steps(detected, self.params).tolist() if len(detected) else []
        dt = self.dt_s
        labels = {k: (f"last saving detection at step {k} ({k * dt:.2f} s)" if k >= 0 else "no single detection saves it")
                  for k in set(keys)}  # fmt: skip
        return "the last step at which one detection alone still saves the rollout (exact replays)", keys, labels
