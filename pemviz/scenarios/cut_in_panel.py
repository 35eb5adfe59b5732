"""The cut-in scenario's hooks of the panel (:class:`pemviz.app.drawing.PanelDrawing`), mixed into
:class:`pemviz.scenarios.cut_in_drawing.CutInDrawing`."""

from __future__ import annotations


class CutInPanel:
    """What the panel draws of a cut-in rollout (the ``params`` attribute is the drawing object's)."""
