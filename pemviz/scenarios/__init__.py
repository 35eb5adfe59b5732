"""Scenarios: black-box simulators stepped by a detector's perception of their objects, one package each.

:mod:`pemviz.scenarios.braking` (the braking scenario, its batched twin, its problem and its exact answers,
:mod:`pemviz.scenarios.braking.truth`), :mod:`pemviz.scenarios.cut_in` (the cut-in scene),
:mod:`pemviz.scenarios.crossing` (a scene built on :mod:`pemviz.stack`), :mod:`pemviz.scenarios.toy` and
:mod:`pemviz.scenarios.crowd` (the toys); beside them, what they share: their parameters
(:mod:`pemviz.scenarios.parameters`), their problems by name (:mod:`pemviz.scenarios.problems`: ``problem_for``,
``build_problem``), and the scenarios by name (:mod:`pemviz.scenarios.registry`).

The simulator protocols (``Simulator``, ``BatchedSimulator``, the optional ``Snapshotting``) and ``RolloutBatch`` live
in :mod:`pemviz.core.rollouts`, the rollout runner (``run_batched``, ``simulate``, ``Lockstep``, ``iter_rollouts``,
``branch`` ...) in :mod:`pemviz.core.lockstep`: scene-neutral, so that the core, the engine and the estimators need no
scenario. This package holds the four names the user guide imports from it, for a simulator and a scenario of one's
own: :func:`simulate` and :func:`branch` (N simulators in lockstep, :mod:`pemviz.core.lockstep`), :func:`register` and
:func:`registered` (the registry, :mod:`pemviz.scenarios.registry`: importing it loads no problem, PEM or torch);
:func:`pemviz.testing.check_scenario` checks any registered scenario. Every other name has one import path, its
module's.
"""

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
