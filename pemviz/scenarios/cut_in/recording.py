"""The cut-in scenario's hooks of the recording (:class:`pemviz.sinks.drawing.RecordingDrawing`), mixed into
:class:`pemviz.scenarios.cut_in.drawing.CutInDrawing`. The recording draws the cut-in's scene from the rollouts'
object rows (:attr:`pemviz.core.problem_view.ProblemView.objects_xy`), so these add no lanes and no story, and the
run's description is the recording's own; each rollout's outcome is the cut-in's severity
(:func:`pemviz.scenarios.cut_in.story.cut_in_severity`), in the words the panel shows too."""

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
        object_words: ``the car ahead`` (a sentence on one object; the cut-in's rollouts have several).
    """

    outcome: Callable[[RolloutBatch, int], CutInSeverity]  # the drawing object's (CutInDrawing.outcome)
    draws_scene = False
    object_words = "the car ahead"

    def intro(self, formula: str, metric: str, method: str) -> None:
        """None: the recording's own description (the problem's name and description)."""
        return None

    def outcome_values(self, batch: RolloutBatch, i: int) -> dict[str, Any] | None:
        """Rollout ``i``'s :class:`~pemviz.scenarios.cut_in.story.CutInSeverity`: ``outcome`` (its words, e.g.
        ``contact at 2.8 m/s closing speed at 3.10 s · minimum clearance -0.66 m ...``), ``min_clearance_m``
        (metres; negative: the boxes overlap), ``contact``, ``closing_speed_mps`` (m/s; NaN: no contact, or none in
        front); None where the rollouts lack the scene columns the severity reads."""
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
