"""The braking scenario's hooks of the recording (:class:`pemviz.sinks.drawing.RecordingDrawing`), mixed into
:class:`pemviz.scenarios.braking_drawing.BrakingDrawing`."""

from __future__ import annotations


class BrakingRecording:
    """What the recording draws of a braking rollout (the ``params`` attribute is the drawing object's)."""
