"""The engine: runs an estimator's stages on a problem and emits events (:mod:`pemviz.engine.experiment`).

With it: the events and what they carry (:mod:`pemviz.engine.events`; the run's plan of stages is the core's,
:mod:`pemviz.core.plan`), what a run costs before it starts and while it runs (:mod:`pemviz.engine.cost`), its
memory and CPUs (:mod:`pemviz.engine.resources`), and where its rollouts are simulated (:mod:`pemviz.engine.executors`).

``from pemviz.engine import Experiment`` (and the other names of :data:`__all__`; the events have their one home in
:mod:`pemviz.engine.events`) imports
:mod:`pemviz.engine.experiment`, and with it torch, only when asked: the light modules of this package
(``events``, ``cost``, ``resources``) import neither, so ``pemviz --help`` stays fast. To change one of the
engine's constants (``STREAM_ABOVE``) set it on :mod:`pemviz.engine.experiment`, which reads it.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPERIMENT = ("Experiment", "Cancelled", "RobustnessByMetric", "StageSample", "STREAM_ABOVE", "SAMPLE_LEAST_ROBUST",
               "SAMPLE_FAILURES", "SAMPLE_UNIFORM")  # fmt: skip
_HOMES = dict.fromkeys(_EXPERIMENT, "experiment")
__all__ = sorted(_HOMES)


def __getattr__(name: str) -> Any:
    """A name of :data:`__all__`, from its module, imported on first use (PEP 562)."""
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{home}"), name)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
