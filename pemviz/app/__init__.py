"""The viser panel of ``pemviz serve`` (:class:`PanelApp`); run bookkeeping in :mod:`pemviz.app.runs`."""

from pemviz.app.panel import PanelApp, serve
from pemviz.app.runs import RunRecord, Trajectory, export_path, sanitize_export_name, scene_positions

__all__ = ["PanelApp", "RunRecord", "Trajectory", "export_path", "sanitize_export_name", "scene_positions", "serve"]
