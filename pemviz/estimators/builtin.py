"""The built-in methods' builders and plans, as :mod:`pemviz.estimators.registry` names them (each imported when a
run first uses it): ``adaptive`` (:class:`pemviz.estimators.cross_entropy.CrossEntropy`), ``mc``, ``naive50``,
``mixed50`` (:mod:`pemviz.estimators.fixed`), ``ams`` (:class:`pemviz.estimators.ams.AdaptiveMultilevelSplitting`) and
``tilt`` (:class:`pemviz.estimators.tilt.CommittorTilt`).

Each builder is ``(config, problem, check) -> Estimator``: the baselines draw ``config.n_per_stage`` rollouts and stop
their weights at the failure step with ``config.weights_until_failure``, like the adaptive sampler's.
"""

from __future__ import annotations

from typing import Any

from pemviz.core.plan import RunPlan
from pemviz.estimators.base import Check, Estimator


def adaptive(config: Any, problem: Any, check: Check | None = None) -> Estimator:
    """Cross-entropy adaptive importance sampling (:class:`pemviz.estimators.cross_entropy.CrossEntropy`)."""
    from pemviz.estimators.cross_entropy import CrossEntropy

    return CrossEntropy(config, problem, check)


def adaptive_plan(config: Any) -> RunPlan:
    """The cross-entropy sampler's stages, from the config alone."""
    from pemviz.estimators.cross_entropy import CrossEntropy

    return CrossEntropy.run_plan(config)


def mc(config: Any, problem: Any, check: Check | None = None) -> Estimator:
    """Plain Monte Carlo: one batch drawn by the PEM itself (:func:`pemviz.estimators.fixed.monte_carlo`)."""
    from pemviz.estimators.fixed import monte_carlo

    return monte_carlo(problem, config.n_per_stage, config.weights_until_failure, config.seed)


def naive50(config: Any, problem: Any, check: Check | None = None) -> Estimator:
    """One batch by a 50 % detector (:func:`pemviz.estimators.fixed.naive50`)."""
    from pemviz.estimators.fixed import naive50 as build

    return build(problem, config.n_per_stage, config.weights_until_failure, config.seed)


def mixed50(config: Any, problem: Any, check: Check | None = None) -> Estimator:
    """One batch by 50 % inside the window, the PEM outside (:func:`pemviz.estimators.fixed.mixed50`)."""
    from pemviz.estimators.fixed import mixed50 as build

    return build(problem, config.n_per_stage, config.weights_until_failure, config.seed)


def ams(config: Any, problem: Any, check: Check | None = None) -> Estimator:
    """Adaptive multilevel splitting (:class:`pemviz.estimators.ams.AdaptiveMultilevelSplitting`)."""
    from pemviz.estimators.ams import AdaptiveMultilevelSplitting

    return AdaptiveMultilevelSplitting(config, problem, check)


def ams_plan(config: Any) -> RunPlan:
    """Splitting's stages, from the config alone."""
    from pemviz.estimators.ams import AdaptiveMultilevelSplitting

    return AdaptiveMultilevelSplitting.run_plan(config)


def tilt(config: Any, problem: Any, check: Check | None = None) -> Estimator:
    """The scenario's own tilted proposal (:class:`pemviz.estimators.tilt.CommittorTilt`)."""
    from pemviz.estimators.tilt import CommittorTilt

    return CommittorTilt(problem, config.n_per_stage, config.weights_until_failure, config.seed)
