"""The panel's experiment form: what was typed, parsed exactly, with every error in plain words.

Numbers are typed into text fields and parsed here, so the form never rounds, rescales or silently
keeps an earlier value: ``12.5`` in N is an error (N counts rollouts), ``1e-3`` in alpha is 0.001, an
empty field is an error. :func:`parse_form` returns the config and, per field, the reason it is
refused, all at once. :func:`run_cost` says what a run will take before it starts, and
:func:`run_label` names a run by the settings that differ from the defaults. No viser here.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass
from typing import Any

from pemviz.config import MAX_EPOCHS, MAX_SEED, MAX_STAGES, ConfigError, ExperimentConfig


@dataclass(frozen=True)
class NumberField:
    """A number typed into the form.

    Attributes:
        key: the :class:`ExperimentConfig` field.
        label: the field's label in the panel (the paper's symbol where it has one).
        words: what it is, in plain words (used in the error messages).
        integer: whole numbers only.
        lo, hi: the allowed range; ``lo_open`` / ``hi_open`` exclude the end.
        hint: the help text beside the field.
    """

    key: str
    label: str
    words: str
    integer: bool
    lo: float
    hi: float = math.inf
    lo_open: bool = False
    hi_open: bool = False
    hint: str = ""

    @property
    def allowed(self) -> str:
        if self.integer:
            lo = int(self.lo)
            return f"a whole number >= {lo}" if math.isinf(self.hi) else f"a whole number in [{lo}, {int(self.hi)}]"
        left = "(" if self.lo_open else "["
        right = ")" if self.hi_open else "]"
        return f"a number > {self.lo:g}" if math.isinf(self.hi) else f"a number in {left}{self.lo:g}, {self.hi:g}{right}"


NUMBER_FIELDS: tuple[NumberField, ...] = (
    NumberField("smoothing", "alpha", "the smoothing alpha", False, 0.0, 1.0, lo_open=True,
                hint="smoothing alpha in (0, 1]: the weight of the new fit in each stage's update"),
    NumberField("quantile_level", "sigma", "the quantile level sigma", False, 0.5, 1.0, hi_open=True,
                hint="quantile level sigma in [0.5, 1): the elites are the (1 - sigma) least robust"),
    NumberField("n_stages", "K", "the number of cross-entropy stages K", True, 1, MAX_STAGES,
                hint="cross-entropy stages"),
    NumberField("n_per_stage", "N", "the rollouts per stage N", True, 2, hint="rollouts per CE stage"),
    NumberField("n_final", "N_e", "the rollouts of the final estimate N_e", True, 1, hint="rollouts of the final batch"),
    NumberField("seed", "seed", "the seed", True, 0, MAX_SEED, hint="random seed: the same seed gives the same run"),
    NumberField("ce_epochs", "CE epochs", "the Adam epochs per stage", True, 1, MAX_EPOCHS),
    NumberField("pretrain_rollouts", "pretrain rollouts", "the pretraining rollouts", True, 1),
    NumberField("pretrain_epochs", "pretrain epochs", "the pretraining epochs", True, 1, MAX_EPOCHS),
    NumberField("learning_rate", "learning rate", "the learning rate", False, 0.0, lo_open=True),
)  # fmt: skip
FIELDS_BY_KEY = {f.key: f for f in NUMBER_FIELDS}

_NUMBER = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$")


def parse_number(field: NumberField, text: str) -> tuple[float | int | None, str]:
    """``(value, "")`` for a valid entry, ``(None, reason)`` otherwise; the reason names the field in words.

    Accepts decimal and scientific notation (``0.2``, ``1e-3``, ``1e5``) with surrounding spaces; whole-number
    fields accept only values that are whole (``1e5`` yes, ``12.5`` no). Nothing is rounded or clipped.
    """
    raw = str(text).strip()
    if raw == "":
        return None, f"{field.label}: empty; type {field.allowed} ({field.words})"
    if not _NUMBER.match(raw):
        return None, f"{field.label}: {raw!r} is not a number; type {field.allowed} ({field.words})"
    if field.integer and re.fullmatch(r"[+-]?\d+", raw):
        value: float | int = int(raw)  # exact, also beyond float64's 2^53
    else:
        value = float(raw)
    if not math.isfinite(value):
        return None, f"{field.label}: {raw!r} is too large; type {field.allowed} ({field.words})"
    if field.integer and isinstance(value, float):
        if not value.is_integer():
            return None, f"{field.label}: {raw} is not a whole number; {field.words} must be {field.allowed}"
        value = int(value)
    too_low = value <= field.lo if field.lo_open else value < field.lo
    too_high = value >= field.hi if field.hi_open else value > field.hi
    if too_low or too_high:
        return None, f"{field.label}: {raw} is out of range; {field.words} must be {field.allowed}"
    return value, ""


def format_number(field: NumberField, value: Any) -> str:
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


SHORT_NAMES = {
    "smoothing": "alpha", "quantile_level": "sigma", "n_stages": "K", "n_per_stage": "N", "n_final": "N_e",
    "sim": "simulator", "pem": "PEM", "final_estimate": "final", "ce_epochs": "CE epochs",
    "pretrain_rollouts": "pretrain rollouts", "pretrain_epochs": "pretrain epochs", "learning_rate": "lr",
}  # fmt: skip


def setting_name(key: str) -> str:
    """The name a setting goes by in labels and the compare table (``smoothing`` -> ``alpha``)."""
    return SHORT_NAMES.get(key, key.replace("_", " "))


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
