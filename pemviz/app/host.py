"""What the parts of a :class:`pemviz.app.session.Session` need of the server that owns them."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

from pemviz.app.drawing import LanePanel
from pemviz.config import ExperimentConfig


class PanelHost(Protocol):
    """What a session needs of the server that owns it (:class:`pemviz.app.panel.PanelApp`)."""

    drawing: LanePanel
    """The drawing object of the idle scene (before a run)."""
    config0: ExperimentConfig
    """The configuration the panel opened with."""
    preset_name: str
    recordings_dir: Path
    """Where exported recordings go."""

    def next_run_id(self) -> int: ...

    def wait_warm(self) -> None: ...
