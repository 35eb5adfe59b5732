"""ExperimentConfig validation: one clear message naming the setting, the value and what is allowed."""

from __future__ import annotations

import pytest

from pemviz.config import PRESETS, ConfigError, ExperimentConfig


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("smoothing", 0.0, r"alpha must be in \(0, 1\]"),
        ("smoothing", 1.5, r"alpha must be in \(0, 1\]"),
        ("quantile_level", 1.0, r"sigma must be in \[0.5, 1\)"),
        ("quantile_level", 0.4, r"sigma must be in \[0.5, 1\)"),
        ("n_per_stage", 1, r"N must be an integer >= 2"),
        ("n_stages", 0, r"K must be an integer in \[1, 1000\]"),
        ("metric", "robust", r"use one of classic, agm, smooth-cumulative"),
        ("method", "mcmc", r"use one of adaptive, mc, naive50, mixed50"),
        ("seed", -1, r"seed must be an integer in \[0, 2\^64 - 1\]"),
    ],
)
def test_invalid_setting_is_rejected_with_its_name_value_and_range(field, value, message):
    with pytest.raises(ConfigError, match=message) as err:
        ExperimentConfig(**{field: value})
    assert field in str(err.value) and repr(value) in str(err.value)


def test_defaults_keep_the_papers_stages_with_a_larger_final_batch_and_count_2100_simulations():
    c = ExperimentConfig()
    assert (c.n_stages, c.n_per_stage, c.n_final, c.quantile_level, c.smoothing, c.metric, c.seed) == (
        10, 100, 1000, 0.95, 0.1, "classic", 0,
    )  # fmt: skip
    assert c.n_simulations == 100 + 10 * 100 + 1000
    assert ExperimentConfig(**PRESETS["paper"]).n_simulations == 100 + 10 * 100 + 100  # the paper's 1,200
    assert ExperimentConfig(method="mc", n_per_stage=10000).n_simulations == 10000


def test_default_is_the_state_ce_sampler_and_paper_turns_every_improvement_off():
    c = ExperimentConfig()
    assert (c.proposal_inputs, c.proposal_window, c.weights_until_failure, c.defensive) == ("state", True, True, 0.2)
    p = ExperimentConfig(**PRESETS["paper"])
    assert (p.proposal_inputs, p.proposal_window, p.weights_until_failure, p.smoothing_at_failure) == (
        "gap", False, False, None,
    )  # fmt: skip
    assert (p.elite_ties, p.pretrain_cap, p.defensive) == ("all", None, 0.0)


def test_authors_code_preset_is_the_paper_with_the_authors_training():
    c = ExperimentConfig(**PRESETS["authors-code"])
    assert (c.smoothing, c.ce_epochs, c.weights, c.final_estimate) == (0.5, 1000, "recomputed", "last-stage")
    assert c.proposal_inputs == "gap" and c.defensive == 0.0
    assert c.n_simulations == 100 + 10 * 100


@pytest.mark.parametrize("field, value", [("fit", "sgd"), ("fit_max_steps", 0), ("fit_rows", 0), ("fit_tolerance", 0.0)])
def test_fitting_settings_are_validated(field, value):
    with pytest.raises(ConfigError, match=field):
        ExperimentConfig(**{field: value})


def test_paper_presets_keep_the_full_batch_adam_fit():
    for name in ("paper", "authors-code"):
        cfg = ExperimentConfig(**PRESETS[name])
        assert (cfg.fit, cfg.fit_rows, cfg.fit_tolerance) == ("adam", None, None)
