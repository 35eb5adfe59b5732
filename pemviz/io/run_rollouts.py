"""What a run's rollout file holds beyond the rollouts, by the run's problem (what
:class:`pemviz.sinks.rollouts.RolloutSink` writes): the sidecar, the braking lead's salient variables, the severity."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from pemviz.core.rollouts import RolloutBatch
from pemviz.core.severity import rollout_severity, severity_of_signal
from pemviz.io.rollout_format import RolloutMeta
from pemviz.io.rollout_sidecars import braking_meta, problem_meta
from pemviz.io.rollout_table import braking_salient

if TYPE_CHECKING:
    from pemviz.core.problems import Problem


def braking_file(problem: Problem) -> bool:
    """Whether the rollouts of ``problem`` (a :class:`pemviz.core.problems.Problem`, or None: not known) go into a
    braking scenario's file: its problem (its drawing object is the braking scenario's), or none known."""
    from pemviz.scenarios.braking.drawing import BrakingDrawing

    return problem is None or isinstance(getattr(problem, "drawing", None), BrakingDrawing)


def run_meta(
    problem: Problem,
    formula: str | None,
    *,
    pem: str | None = None,
    proposal: str | None = None,
    provenance: Mapping[str, Any] | None = None,
) -> RolloutMeta:
    """The sidecar of a run's rollouts (:func:`braking_file`: :func:`~pemviz.io.rollout_sidecars.braking_meta`, else
    :func:`~pemviz.io.rollout_sidecars.problem_meta`).

    Raises:
        ValueError: a problem other than the braking one that does not know its step (``dt_s`` None)."""
    if braking_file(problem):
        return braking_meta(formula, pem=pem, proposal=proposal, provenance=provenance)
    return problem_meta(problem, formula, pem=pem, proposal=proposal, provenance=provenance)


def run_salient(problem: Problem, batch: RolloutBatch) -> np.ndarray | None:
    """The PEM's salient variables the file holds for ``batch``'s rollouts: float64 [N, T, 11] of the car ahead at
    each gap for a braking file (:func:`pemviz.io.rollout_table.braking_salient`), else None.

    Raises:
        KeyError: a braking file's rollouts without a ``gap_m`` column."""
    return braking_salient(batch.signal("gap_m")) if braking_file(problem) else None


def run_severity(problem: Problem, batch: RolloutBatch) -> tuple[np.ndarray, np.ndarray] | None:
    """Each rollout's min distance (metres) and impact speed (m/s, NaN: no contact), float64 [N] each, for the file's
    severity columns (:func:`pemviz.core.severity.rollout_severity`); without a problem, those of the braking
    scenario's gap at its defaults (contact gap, step) as its sidecar assumes; None for a problem without a severity
    scale."""
    if problem is None:
        from pemviz.scenarios.braking.simulator import BrakingParams

        p = BrakingParams()
        return severity_of_signal(batch.signal("gap_m"), p.contact_gap_m, p.dt_s)
    if getattr(problem, "severity", None) is None:
        return None
    return rollout_severity(problem, batch)
