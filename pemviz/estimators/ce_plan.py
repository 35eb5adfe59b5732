"""The cross-entropy sampler's stages, from its settings alone (:func:`adaptive_run_plan`): light to import, so that a
config can count its simulations (:attr:`pemviz.config.ExperimentConfig.n_simulations`) without loading the sampler."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pemviz.core.plan import RunPlan

if TYPE_CHECKING:
    from pemviz.config import ExperimentConfig


def adaptive_run_plan(config: ExperimentConfig) -> RunPlan:
    """Stage 0 pretraining (``pretrain_rollouts``), 1..K cross-entropy stages of N, K+1 the final batch of N_e (none
    with ``final_estimate = "last-stage"``)."""
    ce = config.adaptive
    final = [(ce.n_stages + 1, "final", ce.n_final)] if ce.has_final_batch else []
    return RunPlan.of(
        [(0, "pretrain", ce.pretrain_rollouts)]
        + [(k, "ce", config.n_per_stage) for k in range(1, ce.n_stages + 1)]
        + final
    )
