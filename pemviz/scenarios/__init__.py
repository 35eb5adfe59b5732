"""Scenarios: black-box simulators stepped by a detector's perception of their objects, and the rollout runner.

The simulator protocols (:class:`Simulator`, :class:`BatchedSimulator`, the optional :class:`Snapshotting`) and
:class:`RolloutBatch` live in :mod:`pemviz.core.rollouts`, the rollout runner (:func:`run_batched`, :func:`simulate`,
:class:`Lockstep`, :func:`iter_rollouts`, :func:`branch` ...) in :mod:`pemviz.core.lockstep`: scene-neutral, so that
the core, the engine and the estimators need no scenario. This package re-exports them, and holds the scenarios
themselves, one package each: :mod:`pemviz.scenarios.braking` (the braking scenario, its batched twin, its problem and
its exact answers, :mod:`pemviz.scenarios.braking.truth`), :mod:`pemviz.scenarios.cut_in` (the cut-in scene),
:mod:`pemviz.scenarios.toy` and :mod:`pemviz.scenarios.crowd` (the toys); beside them, what they share: their
parameters (:mod:`pemviz.scenarios.parameters`) and their problems by name (:mod:`pemviz.scenarios.problems`:
``problem_for``, ``build_problem``, ``braking_problem`` ...).

The scenarios by name (:mod:`pemviz.scenarios.registry`): :func:`registered` lists them, :func:`get_scenario` returns
one's record and :func:`register` adds one of one's own (imported when first named: ``from pemviz.scenarios import
registered``); :func:`pemviz.testing.check_scenario` checks any of them.
"""

from __future__ import annotations

from typing import Any

from pemviz.core.lockstep import (  # noqa: F401 (the rollout runner, re-exported: importable from here as before)
    DEFAULT_CHUNK_SIZE as DEFAULT_CHUNK_SIZE,
    Lockstep as Lockstep,
    branch as branch,
    branch_rollouts as branch_rollouts,
    check_branch_args as check_branch_args,
    check_counts as check_counts,
    iter_rollouts as iter_rollouts,
    replay_rows as replay_rows,
    run_batched as run_batched,
    simulate as simulate,
    simulate_rollouts as simulate_rollouts,
    uniform_chunks as uniform_chunks,
)
from pemviz.core.rollouts import (  # noqa: F401 (the protocols and rollouts, re-exported: importable from here)
    BatchedSimulator as BatchedSimulator,
    RolloutBatch as RolloutBatch,
    Simulator as Simulator,
    Snapshotting as Snapshotting,
    can_snapshot as can_snapshot,
    draws_per_rollout as draws_per_rollout,
    n_objects_of as n_objects_of,
)


_REGISTRY_NAMES = {"registered": "registered", "register": "register", "get_scenario": "get", "Scenario": "Scenario"}
"""The names this package lends from :mod:`pemviz.scenarios.registry` (the name here -> the name there)."""


def __getattr__(name: str) -> Any:
    """:func:`registered`, :func:`register`, :func:`get_scenario` (the registry's ``get``) and :class:`Scenario` of
    :mod:`pemviz.scenarios.registry`, imported when first named (importing this package loads no registry)."""
    if name in _REGISTRY_NAMES:
        from pemviz.scenarios import registry

        return getattr(registry, _REGISTRY_NAMES[name])
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
