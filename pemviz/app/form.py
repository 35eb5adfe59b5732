"""The panel's experiment form: what was typed, parsed exactly, with every error in plain words.

Numbers are typed into text fields and parsed here, so the form never rounds, rescales or silently
keeps an earlier value: ``12.5`` in N is an error (N counts rollouts), ``1e-3`` in alpha is 0.001, an
empty field is an error. :func:`parse_form` returns the config and, per field, the reason it is
refused, all at once. :func:`run_cost` says what a run will take before it starts (the model of
:mod:`pemviz.engine.cost`), and :func:`run_label` names a run by the settings that differ from the defaults. No
viser here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from pemviz.config import SETTINGS, ConfigError, ExperimentConfig, Setting
from pemviz.engine import cost
from pemviz.engine.cost import N_STEPS, RunCost


NUMBER_FIELDS: tuple[Setting, ...] = tuple(SETTINGS[name] for name in (
    "smoothing", "quantile_level", "n_stages", "n_per_stage", "n_final", "seed", "ce_epochs", "pretrain_rollouts",
    "pretrain_epochs", "learning_rate", "rel_error", "max_sims", "max_time_s",
))  # fmt: skip
"""The numbers the form shows, each with its :class:`~pemviz.config.Setting` (label, words, range, hint)."""
FIELDS_BY_KEY = {f.name: f for f in NUMBER_FIELDS}

def parse_number(field: Setting, text: str) -> tuple[float | int | None, str]:
    """``(value, "")`` for a valid entry, ``(None, reason)`` otherwise; the reason names the field in words.

    Parsed by :meth:`pemviz.config.Setting.parse` (as the command line's flags are), then checked against the
    setting's range. Nothing is rounded or clipped.
    """
    if field.optional and str(text).strip() == "":  # an optional setting left empty: its default (None)
        return None, ""
    try:
        value = field.parse(text)
    except ValueError as exc:
        return None, f"{field.label}: {exc}"
    if not field.accepts(value):
        return None, f"{field.label}: {str(text).strip()} is out of range; {field.words} must be {field.allowed}"
    return value, ""


def format_number(field: Setting, value: Any) -> str:
    """The text a field shows for a config value (``repr`` of floats: ``0.001`` stays ``0.001``; empty for None)."""
    if value is None:
        return ""
    if field.integer:
        return str(int(value))
    return repr(float(value))


@dataclass(frozen=True)
class FormResult:
    """What the form describes: the config, or the errors (field key -> message; ``""`` for cross-field ones)."""

    config: ExperimentConfig | None
    errors: dict[str, str]

    @property
    def ok(self) -> bool:
        return self.config is not None


def parse_form(texts: dict[str, str], choices: dict[str, Any], base: ExperimentConfig | None = None) -> FormResult:
    """Parse every number field and build the config; every error at once.

    Args:
        texts: field key -> the text typed (keys of :data:`NUMBER_FIELDS`).
        choices: field key -> value for the dropdowns (metric, pem, sim, method, ...).
        base: settings the form does not show (default: :class:`ExperimentConfig`'s defaults).
    """
    errors: dict[str, str] = {}
    values: dict[str, Any] = {}
    for key, text in texts.items():
        value, error = parse_number(FIELDS_BY_KEY[key], text)
        if error:
            errors[key] = error
        else:
            values[key] = value
    known = {f.name for f in dataclasses.fields(ExperimentConfig)}
    values.update({k: (None if k == "pem" and v in ("", None) else v) for k, v in choices.items() if k in known})
    if errors:
        return FormResult(None, errors)
    try:
        return FormResult(dataclasses.replace(base or ExperimentConfig(), **values), {})
    except (ConfigError, TypeError) as exc:
        return FormResult(None, {"": str(exc)})


def run_cost(cfg: ExperimentConfig, n_steps: int = N_STEPS) -> RunCost:
    """What ``cfg``'s run will take (:func:`pemviz.engine.cost.run_cost` of the plan its estimator states,
    :func:`pemviz.estimators.run_plan`): simulations, memory of the largest batch, expected seconds."""
    from pemviz.engine.experiment import stream_above  # the engine and the estimators import torch: only when asked
    from pemviz.estimators import run_plan

    return cost.run_cost(cfg, run_plan(cfg), n_steps, stream_above(cfg))


def setting_name(key: str) -> str:
    """The name a setting goes by in labels and the compare table (``smoothing`` -> ``alpha``): its
    :attr:`~pemviz.config.Setting.label`."""
    return SETTINGS[key].label


def setting_value(value: Any) -> str:
    if value is None:
        return "default"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def run_label(run_id: int, cfg: ExperimentConfig, defaults: ExperimentConfig | None = None) -> str:
    """``run 3 · agm, alpha 0.2, K 8``: the run number, the metric and every setting that differs from ``defaults``."""
    base = defaults or ExperimentConfig()
    parts = [cfg.metric]
    for f in dataclasses.fields(ExperimentConfig):
        if f.name == "metric":
            continue
        value = getattr(cfg, f.name)
        if value != getattr(base, f.name):
            parts.append(f"{setting_name(f.name)} {setting_value(value)}")
    return f"run {run_id} · " + ", ".join(parts)
