"""The braking scenario's hooks of the panel (:class:`pemviz.app.drawing.PanelDrawing`), mixed into
:class:`pemviz.scenarios.braking_drawing.BrakingDrawing`."""

from __future__ import annotations


class BrakingPanel:
    """What the panel draws of a braking rollout (the ``params`` attribute is the drawing object's)."""
