"""What the recording (:mod:`pemviz.sinks.recording`) asks of a scenario's drawing object, on top of the outcome every
sink shares (:class:`pemviz.core.drawing.Drawing`).

The hooks return data (words, numbers, arrays, Markdown), never rerun objects; None where the scenario has nothing of
that kind. Colours are named by role (:data:`ROLES`). One hook is optional (read with ``getattr``):
``contacts(batch, rows)``, bool [k] whether each of the rollouts ``rows`` made contact."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, Protocol, cast, runtime_checkable

from pemviz.core.drawing import Drawing

if TYPE_CHECKING:  # annotations only
    import numpy as np

    from pemviz.core.rollouts import RolloutBatch

ROLES = ("failure", "detected", "missed", "window", "replay", "ego_speed", "object_speed")
"""The colour roles a hook may name: the failure red, the detection green, the miss orange, the sampler window's
yellow, a replay's violet, the ego's and the object's speeds."""

SceneBox = tuple[str, "np.ndarray", tuple[float, float], "np.ndarray | None"]
"""``(name, centre_x [T] metres, (half length, half width) metres, alarm bool [T] or None)``: one object of a lane."""

SceneLane = tuple[tuple[SceneBox, ...], "tuple[np.ndarray, np.ndarray] | None", float]
"""``(boxes, sight (from_x [T], to_x [T]) or None, end_m)``: one rollout drawn as a lane seen from above."""


@runtime_checkable
class RecordingDrawing(Drawing, Protocol):
    """The recording's hooks of a scenario's drawing object.

    Attributes:
        draws_scene: the recording draws each stage's least robust rollouts as lanes of a scene seen from above
            (:meth:`scene_lane`), explains the most likely failure with replays, a controller and speeds
            (:meth:`explanation`) and charts the failures' share of contact (e.g. True for the braking scenario,
            False where the scene is drawn from the rollouts' object rows instead).
        object_words: the object the detector looks for, as a sentence names it (e.g. ``the car ahead``), for a
            rollout of one object."""

    @property
    def draws_scene(self) -> bool: ...

    @property
    def object_words(self) -> str: ...

    def intro(self, formula: str, metric: str, method: str) -> tuple[str, str] | None:
        """The head of the recording's description, or None (the recording's own, from the problem's name and
        description).

        Args:
            formula: the safety specification (STL).
            metric: the robustness metric the rollouts are ranked by.
            method: one sentence on the run's method (Markdown).
        Returns:
            (the title and the paragraph on the scenario, in Markdown; what the scene adds to the paragraph on how
            to read the recording, a phrase that starts with `` and``)."""
        ...

    def outcome_values(self, batch: RolloutBatch, i: int) -> Mapping[str, Any] | None:
        """The outcome of rollout ``i`` of ``batch`` as the recording's properties of it: ``outcome`` (words, e.g.
        ``contact at 3.2 m/s``), ``contact`` (bool) and the scenario's numbers (e.g. the min distance, metres);
        None: the recording says only ``failure`` or ``safe`` (also where the batch lacks the columns read)."""
        ...

    def scene_lane(self, batch: RolloutBatch, i: int) -> SceneLane | None:
        """Rollout ``i`` of ``batch`` as one lane of the scene seen from above (:data:`SceneLane`); None: not drawn
        (no scene, or the batch lacks the columns read)."""
        ...

    def explanation(self, batch: RolloutBatch, i: int) -> Mapping[str, Any] | None:
        """What the recording's *Explain* tab adds for the failing rollout ``i`` of ``batch`` (the module's
        explanation mapping: words, properties, summary lines, series and markers); None: nothing beyond the
        signals, p(detect) and the misses."""
        ...


def recording_hooks(drawing: object) -> RecordingDrawing | None:
    """A scenario's drawing object (:attr:`pemviz.core.problem_view.ProblemView.drawing`, or None) as the recording
    reads it: its hooks (:class:`RecordingDrawing`), called without checking for them, as every caller did."""
    return cast("RecordingDrawing | None", drawing)
