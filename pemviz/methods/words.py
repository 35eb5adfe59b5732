"""The built-in methods' own words on a run (:attr:`pemviz.methods.Method.describe`): one Markdown sentence each on
the method, its stages and sizes, for the recording's description (:func:`pemviz.sinks.rerun_views.method_markdown`).
Each takes ``(config, plan, window)``: the run's :class:`~pemviz.config.ExperimentConfig`, its
:class:`~pemviz.core.plan.RunPlan` and the sampler window's words. Light to import."""

from __future__ import annotations

from typing import Any

AMS_SCORE_WORDS = {"robustness": "robustness", "committor": "-log of the scenario's learned committor"}
"""What ranks the AMS particles, in the recording's description of the run."""


def adaptive(cfg: Any, plan: Any, window: str) -> str:
    """Algorithm 1 of Innes & Ramamoorthy (2022): pretraining, K stages, the final batch."""
    n_final = plan.stages[-1].n_rollouts if plan.has_final_batch else None
    final = (
        f"a final batch of N_e = {n_final} rollouts gives the estimate"
        if n_final is not None
        else "the last stages give the estimate"
    )
    return (
        f"**adaptive importance sampling** (cross-entropy method, Innes & Ramamoorthy 2022): "
        f"{plan.stages[0].n_rollouts} rollouts of the target pretrain the proposal q(detect | d) (stage 0), "
        f"K = {plan.n_ce} stages of N = {cfg.n_per_stage} rollouts each move it toward the "
        f"failures (elites: robustness at or below the (1 - sigma) quantile gamma, sigma = "
        f"{cfg.adaptive.quantile_level}, smoothing alpha = {cfg.adaptive.smoothing}), and {final}."
    )


def mc(cfg: Any, plan: Any, window: str) -> str:
    """Plain Monte Carlo."""
    return f"plain **Monte Carlo** with the PEM: {cfg.n_per_stage} rollouts."


def naive50(cfg: Any, plan: Any, window: str) -> str:
    """The fixed 50 % detector of Innes & Ramamoorthy (2022), Table II."""
    return f"a **50 % detector** at every step, weighted by the PEM: {cfg.n_per_stage} rollouts."


def mixed50(cfg: Any, plan: Any, window: str) -> str:
    """The 50 % detector inside the sampler window."""
    return f"a **50 % detector inside the window** ({window}), the PEM outside: {cfg.n_per_stage} rollouts."


def ams(cfg: Any, plan: Any, window: str) -> str:
    """Adaptive multilevel splitting (Cerou & Guyader 2007)."""
    return (
        f"**adaptive multilevel splitting** on {AMS_SCORE_WORDS.get(cfg.ams.ams_score, cfg.ams.ams_score)} "
        "(Cerou & "
        f"Guyader 2007): N = {cfg.n_per_stage} "
        f"PEM rollouts, the k = {cfg.ams.ams_killed} highest killed per iteration and branched from survivors; "
        "each stage shows the particles after about N resamplings"
        + (
            f"; {cfg.ams.ams_replicas} such runs from streams of their own, their mean."
            if cfg.ams.ams_replicas > 1
            else "."
        )
    )


def tilt(cfg: Any, plan: Any, window: str) -> str:
    """Approximate zero-variance importance sampling (L'Ecuyer & Tuffin 2008)."""
    return (
        f"**approximate zero-variance importance sampling** (L'Ecuyer & Tuffin 2008): {cfg.n_per_stage} "
        "rollouts, each step's events drawn in proportion to their PEM probability times the scenario's "
        "approximate probability of failure after them, mixed with the PEM; the simulations count the "
        "look-aheads' steps too."
    )
