"""Scenario parameters a user can set (``pemviz run --param NAME=VALUE``), derived from each scenario's dataclass.

A scenario's parameters are the scalar fields (float, int, bool) of its params dataclass, each with its default,
type and unit (from the name's suffix: ``_m`` metres, ``_mps`` m/s, ``_s`` seconds, ...); their range is the
dataclass's own ``__post_init__`` check, whose one-line message :func:`apply_parameters` passes on. They travel in
:attr:`pemviz.config.ExperimentConfig.scenario_params` as ``(name, value)`` pairs;
:func:`pemviz.scenarios.problems.problem_for` builds the scenario from them. No PEM or torch is imported here."""

from __future__ import annotations

import dataclasses
import functools
import math
import re
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, cast

from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.settings import scenario_names


class DataclassInstance(Protocol):
    """Any dataclass instance (a scenario's parameters, a plugin's included): what ``dataclasses.replace`` takes."""

    __dataclass_fields__: ClassVar[dict[str, Any]]


if TYPE_CHECKING:
    from pemviz.scenarios.cut_in.scenario import CutInParams

Value = float | int | bool
"""A parameter's value: a float, an int or a bool (the field's type)."""

PairValue = float | int | bool | str
"""A value of a ``(name, value)`` pair of ``scenario_params``: a :data:`Value`, or for a parameter drawn per rollout
the text ``"~" + its distribution`` (:func:`pemviz.scenarios.odd.odd_value`)."""

UNIT_SUFFIXES: tuple[tuple[str, str], ...] = (
    ("_mps2", "m/s^2"),
    ("_mps", "m/s"),
    ("_kmh", "km/h"),
    ("_per_s", "1/s"),
    ("_steps", "steps"),
    ("_m", "m"),
    ("_s", "s"),
)
"""A field name's suffix -> the unit of its value (the first suffix that matches)."""

KINDS = {"float": "a number", "int": "a whole number", "bool": "true or false"}
"""A parameter's kind -> what its value must be, in words."""

_NUMBER = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?$")
_WHOLE = re.compile(r"^[+-]?\d{1,18}$")
_TRUE, _FALSE = ("true", "yes", "on", "1"), ("false", "no", "off", "0")


class ParameterError(ValueError):
    """A scenario parameter that cannot be set: an unknown name (the message lists the scenario's names), a value that
    is not of the field's kind, or one outside its range (the dataclass's own message). One line."""


@dataclass(frozen=True)
class Parameter:
    """One parameter of a scenario.

    Attributes:
        name: the dataclass field (``cut_in_gap_m``).
        kind: ``float``, ``int`` or ``bool`` (the field's type).
        default: the scenario's value when the parameter is not set.
        unit: of the value (``m``, ``m/s``, ``s``, ``m/s^2``, ...; ``""``: a count, a flag or a fraction)."""

    name: str
    kind: str
    default: Value
    unit: str

    def parse(self, text: str) -> Value:
        """The value written as ``text``: a decimal or scientific number (``float``), digits (``int``), ``true`` /
        ``false`` (also yes / no, on / off, 1 / 0; ``bool``); surrounding spaces are ignored. Its range is not checked
        here (:func:`apply_parameters`).

        Raises:
            ParameterError: ``text`` is not a value of :attr:`kind` (not finite, not whole, not a truth value)."""
        raw = str(text).strip()
        if self.kind == "bool":
            if raw.lower() in _TRUE + _FALSE:
                return raw.lower() in _TRUE
        elif self.kind == "int":
            if _WHOLE.match(raw):
                return int(raw)
        elif _NUMBER.match(raw) and math.isfinite(float(raw)):
            return float(raw)
        return self._refuse(text)

    def check(self, value: object) -> Value:
        """``value`` if it is of :attr:`kind` (an int for a float too, as float; a finite number), else
        :class:`ParameterError`."""
        if self.kind == "bool" and isinstance(value, bool):
            return value
        if self.kind == "int" and isinstance(value, int) and not isinstance(value, bool):
            return value
        if self.kind == "float" and isinstance(value, (int, float)) and not isinstance(value, bool):
            if math.isfinite(value):
                return float(value)
        return self._refuse(value)

    def _refuse(self, value: object) -> Value:
        unit = f" in {self.unit}" if self.unit else ""
        raise ParameterError(
            f"{self.name}={value!r} is not {KINDS[self.kind]}: {self.name} takes {KINDS[self.kind]}"
            f"{unit} (default {self.default!r})"
        )


def unit_of(name: str) -> str:
    """The unit of the field ``name`` from its suffix (:data:`UNIT_SUFFIXES`); ``""`` when none matches."""
    return next((unit for suffix, unit in UNIT_SUFFIXES if name.endswith(suffix)), "")


def default_params(scenario: str) -> BrakingParams | CutInParams | DataclassInstance | None:
    """The params dataclass of ``scenario`` (one of :data:`pemviz.settings.SCENARIOS`, or another registered one:
    :mod:`pemviz.scenarios.registry`) at its defaults; None for a registered scenario without parameters.

    Raises:
        ParameterError: an unknown scenario."""
    if scenario in _REGISTERED_DEFAULTS:  # every scenario of the registry, built-in or a plugin's: its own defaults
        return _REGISTERED_DEFAULTS[scenario]()
    raise ParameterError(f"unknown scenario {scenario!r}; use one of {', '.join(scenario_names())}")


_REGISTERED_DEFAULTS: dict[str, Callable[[], DataclassInstance | None]] = {}
"""Scenario name -> its parameters at their defaults, for the registry's scenarios besides :data:`SCENARIOS` (filled by
:func:`pemviz.scenarios.registry.register` through :func:`register_defaults`: this module sits below the registry)."""


RANDOM_PARAMS: dict[str, tuple[str, ...]] = {}
"""Scenario name -> the parameters it may draw per rollout over an operating design domain
(:attr:`pemviz.scenarios.registry.Scenario.random_params`, written by :func:`register_defaults`)."""


def register_defaults(
    scenario: str, defaults: Callable[[], DataclassInstance | None] | None, random_params: tuple[str, ...] = ()
) -> None:
    """Let :func:`default_params` of ``scenario`` call ``defaults()`` and record the parameters it may draw per
    rollout (None: forget the scenario)."""
    if defaults is None:
        _REGISTERED_DEFAULTS.pop(scenario, None)
        RANDOM_PARAMS.pop(scenario, None)
    else:
        _REGISTERED_DEFAULTS[scenario] = defaults
        RANDOM_PARAMS[scenario] = tuple(random_params)


@functools.cache
def scenario_parameters(scenario: str) -> tuple[Parameter, ...]:
    """The parameters of ``scenario``, in the dataclass's field order: every float, int and bool field, with the
    scenario's default and the unit of :func:`unit_of`.

    Raises:
        ParameterError: an unknown scenario."""
    params = default_params(scenario)
    if params is None:  # a registered scenario without parameters
        return ()
    kinds = {
        f.name: f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "")
        for f in dataclasses.fields(params)
    }  # an annotation as text (postponed) or as the type itself
    return tuple(
        Parameter(f.name, kinds[f.name], getattr(params, f.name), unit_of(f.name))
        for f in dataclasses.fields(params)
        if kinds[f.name] in KINDS
    )


def parameter(scenario: str, name: str) -> Parameter:
    """The parameter ``name`` of ``scenario``.

    Raises:
        ParameterError: not one of the scenario's; the message lists them all."""
    found = {p.name: p for p in scenario_parameters(scenario)}
    if name not in found:
        raise ParameterError(
            f"{name!r} is not a parameter of the {scenario} scenario; use one of " f"{', '.join(found)}"
        )
    return found[name]


def parse_assignment(scenario: str, text: str) -> tuple[str, PairValue]:
    """``(name, value)`` of ``NAME=VALUE`` (``cut_in_gap_m=19.5``), the value parsed by the field's kind
    (:meth:`Parameter.parse`); its range is checked by :func:`apply_parameters`.

    Raises:
        ParameterError: no ``=``, an unknown name (the message lists the allowed ones) or a value not of its kind."""
    head = str(text).split("=", 1)[0]
    if "~" in head:  # NAME~DIST: drawn per rollout from a distribution (pemviz.scenarios.odd)
        from pemviz.scenarios.odd import law_of, odd_value

        name, _, dist = str(text).partition("~")
        p = parameter(scenario, name.strip())
        try:
            value = odd_value(scenario, p.name, dist, RANDOM_PARAMS.get(scenario, ()))  # its range: check_pairs
        except ValueError as exc:
            raise ParameterError(str(exc)) from None
        law = law_of(value)
        if p.kind != "float" and not (law.discrete and all(float(v).is_integer() for v in law.args)):
            raise ParameterError(
                f"{p.name}~{law.text}: {p.name} takes {KINDS[p.kind]}: draw it from " "choice(...) of whole numbers"
            )
        return p.name, value
    name, sep, value = str(text).partition("=")
    if not sep:
        names = ", ".join(p.name for p in scenario_parameters(scenario))
        raise ParameterError(f"{text!r} is not NAME=VALUE; the {scenario} scenario's names: {names}")
    p = parameter(scenario, name.strip())
    return p.name, p.parse(value)


def parse_assignments(scenario: str, texts: Iterable[str]) -> tuple[tuple[str, PairValue], ...]:
    """The pairs of every ``NAME=VALUE`` of ``texts`` (:func:`parse_assignment`), in the order given.

    Raises:
        ParameterError: one of them is not valid, or a name given twice."""
    pairs = tuple(parse_assignment(scenario, text) for text in texts)
    check_pairs(scenario, pairs)
    return pairs


def check_pairs(scenario: str, pairs: object) -> tuple[tuple[str, PairValue], ...]:
    """``pairs`` if it is a tuple of ``(name, value)`` pairs of parameters of ``scenario``, each name once, each value
    of its kind and the dataclass built from them valid (:func:`apply_parameters`).

    Raises:
        ParameterError: the first thing wrong, in one line."""
    if not isinstance(pairs, tuple) or not all(isinstance(x, tuple) and len(x) == 2 for x in pairs):
        raise ParameterError(f"{pairs!r} is not a tuple of (name, value) pairs")
    seen = set()
    for name, _ in pairs:
        if name in seen:
            raise ParameterError(f"{name} is given twice; give each parameter once")
        seen.add(name)
    from pemviz.scenarios.odd import is_odd, law_of  # drawn parameters (NAME~DIST): as the command line checks them

    for name, value in pairs:
        if is_odd(value):
            parse_assignment(scenario, f"{name}{value}")
    fixed = representative(scenario, pairs)  # the fixed values, a drawn one at its support's first end
    try:
        apply_parameters(scenario, fixed)
    except ParameterError:
        if any(is_odd(value) for _, value in pairs):  # the fixed ones alone (drawn ones at their defaults) first
            apply_parameters(scenario, {name: value for name, value in pairs if not is_odd(value)})
        else:
            raise
    for name, value in pairs:
        if is_odd(value):
            law = law_of(value)
            for end in law.args if law.discrete else law.support():  # the support's ends, with the fixed ones
                whole = parameter(scenario, name).kind == "int"
                try:
                    apply_parameters(scenario, {**fixed, name: int(end) if whole else float(end)})
                except ParameterError as exc:
                    raise ParameterError(
                        f"{name}~{law.text}: its value {end:g} is out of the parameter's " f"range: {exc}"
                    ) from None
    return pairs


def representative(scenario: str, pairs: Iterable[tuple[str, object]]) -> dict[str, object]:
    """name -> value of ``pairs`` with each drawn parameter (``NAME~DIST``, :mod:`pemviz.scenarios.odd`) at its
    support's first end (a whole number for an int field): parameters the scenario's dataclass can be built from,
    the drawn ones replaced per rollout."""
    from pemviz.scenarios.odd import is_odd, law_of

    out: dict[str, object] = {}
    for name, value in pairs:
        if is_odd(value):
            law = law_of(str(value))
            end = law.args[0] if law.discrete else law.support()[0]
            out[name] = int(end) if parameter(scenario, name).kind == "int" else float(end)
        else:
            out[name] = value
    return out


def apply_parameters(scenario: str, values: Mapping[str, object]) -> BrakingParams | CutInParams | DataclassInstance:
    """The params dataclass of ``scenario`` with ``values`` (name -> value) replacing its defaults.

    Raises:
        ParameterError: an unknown name (the message lists the allowed ones), a value not of its field's kind, or a
            value the dataclass refuses (its message, led by the scenario's name instead of the dataclass's: the
            field, what is allowed and what was given)."""
    changes: dict[str, Any] = {}  # the fields' own kinds, each checked by Parameter.check
    for name, value in values.items():
        if not isinstance(name, str):
            raise ParameterError(f"{name!r} is not a parameter name")
        changes[name] = parameter(scenario, name).check(value)
    params = default_params(scenario)  # None (a scenario without parameters): replace's TypeError, as always
    try:
        return dataclasses.replace(cast("DataclassInstance", params), **changes)
    except ValueError as exc:
        raise refusal(scenario, params, exc) from None


def refusal(scenario: str, params: object, exc: ValueError) -> ParameterError:
    """The one line of a value the parameters' dataclass ``params`` refused with ``exc``: its words, led by the
    scenario's name instead of the dataclass's (``the cut-in scenario: cut_in_gap_m must be finite and >= 0, got
    -5.0``, not ``CutInParams: ...``: a user names the scenario, never its class)."""
    text, name = str(exc).replace("\n", " "), type(params).__name__
    for sep in (": ", "."):
        text = text.removeprefix(name + sep)
    return ParameterError(f"the {scenario} scenario: {text}")


def changed_parameters(scenario: str, pairs: Iterable[tuple[str, PairValue]]) -> tuple[tuple[str, PairValue], ...]:
    """The pairs of ``pairs`` whose value differs from the scenario's default, in the order given."""
    defaults = {p.name: p.default for p in scenario_parameters(scenario)}
    return tuple((name, value) for name, value in pairs if name in defaults and value != defaults[name])


def parameters_text(scenario: str, pairs: Iterable[tuple[str, PairValue]]) -> str:
    """``cut_in_gap_m=19.5 m, n_objects=4``: the pairs with their units, as the console's header line prints them
    (``""``: none)."""
    units = {p.name: p.unit for p in scenario_parameters(scenario)}
    from pemviz.scenarios.odd import is_odd

    drawn = {name for name, value in pairs if is_odd(value)}  # NAME~DIST
    return ", ".join(
        (f"{name} {value[0]} {value[1:]}" if name in drawn and isinstance(value, str) else f"{name}={value!r}")
        + (f" {units[name]}" if units.get(name) else "")
        for name, value in pairs
    )


def as_pairs(value: object) -> tuple[tuple[str, Value], ...]:
    """A recorded ``scenario_params`` (a JSON document's list of ``[name, value]`` lists, or the config's tuple) as
    the config's tuple of pairs; anything else as it is, for the config to refuse."""
    if isinstance(value, list) and all(isinstance(x, list) and len(x) == 2 for x in value):
        return tuple((str(x[0]), x[1]) for x in value)
    return value  # type: ignore[return-value]


def scenario_params_text(scenario: str, pairs: tuple[tuple[str, Value], ...]) -> str:
    """The parameters ``pairs`` ((name, value), a config's ``scenario_params``) of the scenario named ``scenario``
    that differ from its defaults, as the header line of ``pemviz run`` gives them after the scenario's name (``""``:
    none; e.g. `` (cut_in_gap_m=19.5 m)``)."""
    if not pairs:
        return ""
    changed = changed_parameters(scenario, pairs)
    return f" ({parameters_text(scenario, changed)})" if changed else ""
