"""Rare-event estimators, one per method of :data:`pemviz.config.METHODS`, behind one small interface
(:class:`Estimator`) that the engine drives stage by stage.

- :class:`CrossEntropy` (``adaptive``): Algorithm 1 of Innes & Ramamoorthy (2022) with pemviz's improvements.
- :class:`FixedSampler` (``mc``, ``naive50``, ``mixed50``): one importance-weighted batch from a fixed detector.
- :class:`AdaptiveMultilevelSplitting` (``ams``): splitting of target rollouts on their robustness, no weights.
- :class:`~pemviz.estimators.tilt.CommittorTilt` (``tilt``): the scenario's own tilted proposal, one weighted batch.
- :class:`PrecisionTarget` (``rel_error``, ``require``): any of the first two, with final batches added until a
  relative precision or a decision on a requirement.

Every method, these and a user's own, is a record of :mod:`pemviz.estimators.registry`, which
:func:`build_estimator` and :func:`run_plan` read.
"""

from __future__ import annotations

from pemviz.config import ExperimentConfig
from pemviz.core.problems import Problem
from pemviz.core.plan import PlannedStage, RunPlan
from pemviz.estimators.base import (
    Check,
    Estimator,
    StageOutcome,
    StagePlan,
    failure_steps,
    log_p_before_failure,
    log_weight,
)
from pemviz.estimators.cross_entropy import (
    CappedDetector, CrossEntropy, DefensiveDetector, break_ties, check_runnable,
)
from pemviz.estimators.fixed import FixedSampler, mixed50, monte_carlo, naive50
from pemviz.estimators.precision import PrecisionTarget
from pemviz.estimators.registry import Method, get_method, method_names, register_method, unregister_method

__all__ = [
    "AdaptiveMultilevelSplitting", "CappedDetector", "Check", "CrossEntropy", "DefensiveDetector", "Estimator",
    "FixedSampler", "PlannedStage", "PrecisionTarget", "RunPlan", "StageOutcome", "StagePlan", "break_ties",
    "build_estimator", "check_runnable",
    "failure_steps", "log_p_before_failure", "log_weight", "mixed50", "monte_carlo", "naive50", "run_plan",
    "Method", "get_method", "method_names", "register_method", "unregister_method",
]  # fmt: skip


def build_estimator(config: ExperimentConfig, problem: Problem, check: Check | None = None) -> Estimator:
    """The estimator of ``config.method`` on ``problem`` (``check``: called between and inside fits, may raise).

    The baselines draw ``config.n_per_stage`` rollouts and stop their weights at the failure step with
    ``config.weights_until_failure``, like the adaptive sampler's.
    The method is the registry's (:func:`pemviz.estimators.registry.get_method`: the built-in ones and a user's own);
    a method that can be extended is wrapped in a :class:`PrecisionTarget` when the config has a stop rule.

    Raises:
        KeyError: a method no one registered; ValueError: a stop rule for a method that cannot take more batches.
    """
    method = _method_of(config)
    inner = method.builder()(config, problem, check)
    return inner if config.stop_rule is None or not method.extensible else PrecisionTarget(inner, config)


def _method_of(config: ExperimentConfig) -> Method:
    """The registry's record of ``config.method``.

    Raises:
        KeyError: a method no one registered; ValueError: a stop rule (``rel_error``, ``require``) for a method that
            cannot take more final batches (:attr:`pemviz.estimators.registry.Method.extensible`)."""
    method = get_method(config.method)
    if config.stop_rule is not None and not method.extensible:
        raise ValueError(f"method {method.name} cannot add final batches: --rel-error and --require need a method "
                         "that can (adaptive, mc, naive50, mixed50, tilt)")
    return method


def run_plan(config: ExperimentConfig) -> RunPlan:
    """The :class:`RunPlan` the estimator of ``config.method`` states (:meth:`Estimator.plan`), without building it:
    e.g. to check a run's memory before its problem is loaded (:meth:`pemviz.estimators.registry.Method.run_plan`)."""
    method = _method_of(config)
    plan = method.run_plan(config)
    return plan if config.stop_rule is None or not method.extensible else RunPlan(plan.stages, open_ended=True)


def __getattr__(name: str) -> object:
    """:class:`AdaptiveMultilevelSplitting`, imported when first named (a run of another method never loads it)."""
    if name == "AdaptiveMultilevelSplitting":
        from pemviz.estimators.ams import AdaptiveMultilevelSplitting

        return AdaptiveMultilevelSplitting
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
