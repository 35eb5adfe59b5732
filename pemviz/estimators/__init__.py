"""Rare-event estimators, one per method of :data:`pemviz.methods.BUILTIN_METHODS`, behind one small interface
(:class:`~pemviz.estimators.base.Estimator`) that the engine drives stage by stage:
:class:`~pemviz.estimators.cross_entropy.CrossEntropy` (``adaptive``: Algorithm 1 of Innes & Ramamoorthy 2022,
improved), :class:`~pemviz.estimators.fixed.FixedSampler` (``mc``, ``naive50``, ``mixed50``),
:class:`~pemviz.estimators.ams.AdaptiveMultilevelSplitting` (``ams``),
:class:`~pemviz.estimators.tilt.CommittorTilt` (``tilt``) and :class:`~pemviz.estimators.precision.PrecisionTarget`
(``rel_error``, ``require``). Every method is a record of :mod:`pemviz.methods`, read by :func:`build_estimator` and
:func:`run_plan`. Each estimator's name has one import path, its module's."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pemviz.methods import Method
from pemviz.plugins import resolve

if TYPE_CHECKING:  # the package stays light: importing its registry (a config's checks) loads no estimator
    from pemviz.config import ExperimentConfig
    from pemviz.core.plan import RunPlan
    from pemviz.core.problems import Problem
    from pemviz.estimators.base import Check, Estimator


def build_estimator(config: ExperimentConfig, problem: Problem, check: Check | None = None) -> Estimator:
    """The estimator of ``config.method`` on ``problem`` (``check``: called between and inside fits, may raise),
    from the registry (:func:`pemviz.methods.get_method`), wrapped in a :class:`PrecisionTarget` when the config has
    a stop rule and in what the method runs after its stages (:attr:`pemviz.methods.Method.then`).

    Raises:
        KeyError: a method no one registered; ValueError: a stop rule for a method that cannot take more batches."""
    from pemviz.estimators.precision import PrecisionTarget

    method = _method_of(config)
    inner = method.builder()(config, problem, check)
    built = inner if config.stop_rule is None or not method.extensible else PrecisionTarget(inner, config)
    return built if method.then is None else resolve(method.then)(built, config, problem)


def check_runnable(config: ExperimentConfig, problem: Problem) -> None:
    """Refuse, before any rollout or output, a ``config`` whose method cannot run on ``problem`` (e.g. the
    cross-entropy fit of whole elite rollouts, the ``paper`` preset's, on a scene of several objects a step):
    :meth:`pemviz.methods.Method.conflict` with the problem's objects.

    Raises:
        ValueError: one line naming what cannot run and what to use instead."""
    conflict = config.method_record.conflict(config, problem.n_objects)
    if conflict is not None:
        raise ValueError(conflict[1])


def _method_of(config: ExperimentConfig) -> Method:
    """The registry's record of ``config.method`` (:attr:`pemviz.config.ExperimentConfig.method_record`).

    Raises:
        ValueError: a stop rule (``rel_error``, ``require``) for a method that
            cannot take more final batches (:attr:`pemviz.methods.Method.extensible`)."""
    method = config.method_record
    if config.stop_rule is not None and not method.extensible:
        raise ValueError(
            f"method {method.name} cannot add final batches: --rel-error and --require need a method "
            "that can (adaptive, mc, naive50, mixed50, tilt)"
        )
    return method


def run_plan(config: ExperimentConfig) -> RunPlan:
    """The :class:`RunPlan` the estimator of ``config.method`` states (:meth:`Estimator.plan`), without building it:
    e.g. to check a run's memory before its problem is loaded (:meth:`pemviz.methods.Method.run_plan`)."""
    from pemviz.core.plan import RunPlan

    method = _method_of(config)
    plan = method.run_plan(config)
    return plan if config.stop_rule is None or not method.extensible else RunPlan(plan.stages, open_ended=True)
