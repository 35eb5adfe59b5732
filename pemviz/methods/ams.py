"""Adaptive multilevel splitting's settings (``method = "ams"``): :class:`AmsSettings`, the
:attr:`pemviz.config.ExperimentConfig.ams` of a run; each field's row of :data:`pemviz.settings.SETTINGS` has owner
``ams``, and :class:`pemviz.estimators.ams.AdaptiveMultilevelSplitting` reads them. Light to import."""

from __future__ import annotations

from dataclasses import dataclass

AMS_STAGE = "ams"
"""The kind of splitting's stages in a run's plan (:class:`pemviz.core.plan.RunPlan`): its particles, then each batch
of iterations."""


@dataclass(frozen=True)
class AmsSettings:
    """The splitting of Cerou & Guyader (2007) as pemviz runs it; N, its particles, is the run's
    :attr:`pemviz.config.ExperimentConfig.n_per_stage`.

    Attributes:
    ams_killed: k, particles killed and resampled per AMS iteration at least (every tie at the level is killed
        too), 1 <= k < N (``method = "ams"``).
    ams_max_iterations: the most AMS iterations; a run stopped by it before its level reached the failure
        threshold gets the verdict ``doubtful``.
    ams_score: what ranks the AMS particles: ``robustness`` (the formula's classic robustness) or ``committor``
        (-log of the scenario's learned probability of failure, where it has one: e.g. the cut-in).
    ams_replicas: R, whole splitting runs from streams of their own; the estimate is their mean, its interval from
        their spread (:func:`pemviz.estimators.ams.replicas_estimate`); 1: one run and its genealogy's interval."""

    ams_killed: int = 10
    ams_max_iterations: int = 10_000
    ams_score: str = "robustness"
    ams_replicas: int = 1
