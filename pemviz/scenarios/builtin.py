"""The factories of the built-in scenarios of :mod:`pemviz.scenarios.registry`: ``factory(config, params) ->
Problem``, each a thin call of :mod:`pemviz.scenarios.problems` (the registry names them as ``"module:name"`` texts and
imports this module only when a problem is built)."""

from __future__ import annotations

from typing import Any

from pemviz.core.problems import Problem
from pemviz.scenarios.crowd.problem import crowd_problem
from pemviz.scenarios.crowd.simulator import CrowdParams
from pemviz.scenarios.toy import ToyParams
from pemviz.scenarios.toy.problem import toy_problem


def toy(config: Any, params: ToyParams | None = None) -> Problem:
    """The toy braking model (:func:`pemviz.scenarios.toy.problem.toy_problem`; named ``toy`` at its defaults, as
    ``pemviz validate``'s); the config is not read (the toy's detector is its own)."""
    p = params if params is not None else ToyParams()
    return toy_problem(p, name="toy" if p == ToyParams() else None)


def crowd(config: Any, params: CrowdParams | None = None) -> Problem:
    """The crowd toy (:func:`pemviz.scenarios.crowd.problem.crowd_problem`; named ``crowd`` at its defaults); the config
    is not read."""
    p = params if params is not None else CrowdParams()
    return crowd_problem(p, name="crowd" if p == CrowdParams() else None)
