"""Scenarios: black-box simulators stepped by a detector's perception of their objects, one package each, with their
parameters, problems by name and the registry (``docs/layout.md``). This package holds the five names the user guide
imports from it: :func:`simulate`, :func:`branch` and :func:`state_replay` (:mod:`pemviz.core.lockstep`),
:func:`register` and :func:`registered`; every other name has one import path, its module's."""

from typing import Any

from pemviz.scenarios.registry import register, registered

__all__ = ["branch", "register", "registered", "simulate", "state_replay"]


def __getattr__(name: str) -> Any:
    """:func:`branch`, :func:`simulate` and :func:`state_replay`, imported when first asked for (PEP 562): the
    registry's import (the command line's help lists the scenarios) loads no rollout runner."""
    if name in ("branch", "simulate", "state_replay"):
        from pemviz.core import lockstep

        return getattr(lockstep, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
