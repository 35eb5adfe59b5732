"""The viser panel of ``pemviz serve`` (:class:`PanelApp`, one :class:`Session` per browser client).

Run bookkeeping in :mod:`pemviz.app.runs`, the form in :mod:`pemviz.app.form`, the failure explanation in
:mod:`pemviz.app.explain`, the figures in :mod:`pemviz.app.plots`.
"""

from pemviz.app.panel import PanelApp, serve
from pemviz.app.runs import PanelRun, Trajectory, export_path, sanitize_export_name, scene_positions
from pemviz.app.session import Session

__all__ = [
    "PanelApp", "PanelRun", "Session", "Trajectory", "export_path", "sanitize_export_name", "scene_positions", "serve",
]  # fmt: skip
