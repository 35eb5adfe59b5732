"""Rare-event estimators, one per method of :data:`pemviz.config.METHODS`, behind one small interface
(:class:`Estimator`) that the engine drives stage by stage.

- :class:`CrossEntropy` (``adaptive``): Algorithm 1 of Innes & Ramamoorthy (2022) with pemviz's improvements.
- :class:`FixedSampler` (``mc``, ``naive50``, ``mixed50``): one importance-weighted batch from a fixed detector.
- :class:`AdaptiveMultilevelSplitting` (``ams``): splitting of target rollouts on their robustness, no weights.
- :class:`~pemviz.estimators.tilt.CommittorTilt` (``tilt``): the scenario's own tilted proposal, one weighted batch.
- :class:`PrecisionTarget` (``rel_error``, ``require``): any of the first two, with final batches added until a
  relative precision or a decision on a requirement.
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

__all__ = [
    "AdaptiveMultilevelSplitting", "CappedDetector", "Check", "CrossEntropy", "DefensiveDetector", "Estimator",
    "FixedSampler", "PlannedStage", "PrecisionTarget", "RunPlan", "StageOutcome", "StagePlan", "break_ties",
    "build_estimator", "check_runnable",
    "failure_steps", "log_p_before_failure", "log_weight", "mixed50", "monte_carlo", "naive50", "run_plan",
]  # fmt: skip


def build_estimator(config: ExperimentConfig, problem: Problem, check: Check | None = None) -> Estimator:
    """The estimator of ``config.method`` on ``problem`` (``check``: called between and inside fits, may raise).

    The baselines draw ``config.n_per_stage`` rollouts and stop their weights at the failure step with
    ``config.weights_until_failure``, like the adaptive sampler's.
    """
    if config.method == "ams":
        from pemviz.estimators.ams import AdaptiveMultilevelSplitting

        return AdaptiveMultilevelSplitting(config, problem, check)
    if config.method == "adaptive":
        inner: CrossEntropy | FixedSampler = CrossEntropy(config, problem, check)
    elif config.method == "tilt":
        from pemviz.estimators.tilt import CommittorTilt

        inner = CommittorTilt(problem, config.n_per_stage, config.weights_until_failure, config.seed)
    else:
        baseline = {"mc": monte_carlo, "naive50": naive50, "mixed50": mixed50}[config.method]
        inner = baseline(problem, config.n_per_stage, config.weights_until_failure, config.seed)
    return inner if config.stop_rule is None else PrecisionTarget(inner, config)


def run_plan(config: ExperimentConfig) -> RunPlan:
    """The :class:`RunPlan` the estimator of ``config.method`` states (:meth:`Estimator.plan`), without building it:
    e.g. to check a run's memory before its problem is loaded."""
    if config.method == "ams":
        from pemviz.estimators.ams import AdaptiveMultilevelSplitting

        return AdaptiveMultilevelSplitting.run_plan(config)
    plan = CrossEntropy.run_plan(config) if config.method == "adaptive" else FixedSampler.run_plan(config.n_per_stage)
    return plan if config.stop_rule is None else RunPlan(plan.stages, open_ended=True)


def __getattr__(name: str) -> object:
    """:class:`AdaptiveMultilevelSplitting`, imported when first named (a run of another method never loads it)."""
    if name == "AdaptiveMultilevelSplitting":
        from pemviz.estimators.ams import AdaptiveMultilevelSplitting

        return AdaptiveMultilevelSplitting
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
