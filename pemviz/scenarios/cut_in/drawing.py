"""The cut-in scenario's drawing object (:class:`pemviz.core.drawing.Drawing`) for the recording
(:class:`~pemviz.scenarios.cut_in.recording.CutInRecording`) and the panel
(:class:`~pemviz.scenarios.cut_in.panel.CutInPanel`): cars on a three-lane road, the cut-in's story, the outcome in
words (:func:`pemviz.scenarios.cut_in.story.cut_in_severity`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from pemviz.scenarios.cut_in.panel import CutInPanel
from pemviz.scenarios.cut_in.recording import CutInRecording
from pemviz.scenarios.cut_in.scenario import CutInParams

if TYPE_CHECKING:
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.scenarios.cut_in.story import CutInSeverity


@dataclass(frozen=True)
class CutInDrawing(CutInRecording, CutInPanel):
    """The cut-in scenario's drawing object.

    Attributes:
        params: the scenario's constants (cars, lanes, dt)."""

    params: CutInParams = field(default_factory=CutInParams)

    @property
    def dt_s(self) -> float:
        return float(self.params.dt_s)

    def outcome(self, batch: RolloutBatch, i: int) -> CutInSeverity:
        """The :class:`~pemviz.scenarios.cut_in.story.CutInSeverity` of rollout ``i`` of ``batch`` (its scene
        signals and object rows).

        Raises:
            ValueError: the rollouts lack the columns the story reads."""
        from pemviz.scenarios.cut_in.story import cut_in_severity, has_story_columns

        names = tuple(batch.observation_names)
        object_names = tuple(batch.object_names or ())
        if batch.objects is None or not has_story_columns(names, object_names):
            raise ValueError("CutInDrawing.outcome: the rollouts lack the scene columns its severity reads")
        return cut_in_severity(batch.observations[i], names, batch.objects[i], object_names, self.params.dt_s)
