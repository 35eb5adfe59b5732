"""Scenarios: black-box simulators stepped by a detector's perception of their objects, one package each.

:mod:`pemviz.scenarios.braking`, :mod:`pemviz.scenarios.cut_in`, :mod:`pemviz.scenarios.crossing` (built on
:mod:`pemviz.stack`), :mod:`pemviz.scenarios.toy` and :mod:`pemviz.scenarios.crowd`; beside them their parameters
(:mod:`pemviz.scenarios.parameters`), problems by name (:mod:`pemviz.scenarios.problems`) and the registry
(:mod:`pemviz.scenarios.registry`). The simulator protocols live in :mod:`pemviz.core.rollouts` and the rollout
runner in :mod:`pemviz.core.lockstep`, scene-neutral. This package holds the four names the user guide imports from
it: :func:`simulate` and :func:`branch` (:mod:`pemviz.core.lockstep`), :func:`register` and :func:`registered`;
every other name has one import path, its module's."""

from typing import Any

from pemviz.scenarios.registry import register, registered

__all__ = ["branch", "register", "registered", "simulate"]


def __getattr__(name: str) -> Any:
    """:func:`branch` and :func:`simulate`, imported when first asked for (PEP 562): the registry's import (the
    command line's help lists the scenarios) loads no rollout runner."""
    if name in ("branch", "simulate"):
        from pemviz.core import lockstep

        return getattr(lockstep, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
