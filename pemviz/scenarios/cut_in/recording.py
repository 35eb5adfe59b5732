"""The cut-in scenario's hooks of the recording (:class:`pemviz.sinks.drawing.RecordingDrawing`), mixed into
:class:`pemviz.scenarios.cut_in.drawing.CutInDrawing`: the scene is drawn from the object rows
(:attr:`pemviz.core.problem_view.ProblemView.objects_xy`), so these add each rollout's outcome as the cut-in's
severity (:func:`pemviz.scenarios.cut_in.story.cut_in_severity`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.scenarios.cut_in.story import CutInSeverity


class CutInRecording:
    """What the recording draws of a cut-in rollout (the ``params`` attribute is the drawing object's).

    Attributes:
        draws_scene: False: the scene is drawn from the object rows.
        object_words: ``the car ahead`` (a sentence on one object; the cut-in's rollouts have several)."""

    outcome: Callable[[RolloutBatch, int], CutInSeverity]  # the drawing object's (CutInDrawing.outcome)
    draws_scene = False
    object_words = "the car ahead"

    def intro(self, formula: str, metric: str, method: str) -> None:
        """None: the recording's own description (the problem's name and description)."""
        return None

    def outcome_values(self, batch: RolloutBatch, i: int) -> dict[str, Any] | None:
        """Rollout ``i``'s :class:`~pemviz.scenarios.cut_in.story.CutInSeverity` (``outcome`` words,
        ``min_clearance_m`` in metres, ``contact``, ``closing_speed_mps`` in m/s, NaN without contact); None where
        the rollouts lack its columns."""
        from pemviz.scenarios.cut_in.story import has_story_columns

        names, object_names = tuple(batch.observation_names), tuple(batch.object_names or ())
        if batch.objects is None or not has_story_columns(names, object_names):
            return None
        sev = self.outcome(batch, i)
        return dict(
            outcome=sev.short,
            min_clearance_m=sev.min_clearance_m,
            contact=sev.contact,
            closing_speed_mps=sev.closing_speed_mps,
        )

    def scene_lane(self, batch: RolloutBatch, i: int) -> None:
        """None: no lane (the scene is drawn from the object rows)."""
        return None

    def explanation(self, batch: RolloutBatch, i: int) -> dict[str, Any] | None:
        """None: the Explain tab shows the signals, each object's events and the objects seen from the ego."""
        return None
