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

from pemviz.core.lockstep import branch, simulate
from pemviz.scenarios.registry import register, registered

__all__ = ["branch", "register", "registered", "simulate"]
