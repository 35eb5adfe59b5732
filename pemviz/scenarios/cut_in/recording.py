"""The cut-in scenario's hooks of the recording (:class:`pemviz.sinks.drawing.RecordingDrawing`), mixed into
:class:`pemviz.scenarios.cut_in.drawing.CutInDrawing`. The recording draws the cut-in's scene from the rollouts'
object rows (:attr:`pemviz.core.problems.ProblemView.objects_xy`), so these add nothing: no lanes, no story, the
run's description and each rollout's words are the recording's own."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pemviz.core.rollouts import RolloutBatch


class CutInRecording:
    """What the recording draws of a cut-in rollout (the ``params`` attribute is the drawing object's).

    Attributes:
        draws_scene: False: the scene is drawn from the object rows.
        object_words: ``the car ahead`` (a sentence on one object; the cut-in's rollouts have several).
    """

    draws_scene = False
    object_words = "the car ahead"

    def intro(self, formula: str, metric: str, method: str) -> None:
        """None: the recording's own description (the problem's name and description)."""
        return None

    def outcome_values(self, batch: RolloutBatch, i: int) -> None:
        """None: the recording says ``failure`` or ``safe``."""
        return None

    def scene_lane(self, batch: RolloutBatch, i: int) -> None:
        """None: no lane (the scene is drawn from the object rows)."""
        return None

    def explanation(self, batch: RolloutBatch, i: int) -> dict[str, Any] | None:
        """None: the Explain tab shows the signals, each object's events and the objects seen from the ego."""
        return None
