"""A Problem refuses, when it is made, a window, decided_below or h_scale that is not a number: a user's
``window=None`` (read as "no window") used to pass and fail later inside the rollout sink with a TypeError."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pemviz import stl
from pemviz.core.detectors import PEMDetector
from pemviz.core.problems import Problem
from pemviz.pem import load_pem
from pemviz.scenarios import simulate


class _Car:
    observation_names = ("gap_m",)

    def __init__(self):
        self.gap_m = 20.0

    def reset(self):
        self.gap_m = 20.0

    def observation(self):
        return np.array([self.gap_m])

    def step(self, detected):
        self.gap_m -= 0.5 * (not detected)


def _problem(**fields):
    def run(n, sampler, target, rng):
        return simulate(_Car, n, sampler, target, rng, n_steps=8)

    return Problem("one-car", run, PEMDetector(load_pem()), stl.parse("G(d >= 2)"), {"d": "gap_m"}, **fields)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("window", None),
        ("window", "25"),
        ("window", math.nan),
        ("decided_below", None),
        ("h_scale", None),
        ("h_scale", 0.0),
        ("h_scale", -3.0),
        ("h_scale", math.inf),
    ],
)
def test_problem_refuses_a_field_that_is_not_a_number(field, value):
    with pytest.raises(ValueError, match=rf"Problem 'one-car': {field} must be .*; got {value!r}"):
        _problem(**{field: value})


@pytest.mark.parametrize("value", ["yes", 1, None])
def test_problem_refuses_an_array_rqmc_that_is_not_a_bool(value):
    with pytest.raises(ValueError, match=rf"Problem 'one-car': array_rqmc must be True or False; got {value!r}"):
        _problem(array_rqmc=value)


def test_problem_takes_numbers_and_the_defaults():
    assert _problem().window == math.inf
    problem = _problem(window=np.float64(25.0), h_scale=30, decided_below=1)
    assert (problem.window, problem.h_scale, problem.decided_below) == (25.0, 30, 1)
    batch = problem.simulate(4, problem.target, problem.target, np.random.default_rng(0))
    assert batch.observations.shape[:2] == (4, 8)
