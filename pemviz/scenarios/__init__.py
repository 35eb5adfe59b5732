"""Scenarios: black-box simulators stepped by a detector's perception of their objects, one package each, with their
parameters, problems by name and the registry (``docs/layout.md``). This package holds the four names the user guide
imports from it: :func:`simulate` and :func:`branch` (:mod:`pemviz.core.lockstep`), :func:`register` and
:func:`registered`; every other name has one import path, its module's."""

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
