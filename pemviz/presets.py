"""Named sampler settings (presets), each applied on top of :class:`pemviz.config.ExperimentConfig`'s defaults:
the recommended sampler, the paper's, the authors' code's, a quick one and the default before its mixture over
rollouts. Read by ``pemviz run --preset``, the panel's preset dropdown, ``validate`` and ``tables``."""

from __future__ import annotations

from typing import Any

PAPER: dict[str, Any] = {
    "final_estimate": "fresh",
    "proposal_inputs": "gap",
    "proposal_window": False,
    "weights_until_failure": False,
    "smoothing_at_failure": None,
    "final_smoothing": None,
    "elite_ties": "all",
    "pretrain_cap": None,
    "defensive": 0.0,
    "target_share": 0.0,
    "plain_share": 0.0,
    "fit_all_failures": False,
    "fit_weights": "sampler",
    "fit": "adam",
    "fit_rows": None,
    "fit_tolerance": None,
    "pretrain_epochs": 1000,
    "n_final": 100,
    "uniforms": "iid",
    "learning_rate": 1e-3,
    "ce_epochs": 500,
    "plain_fallback": 0,
}
"""The sampler exactly as Innes & Ramamoorthy (2022) describe it (Algorithm 1, eq. 10-11): a gap-only proposal
fitted on every step by full-batch Adam, weights over T - 1 steps, every tie at gamma an elite, no defensive
mixture, i.i.d. uniforms, and no plain Monte Carlo after it."""

DEFAULT_PRESET = "state-ce"
"""The recommended sampler and the default of ``ExperimentConfig.of()``, ``pemviz run``, the panel, ``validate`` and
``tables``: cross-entropy on a state-dependent proposal (see :class:`ExperimentConfig`)."""

PRESETS: dict[str, dict[str, Any]] = {
    DEFAULT_PRESET: {},
    "paper": dict(PAPER),
    "authors-code": {
        **PAPER,
        "smoothing": 0.5,
        "ce_epochs": 1000,
        "weights": "recomputed",
        "final_estimate": "last-stage",
    },
    "quick": {"n_stages": 8, "ce_epochs": 200, "pretrain_rollouts": 50, "pretrain_epochs": 200, "learning_rate": 2e-2},
    "state-ce-step": {
        "target_share": 0.0,
        "plain_share": 0.0,
        "fit_all_failures": False,
        "fit_weights": "sampler",
        "pool_weights": "rollouts",
        "smoothing_at_failure": 1.0,
        "final_smoothing": None,
        "uniforms": "iid",
        "learning_rate": 1e-3,
        "ce_epochs": 500,
        "skip_decided": False,
        "fit_rows": 10_000,
        "fit_tolerance": None,
    },
}
"""Named settings, each applied on top of the defaults.

``state-ce`` (the default): cross-entropy on a proposal over the whole observed state, weights up to the failure, a
defensive mixture per step and over whole rollouts, Array-RQMC detections, stages pooled by j^2 n_j (its accuracy:
docs/validation.md). ``state-ce-step``: without the mixture over rollouts. ``paper``: the sampler as published.
``authors-code``: how the authors' public code ran it (alpha 0.5, 1000 epochs, the last stage's batch as the
estimate). ``quick``: the default with fewer, larger Adam steps."""

PRESET_HELP: dict[str, str] = {
    DEFAULT_PRESET: "the recommended sampler, right against exact answers (the user guide's Validation page)",
    "paper": "the sampler as published, biased low at the default budget",
    "authors-code": "as the authors' public code ran it",
    "quick": "the recommended sampler with fewer, larger Adam steps: a run of a few seconds",
    "state-ce-step": "the recommended sampler before the mixture over whole rollouts",
}
"""What each preset is, in one line without measured figures: the words of ``pemviz run --preset``'s help, the panel's
preset hint and the user guide."""


def preset_help(names=None) -> str:
    """``state-ce: the recommended sampler ...; paper: ...``: :data:`PRESET_HELP` of ``names`` (default every preset),
    one clause each."""
    return "; ".join(f"{name}: {PRESET_HELP[name]}" for name in (names or PRESETS))
