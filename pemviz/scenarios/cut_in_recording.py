"""The cut-in scenario's hooks of the recording (:class:`pemviz.sinks.drawing.RecordingDrawing`), mixed into
:class:`pemviz.scenarios.cut_in_drawing.CutInDrawing`."""

from __future__ import annotations


class CutInRecording:
    """What the recording draws of a cut-in rollout (the ``params`` attribute is the drawing object's)."""
