"""The panel's experiment form: what was typed, parsed exactly, with every error in plain words.

Numbers are typed into text fields and parsed here, so the form never rounds, rescales or silently
keeps an earlier value: ``12.5`` in N is an error (N counts rollouts), ``1e-3`` in alpha is 0.001, an
empty field is an error. :func:`parse_form` returns the config and, per field, the reason it is
refused, all at once. :func:`run_cost` says what a run will take before it starts, and
:func:`run_label` names a run by the settings that differ from the defaults. No viser here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from pemviz.config import SETTINGS, ConfigError, ExperimentConfig, Setting


NUMBER_FIELDS: tuple[Setting, ...] = tuple(SETTINGS[name] for name in (
    "smoothing", "quantile_level", "n_stages", "n_per_stage", "n_final", "seed", "ce_epochs", "pretrain_rollouts",
    "pretrain_epochs", "learning_rate",
))  # fmt: skip
"""The numbers the form shows, each with its :class:`~pemviz.config.Setting` (label, words, range, hint)."""
FIELDS_BY_KEY = {f.name: f for f in NUMBER_FIELDS}

def parse_number(field: Setting, text: str) -> tuple[float | int | None, str]:
    """``(value, "")`` for a valid entry, ``(None, reason)`` otherwise; the reason names the field in words.

    Parsed by :meth:`pemviz.config.Setting.parse` (as the command line's flags are), then checked against the
    setting's range. Nothing is rounded or clipped.
    """
    try:
        value = field.parse(text)
    except ValueError as exc:
        return None, f"{field.label}: {exc}"
    if not field.accepts(value):
        return None, f"{field.label}: {str(text).strip()} is out of range; {field.words} must be {field.allowed}"
    return value, ""


def format_number(field: Setting, value: Any) -> str:
    """The text a field shows for a config value (``repr`` of floats: ``0.001`` stays ``0.001``)."""
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


SIM_S_PER_ROLLOUT = {"batched": 3e-5, "highway-env": 4e-3}
"""Seconds to simulate one 100-step rollout on one core (benchmarks/sim_speed.py, order of magnitude)."""
EPOCH_S_PER_STEP = 3e-7
"""Seconds of one Adam epoch of the proposal per rollout step (order of magnitude, 2-core machine)."""
BYTES_PER_STEP = 3 * 8 + 1 + 8 + 8
"""A rollout step held in memory: 3 float64 observations, the detection, log p and log q."""
CONFIRM_SIMULATIONS = 500_000
CONFIRM_SECONDS = 120.0
CONFIRM_BYTES = 2 * 1024**3


@dataclass(frozen=True)
class RunCost:
    """What a run will take: simulations, the largest batch in memory (bytes), expected seconds (rough)."""

    simulations: int
    memory_bytes: int
    seconds: float

    @property
    def needs_confirm(self) -> bool:
        """Above any limit (:data:`CONFIRM_SIMULATIONS`, :data:`CONFIRM_SECONDS`, :data:`CONFIRM_BYTES`)."""
        return (
            self.simulations > CONFIRM_SIMULATIONS or self.seconds > CONFIRM_SECONDS or self.memory_bytes > CONFIRM_BYTES
        )

    def text(self) -> str:
        mem = self.memory_bytes / 1024**2
        return (
            f"{self.simulations:,} simulations, {mem:,.1f} MB per batch, about {_duration(self.seconds)}"
        )


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{max(1.0, seconds):.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def run_cost(cfg: ExperimentConfig, n_steps: int = 100, stream_above: int | None = None) -> RunCost:
    """Simulations (:attr:`ExperimentConfig.n_simulations`), memory of the largest batch, expected seconds.

    A stage above ``stream_above`` rollouts (default :data:`pemviz.engine.STREAM_ABOVE`) is simulated in chunks, so
    it does not count in full towards memory.
    """
    if stream_above is None:
        from pemviz.engine import STREAM_ABOVE as stream_above  # the engine imports torch: only when asked
    sims = cfg.n_simulations
    biggest = max(min(cfg.n_per_stage, stream_above), min(cfg.n_final, stream_above), cfg.pretrain_rollouts)
    seconds = sims * SIM_S_PER_ROLLOUT.get(cfg.sim, 4e-3)
    if cfg.method == "adaptive":
        seconds += EPOCH_S_PER_STEP * n_steps * (
            cfg.n_stages * cfg.ce_epochs * cfg.n_per_stage + cfg.pretrain_epochs * cfg.pretrain_rollouts
        )
    return RunCost(int(sims), int(biggest * n_steps * BYTES_PER_STEP), float(seconds))


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
