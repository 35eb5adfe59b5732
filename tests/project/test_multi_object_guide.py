"""The user guide's multi-object simulator (docs/multi-object.md) runs as written: its enumeration is the exact answer
(checked against plain Monte Carlo of the same simulator), and the default sampler's interval holds it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import doc_python_block


def guide_example() -> str:
    return doc_python_block("multi-object.md", "## An example with an exact answer")


def test_the_multi_object_guide_example_runs_and_its_interval_holds_the_exact_answer(capsys):
    namespace: dict = {"__name__": "multi_object_guide"}
    exec(compile(guide_example(), "docs/multi-object.md", "exec"), namespace)
    printed = capsys.readouterr().out
    problem, est = namespace["problem"], namespace["done"].final.estimate
    exact = math.exp(problem.exact_log_p)
    assert exact == pytest.approx(2.483e-2, rel=1e-3)  # the number the guide quotes
    assert f"exact {exact:.3e}" in printed and "inside the interval" in printed
    assert est.log_ci[0] < problem.exact_log_p < est.log_ci[1]
    assert exact / 1.3 < est.mu_hat < 1.3 * exact


def test_the_guides_enumeration_is_what_plain_monte_carlo_of_its_simulator_finds():
    """The enumeration over the first brake step against 40,000 rollouts drawn from the camera itself: within 4
    binomial standard errors (an independent check of the exact answer the guide quotes)."""
    code = guide_example().split("done = Experiment")[0]
    namespace: dict = {"__name__": "multi_object_guide"}
    exec(compile(code, "docs/multi-object.md", "exec"), namespace)
    problem = namespace["problem"]
    n = 40_000
    batch = problem.simulate(n, problem.target, problem.target, np.random.default_rng(7))
    share = float(np.mean(problem.failed(batch)))
    exact = math.exp(problem.exact_log_p)
    assert abs(share - exact) < 4 * math.sqrt(exact * (1 - exact) / n)
    assert batch.detected.shape == (n, namespace["T"], 2) and batch.noise is not None
