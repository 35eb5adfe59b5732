"""A scenario's parameters over an operating design domain: ``pemviz run --param NAME~DIST`` (``gap0_m~uniform(10,
14)``) draws the parameter of each rollout from a distribution (:mod:`pemviz.core.odd`), where the scenario allows
it (:attr:`pemviz.scenarios.registry.Scenario.random_params`); a drawn parameter travels as ``(name, "~uniform(10,
14)")``, checked by :func:`odd_value` and separated by :func:`split_odd`."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any, TypeGuard

from pemviz.core.odd import ODD, Distribution, ODDError, parse_distribution

PREFIX = "~"
"""A drawn parameter's value in ``scenario_params`` is its distribution's text after this mark."""


def is_odd(value: object) -> TypeGuard[str]:
    """Whether a ``scenario_params`` value is a distribution (``"~uniform(10, 14)"``), not a fixed value."""
    return isinstance(value, str) and value.startswith(PREFIX)


def odd_value(scenario: str, name: str, text: str, allowed: tuple[str, ...]) -> str:
    """The ``scenario_params`` value of ``NAME~TEXT``: ``"~" + the distribution's text``, checked (its range, with
    the other parameters: :func:`pemviz.scenarios.parameters.check_pairs`).

    Args:
        scenario: the scenario's name (for the message).
        name: the parameter drawn.
        text: the distribution's text (after ``~``).
        allowed: the parameters ``scenario`` may draw per rollout
            (:attr:`pemviz.scenarios.registry.Scenario.random_params`).
    Raises:
        ValueError: one line: a parameter the scenario does not draw per rollout (its random parameters listed), an
            unknown distribution, bad arguments, an empty support."""
    if name not in allowed:
        which = (
            f"its parameters that can be drawn: {', '.join(allowed)}"
            if allowed
            else "it draws none: a scenario names those it can by random_params= and odd= in its Scenario record"
        )
        raise ValueError(
            f"{name}~...: the {scenario} scenario cannot draw {name} per rollout ({which}); give it a value, "
            f"{name}=VALUE"
        )
    try:
        law = parse_distribution(text, where=f"{name}~{text.strip()}")
    except ODDError as exc:
        raise ValueError(str(exc)) from None
    return PREFIX + law.text


def split_odd(pairs: Iterable[tuple[str, Any]]) -> tuple[tuple[tuple[str, Any], ...], ODD | None]:
    """``(the fixed pairs, the ODD of the drawn ones or None)`` of ``scenario_params`` pairs."""
    fixed, drawn = [], []
    for name, value in pairs:
        if is_odd(value):
            drawn.append((name, parse_distribution(value[len(PREFIX) :], where=name)))
        else:
            fixed.append((name, value))
    return tuple(fixed), (ODD(tuple(drawn)) if drawn else None)


def law_of(value: str) -> Distribution:
    """The distribution of a drawn parameter's ``scenario_params`` value."""
    return parse_distribution(value[len(PREFIX) :])
