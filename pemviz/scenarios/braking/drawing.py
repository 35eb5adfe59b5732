"""The braking scenario's drawing object (:class:`pemviz.core.drawing.Drawing`): what the recording
(:class:`~pemviz.scenarios.braking.recording.BrakingRecording`) and the panel
(:class:`~pemviz.scenarios.braking.panel.BrakingPanel`) draw of its rollouts: two cars on one lane, the ego's
braking distance and crash margin, the outcome in words (:func:`pemviz.scenarios.braking.failures.severity`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from pemviz.scenarios.braking.panel import BrakingPanel
from pemviz.scenarios.braking.recording import BrakingRecording, car_positions
from pemviz.scenarios.braking.simulator import BrakingParams

__all__ = ["BrakingDrawing", "car_positions"]

if TYPE_CHECKING:
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.scenarios.braking.failures import Severity


@dataclass(frozen=True)
class BrakingDrawing(BrakingRecording, BrakingPanel):
    """The braking scenario's drawing object.

    Attributes:
        params: the scenario's constants (car sizes, camera offset, thresholds, dt)."""

    params: BrakingParams = field(default_factory=BrakingParams)

    @property
    def dt_s(self) -> float:
        return float(self.params.dt_s)

    def outcome(self, batch: RolloutBatch, i: int) -> Severity:
        """The :class:`~pemviz.scenarios.braking.failures.Severity` of rollout ``i`` of ``batch`` (from its gaps,
        metres).

        Raises:
            ValueError: the batch has no ``gap_m`` column."""
        from pemviz.scenarios.braking.failures import severity

        if "gap_m" not in batch.observation_names:
            raise ValueError(f"BrakingDrawing.outcome: the rollouts have no gap_m column ({batch.observation_names})")
        return severity(batch.signal("gap_m")[i], self.params)

    def failure_keys(self, detected: np.ndarray) -> tuple[str, list[int], dict[int, str]]:
        """Group failures by the last step at which one detection alone still saves the rollout (exact replays on
        the deterministic twin, :func:`pemviz.scenarios.braking.failures.last_saving_steps`).

        Args:
            detected: bool [F, T] the failures' detections.
        Returns:
            (what the groups are, one key per failure (the step; -1: no single detection saves it), key -> label)."""
        from pemviz.scenarios.braking.failures import last_saving_steps

        keys = last_saving_steps(detected, self.params).tolist() if len(detected) else []
        dt = self.dt_s
        labels = {
            k: (f"last saving detection at step {k} ({k * dt:.2f} s)" if k >= 0 else "no single detection saves it")
            for k in set(keys)
        }
        return "the last step at which one detection alone still saves the rollout (exact replays)", keys, labels
