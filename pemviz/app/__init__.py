"""The viser panel of ``pemviz serve`` (:class:`PanelApp`, one :class:`Session` per browser client).

Run bookkeeping in :mod:`pemviz.app.runs`, the form in :mod:`pemviz.app.form`, what the panel asks of a scenario's
drawing object in :mod:`pemviz.app.drawing`, the figures in :mod:`pemviz.app.plots`.
"""

from pemviz.app.panel import PanelApp, serve
from pemviz.app.runs import PanelRun, Trajectory, export_path, sanitize_export_name
from pemviz.app.session import Session

__all__ = ["PanelApp", "PanelRun", "Session", "Trajectory", "export_path", "sanitize_export_name", "serve"]
