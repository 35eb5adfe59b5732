"""The map of where p_ODD comes from (:class:`pemviz.core.odd.OddMap`), printed after the final estimate of a run over
an operating design domain."""

from __future__ import annotations

import sys
from typing import TextIO

from pemviz.core.odd import OddMap
from pemviz.engine.events import FinalEstimate
from pemviz.sinks import Sink


class OddMapSink(Sink):
    """Prints the final estimate's map to ``out`` (None: stdout); :attr:`map` keeps it (None before, or without an
    ODD)."""

    def __init__(self, out: TextIO | None = None) -> None:
        self.out = out
        self.map: OddMap | None = None

    def on_final_estimate(self, event: FinalEstimate) -> None:
        self.map = event.odd_map
        if self.map is not None:
            for line in self.map.lines():
                print(line, file=self.out or sys.stdout)
