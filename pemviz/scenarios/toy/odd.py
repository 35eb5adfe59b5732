"""The toy over an operating design domain: each rollout's braking distance drawn from a distribution
(``pemviz run --scenario toy --param braking~choice(5, 7)``), with its exact answer in closed form,
p_ODD = sum_b P(b) prod_{d=safe}^{b} (1 - p(d)) (:func:`toy_odd_log_failure_probability`)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
from scipy.special import logsumexp

from pemviz.core.odd import ODD
from pemviz.core.odd_rollouts import problem_over_odd
from pemviz.core.problems import Problem
from pemviz.scenarios.toy.problem import toy_problem
from pemviz.scenarios.toy.simulator import BatchedToy, ToyParams, toy_log_failure_probability


class _PerRollout(BatchedToy):
    """:class:`BatchedToy` with a braking distance per rollout (float64 [n]): the same steps otherwise."""

    def __init__(self, params: ToyParams, n: int, braking: np.ndarray) -> None:
        super().__init__(params, n)
        self.braking = np.asarray(braking, dtype=np.float64)

    def step(self, detected: np.ndarray, noise: np.ndarray | None = None) -> None:
        p, a = self.params, np.asarray(detected, dtype=bool).reshape(self.distance.size)
        crashed = self.distance < p.safe
        self.stopped = self.stopped | crashed | (a & (self.distance <= self.braking))
        self.distance = np.where(self.stopped, self.distance, self.distance - 1.0)


def toy_odd_log_failure_probability(params: ToyParams, odd: ODD) -> float:
    """log p_ODD (nats), exact: the closed form of each braking distance of the ODD's choice, weighed by its
    probability.

    Raises:
        ValueError: an ODD that is not one choice over ``braking``."""
    ((name, law),) = odd.parameters
    if name != "braking" or not law.discrete:
        raise ValueError("the toy's exact answer over an ODD needs braking ~ choice(...)")
    logs = [toy_log_failure_probability(dataclasses.replace(params, braking=int(b))) for b in law.args]
    return float(logsumexp(logs, b=np.asarray(law.weights)))  # a weight of 0 adds nothing


def toy_odd_problem(config: Any, params: ToyParams | None, odd: ODD) -> Problem:
    """The toy over ``odd`` (its braking distance drawn per rollout), with the exact p_ODD.

    Raises:
        ValueError: another parameter in the ODD, or a braking distance the toy refuses."""
    p = params or ToyParams()
    if odd.names != ("braking",):
        raise ValueError(f"the toy draws only its braking distance per rollout, not {list(odd.names)}")
    ((_, law),) = odd.parameters
    for b in law.args if law.discrete else law.support():
        dataclasses.replace(p, braking=int(b))  # its own range check (safe <= braking < total)
    top = int(max(law.args)) if law.discrete else int(np.ceil(law.support()[1]))

    def make(n: int, values: np.ndarray) -> _PerRollout:
        return _PerRollout(p, n, values[:, 0])

    base = toy_problem(dataclasses.replace(p, braking=top))
    exact = toy_odd_log_failure_probability(p, odd) if law.discrete else None
    return problem_over_odd(
        base,
        make,
        odd,
        p.steps,
        exact_log_p=exact,
        name=f"toy over {odd.text()}",
        window=float(top) + 0.5,
        description=f"toy braking, its braking distance drawn per rollout ({odd.text()})",
    )
