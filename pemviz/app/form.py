"""The panel's experiment form: what was typed, parsed exactly, with every error in plain words.

Numbers are typed into text fields and parsed here, never rounded or rescaled (``12.5`` in N is an error, ``1e-3`` in
alpha is 0.001). :func:`parse_form` returns the config and, per field, the reason it is refused, all at once. No viser.
"""

from __future__ import annotations

import dataclasses
import time
import types
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from pemviz.config import ConfigError, ExperimentConfig
from pemviz.engine import cost
from pemviz.engine.cost import N_STEPS, RunCost
from pemviz.engine.resources import LoadReading
from pemviz.methods import method_or_none
from pemviz.scenarios.odd import is_odd
from pemviz.scenarios.parameters import PairValue, Parameter, ParameterError, Value, check_pairs, parse_assignment
from pemviz.scenarios.registry import get
from pemviz.settings import PANEL_PLACES, SETTINGS, Setting, rows_of

NUMBERS = ("int", "real")
"""The kinds of setting the form types as a number (a text field); a ``choice`` is a dropdown."""


def panel_rows(rows: Iterable[Setting], place: str) -> tuple[Setting, ...]:
    """The rows of ``rows`` the panel's form shows at ``place`` (:attr:`pemviz.settings.Setting.panel`: ``main`` or
    ``advanced``), in their order: a method's setting is in the form by its own row, no list here."""
    return tuple(s for s in rows if s.panel == place)


PANEL_ROWS: tuple[Setting, ...] = tuple(s for place in PANEL_PLACES for s in panel_rows(SETTINGS.values(), place))
"""The settings the form shows, ``main`` first: every row of :data:`pemviz.settings.SETTINGS` with a
:attr:`~pemviz.settings.Setting.panel` place (a number a text field, a choice a dropdown)."""
NUMBER_FIELDS: tuple[Setting, ...] = tuple(s for s in PANEL_ROWS if s.kind in NUMBERS)
"""The numbers the form shows, each with its :class:`~pemviz.settings.Setting` (label, words, range, hint)."""
FIELDS_BY_KEY = {f.name: f for f in NUMBER_FIELDS}


def parse_number(field: Setting, text: str) -> tuple[float | int | None, str]:
    """``(value, "")`` for a valid entry, ``(None, reason)`` otherwise; the reason names the field in words.

    Parsed by :meth:`pemviz.settings.Setting.parse` (as the command line's flags are), then checked against the
    setting's range. Nothing is rounded or clipped."""
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
    """The text a field shows for a config value (``repr`` of floats: ``0.001`` stays ``0.001``; empty for None;
    ``true`` / ``false`` for a bool, a choice or a text as it is)."""
    if value is None:
        return ""
    if field.kind == "bool":
        return "true" if value else "false"
    if field.kind not in NUMBERS:
        return str(value)
    if field.integer:
        return str(int(value))
    return repr(float(value))


def own_rows(method: str) -> tuple[Setting, ...]:
    """The rows of the registered method ``method``'s own settings (:attr:`pemviz.methods.Method.settings`, each
    field's :func:`pemviz.settings.setting`), in their order: the fields of the form's folder *method settings*;
    ``()`` for a method without (the built-in ones but the state method) or an unknown name."""
    record = method_or_none(method)
    kind = None if record is None else record.settings_class()
    if record is None or kind is None:
        return ()
    return tuple(rows_of(kind, record.name).values())


def parse_own(method: str, texts: Mapping[str, str]) -> tuple[dict[str, Any], dict[str, str]]:
    """The settings of ``method``'s own typed into its fields, each parsed and checked by its row as its flag on
    ``pemviz run`` is (:func:`parse_number`; a bool ``true`` / ``false``, a choice or text as typed).

    Args:
        method: a registered method's name.
        texts: setting name -> the text typed into its field.
    Returns:
        ``(values, errors)``: name -> value of each valid field (the config takes them by name,
        :meth:`pemviz.config.ExperimentConfig.of`), and name -> one line of each refused one."""
    rows = {s.name: s for s in own_rows(method)}
    values: dict[str, Any] = {}
    errors: dict[str, str] = {}
    for name, text in texts.items():
        value: Any
        row = rows.get(name)
        if row is None:
            errors[name] = f"{name!r} is not a setting of method {method}"
            continue
        if row.kind in NUMBERS:
            value, error = parse_number(row, text)
        else:
            raw = str(text).strip()
            if row.optional and raw.lower() in ("", "none"):
                value = None
            elif row.kind == "bool":
                value = {"true": True, "false": False}.get(raw.lower(), raw)
            else:
                value = raw
            ok = row.accepts(value)
            error = "" if ok else f"{row.label}: {raw!r} is not allowed; {row.words} must be {row.allowed}"
        if error:
            errors[name] = error
        else:
            values[name] = value
    return values, errors


PARAM_KEY = "param:"
"""The prefix of a scenario parameter's key among a form's errors (``param:`` and the parameter's name)."""


def param_key(name: str) -> str:
    """The key of the scenario parameter ``name`` in :attr:`FormResult.errors`."""
    return PARAM_KEY + name


def format_param(p: Parameter, value: Value) -> str:
    """The text a parameter's field shows for ``value``: ``repr`` of a float (``20.0``), digits for an int,
    ``true`` / ``false`` for a bool."""
    if p.kind == "bool":
        return "true" if value else "false"
    return str(int(value)) if p.kind == "int" else repr(float(value))


def parse_params(scenario: str, texts: Mapping[str, str]) -> tuple[tuple[tuple[str, PairValue], ...], dict[str, str]]:
    """The changed parameters of ``scenario`` and the errors of its parameter fields: each text parsed by its
    parameter's kind, a value equal to the default left out, the others checked alone, then together.

    Args:
        scenario: a registered scenario's name.
        texts: parameter name -> the text typed into its field.
    Returns:
        ``(pairs, errors)``: the ``(name, value)`` pairs that differ from the defaults, in the order of ``texts``, and
        the errors by :func:`param_key` of the field, or under ``""`` for values refused together. An unknown scenario
        gives no pairs and no errors (the config refuses it)."""
    try:
        found = get(scenario)
    except KeyError:
        return (), {}
    params = {p.name: p for p in found.parameters()}
    pairs: list[tuple[str, PairValue]] = []
    errors: dict[str, str] = {}
    for name, text in texts.items():
        try:
            if name not in params:
                raise ParameterError(f"{name!r} is not a parameter of the {scenario} scenario")
            if is_odd(str(text).strip()):  # ~uniform(a, b): drawn per rollout over an ODD, as --param NAME~DIST
                pairs.append(parse_assignment(scenario, f"{name}{text.strip()}"))
                continue
            value = params[name].parse(text)
        except ParameterError as exc:
            errors[param_key(name)] = str(exc)
            continue
        if value != params[name].default:
            pairs.append((name, value))

    def check(given: list[tuple[str, PairValue]]) -> None:
        if any(is_odd(v) for _, v in given):
            check_pairs(scenario, tuple(given))
        else:
            found.build_params(dict(given))

    valid = [pair for pair in pairs if param_key(pair[0]) not in errors]
    if valid:
        try:
            check(valid)  # the values together (a field may be valid only with another one changed)
        except ParameterError as together:
            alone: dict[str, str] = {}
            for pair in valid:  # blame the fields refused even with the others at their defaults
                try:
                    check([pair])
                except ParameterError as exc:
                    alone[param_key(pair[0])] = str(exc)
            errors.update(alone or {"": str(together)})
    return tuple(pairs), errors


@dataclass(frozen=True)
class FormResult:
    """What the form describes: the config, or the errors (field key -> message; :func:`param_key` of a scenario
    parameter; ``""`` for cross-field ones)."""

    config: ExperimentConfig | None
    errors: dict[str, str]

    @property
    def ok(self) -> bool:
        return self.config is not None


def parse_form(
    texts: dict[str, str],
    choices: dict[str, Any],
    base: ExperimentConfig | None = None,
    params: Mapping[str, str] | None = None,
    own: Mapping[str, str] | None = None,
) -> FormResult:
    """Parse every number field and build the config; every error at once.

    Args:
        texts: field key -> the text typed (keys of :data:`NUMBER_FIELDS`).
        choices: field key -> value for the dropdowns (metric, pem, sim, method, ...).
        base: settings the form does not show (default: :class:`ExperimentConfig`'s defaults).
        params: the chosen scenario's parameter fields, name -> the text typed (:func:`parse_params`): the config's
            ``scenario_params`` are the changed ones (``()``: none changed). None: ``base``'s are kept.
        own: the chosen method's own settings' fields, name -> the text typed (:func:`parse_own`): each goes into the
            config by its name, as its flag on ``pemviz run`` does; errors by the setting's name. None or ``{}``:
            ``base``'s settings if it is of that method, else the method's defaults."""
    errors: dict[str, str] = {}
    values: dict[str, Any] = {}
    for key, text in texts.items():
        value, error = parse_number(FIELDS_BY_KEY[key], text)
        if error:
            errors[key] = error
        else:
            values[key] = value
    known = set(SETTINGS)
    values.update({k: (None if k == "pem" and v in ("", None) else v) for k, v in choices.items() if k in known})
    if params is not None:
        pairs, param_errors = parse_params(values.get("scenario", (base or ExperimentConfig.of()).scenario), params)
        errors.update(param_errors)
        values["scenario_params"] = pairs
    if own:
        own_values, own_errors = parse_own(values.get("method", (base or ExperimentConfig.of()).method), own)
        errors.update(own_errors)
        values.update(own_values)
    if errors:
        return FormResult(None, errors)
    try:
        return FormResult((base or ExperimentConfig.of()).replace(**values), {})
    except (ConfigError, TypeError) as exc:
        return FormResult(None, {"": str(exc)})


_HORIZONS: dict[tuple[Any, ...], tuple[int, float, Any, Any]] = {}


def horizon(cfg: ExperimentConfig) -> tuple[int, float]:
    """T, the steps of a rollout of ``cfg``'s problem, and its look-ahead's seconds a rollout, the problem built once
    per scene; (:data:`pemviz.engine.cost.N_STEPS`, 0) where it cannot be built (the run then says why)."""
    return _horizon(cfg)[:2]


def _key(cfg: ExperimentConfig) -> tuple[Any, ...]:
    return (cfg.scenario, cfg.scenario_params, cfg.value("pem"), cfg.margin, cfg.sim)


def _horizon(cfg: ExperimentConfig) -> tuple[int, float, Any, Any]:
    """:func:`horizon`, what the problem states of its answer (its ``exact_log_p``, ``reference`` and
    ``verdict_cap``, as the run's :class:`~pemviz.engine.events.RunStarted` carries them) and the problem (both None
    where it cannot be built)."""
    from pemviz.scenarios.registry import problem_for

    key = _key(cfg)
    if key not in _HORIZONS:
        try:
            problem = problem_for(cfg)
            stated = types.SimpleNamespace(
                exact_log_p=problem.exact_log_p, reference=problem.reference, verdict_cap=problem.verdict_cap
            )
            _HORIZONS[key] = (int(problem.n_steps or N_STEPS), float(problem.look_ahead_s), stated, problem)
        except (OSError, ValueError, KeyError):  # a PEM that cannot be read, parameters refused: the run says which
            _HORIZONS[key] = (N_STEPS, 0.0, None, None)
    return _HORIZONS[key]


def run_cost(cfg: ExperimentConfig, n_steps: int | None = None, slowdown: float | None = None) -> RunCost:
    """What ``cfg``'s run will take (:func:`pemviz.engine.cost.run_cost` of its plan on its problem's :func:`horizon`,
    or ``n_steps`` steps): simulations, memory of the largest batch, expected seconds as planned and with what may
    follow, on this machine as loaded now (times ``slowdown``; None: :func:`pemviz.engine.cost.start_reading` of a
    pilot, the console's reading, which also prices a pooled batch; read again after :data:`LOAD_FRESH_S`)."""
    from pemviz.engine.experiment import stream_above  # the engine and the estimators import torch: only when asked
    from pemviz.estimators import run_plan

    steps, look, stated, problem = _horizon(cfg) if n_steps is None else (n_steps, 0.0, None, None)
    speed, factor, load = (1.0, float(slowdown), None) if slowdown is not None else _recent_load(cfg, problem)
    plan, above = run_plan(cfg), stream_above(cfg, getattr(problem, "n_objects", 1))  # where the engine streams
    idle = cost.run_cost(cfg, plan, steps, above, look_ahead_s=look, problem=stated, speed=speed, load=load)
    scaled = dataclasses.replace(idle, seconds=idle.seconds * factor, then_seconds=idle.then_seconds * factor)
    return dataclasses.replace(scaled, slowdown=factor)


LOAD_FRESH_S = 3.0
"""How long the panel's cost line reuses a reading of a scene's speed and the machine's load (one reading takes
a quarter of a second of wall time and a pilot of the scene's rollouts: every change to the form would wait on it)."""
_LOAD: dict[tuple[Any, ...], tuple[float, tuple[float, float, LoadReading]]] = {}


def _recent_load(cfg: ExperimentConfig, problem: Any) -> tuple[float, float, LoadReading]:
    """``(speed, slowdown, load)`` of a run of ``cfg`` on ``problem``, as the console's first line reads them
    (:func:`pemviz.engine.cost.start_reading` of a pilot of its rollouts; none without a problem), reused for
    :data:`LOAD_FRESH_S` s per scene."""
    from pemviz.engine.experiment import scene_pilot
    from pemviz.engine.resources import tasks_now

    now, key = time.monotonic(), _key(cfg)
    if key in _LOAD and now - _LOAD[key][0] <= LOAD_FRESH_S:
        return _LOAD[key][1]
    opened = tasks_now()
    pilot, steps = ([], N_STEPS) if problem is None else (scene_pilot(problem), problem.n_steps or N_STEPS)
    reading = cost.start_reading(cfg, pilot, steps, since=opened)
    _LOAD[key] = (now, reading)
    return reading


def setting_name(key: str) -> str:
    """The name a setting goes by in labels and the compare table (``smoothing`` -> ``alpha``): its
    :attr:`~pemviz.settings.Setting.label`."""
    return SETTINGS[key].label


NOT_HELD = object()
"""The value :func:`settings_of` gives a run for a setting its method does not have (shown as ``-``)."""


def settings_of(configs: list[ExperimentConfig]) -> list[tuple[str, str, list[Any]]]:
    """Every setting of the runs ``configs`` as ``(name, label, [its value in each config])``: the settings table's, in
    its order, then each method of one's own's settings (:attr:`pemviz.config.ExperimentConfig.method_settings`) in
    their fields' order, labelled by their rows; a run whose method lacks one has :data:`NOT_HELD` there. What the
    *Runs* and *Compare* tables list."""
    labels = {name: s.label for name, s in SETTINGS.items()}
    for cfg in configs:
        if cfg.method_settings is not None:
            rows = rows_of(type(cfg.method_settings), cfg.method)
            labels.update({name: row.label for name, row in rows.items() if name not in labels})
    flats = [cfg.flat() for cfg in configs]
    return [(name, label, [flat.get(name, NOT_HELD) for flat in flats]) for name, label in labels.items()]


def default_settings(cfg: ExperimentConfig) -> dict[str, Any]:
    """The flat settings of a run of ``cfg``'s method with every setting at its default (its own settings too)."""
    own = cfg.method_settings
    return {**ExperimentConfig.of().flat(), **({} if own is None else dataclasses.asdict(type(own)()))}


def setting_value(value: Any) -> str:
    """The text of a setting's value in labels and tables: ``0.2`` (``:g`` of a float), ``default`` for None, and
    ``cut_in_gap_m=19.5, n_objects=4`` for scenario parameters (``(name, value)`` pairs, e.g. a cut-in's; none:
    ``default``), ``-`` for :data:`NOT_HELD`."""
    if value is NOT_HELD:
        return "-"
    if value is None:
        return "default"
    if isinstance(value, tuple) and all(isinstance(x, tuple) and len(x) == 2 for x in value):
        texts = (f"{name}={str(v).lower() if isinstance(v, bool) else setting_value(v)}" for name, v in value)
        return ", ".join(texts) or "default"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def run_label(run_id: int, cfg: ExperimentConfig, defaults: ExperimentConfig | None = None) -> str:
    """``run 3 · agm, alpha 0.2, K 8``: the run number, the metric and every setting that differs from ``defaults``;
    scenario parameters by name and value (``scenario cut-in, cut_in_gap_m=19.5``, e.g. a cut-in's); a method of one's
    own's settings that differ from its defaults (``method defensive-mc, eps 0.2``)."""
    base = defaults or ExperimentConfig.of()
    parts = [cfg.metric]
    for name in SETTINGS:
        if name == "metric":
            continue
        value = cfg.value(name)
        if value != base.value(name):
            if name == "scenario_params":
                parts.append(setting_value(value) if value else f"{setting_name(name)} {setting_value(value)}")
            else:
                parts.append(f"{setting_name(name)} {setting_value(value)}")
    if cfg.method_settings is not None:  # a method of one's own: its settings that differ from its defaults
        first = type(cfg.method_settings)()
        for row in own_rows(cfg.method):
            if (value := getattr(cfg.method_settings, row.name)) != getattr(first, row.name):
                parts.append(f"{row.label} {setting_value(value)}")
    return f"run {run_id} · " + ", ".join(parts)
