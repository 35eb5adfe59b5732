"""The exact failure probabilities validation judges the estimators against: :func:`exact_answer`
(:class:`ExactAnswer`: closed forms, the latched simulator, the enumeration of :mod:`pemviz.scenarios.braking.truth`
or its kept answers, or a registered scenario's), :func:`validation_problems` and :func:`validation_problem`."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import cast

from pemviz.pem import load_pem
from pemviz.scenarios.braking import truth, truth_known, truth_latched
from pemviz.scenarios.braking.simulator import BrakingParams
from pemviz.scenarios.crowd.simulator import crowd_log_failure_probability
from pemviz.scenarios.problems import CROWD_PROBLEMS, PROBLEMS, TOY_PROBLEMS, build_problem
from pemviz.scenarios.toy.simulator import toy_log_failure_probability


@dataclass(frozen=True)
class ExactAnswer:
    """The truth of a problem: ``log_p_fail`` (nats), where it comes from, and a refinement table if any."""

    log_p_fail: float
    source: str
    table: str | None = None
    wall_s: float = 0.0


def exact_answer(
    name: str, pem_path: str | None = None, *, progress: Callable[[str], None] | None = None, recompute: bool = False
) -> ExactAnswer:
    """The exact p_fail of a problem of :data:`~pemviz.scenarios.problems.PROBLEMS`, ``progress`` receiving a line per
    refinement.

    Raises:
        ValueError: an unknown name."""
    t0 = time.perf_counter()
    if name in TOY_PROBLEMS:
        params = TOY_PROBLEMS[name]
        log_p = toy_log_failure_probability(params)
        q, n = 1 - cast(float, params.p_detect), params.braking - params.safe + 1  # the toys' p(detect): constants
        return ExactAnswer(log_p, f"closed form (1 - p)^(braking - safe + 1) = {q:g}^{n}")
    if name in CROWD_PROBLEMS:
        crowd = CROWD_PROBLEMS[name]
        return ExactAnswer(
            crowd_log_failure_probability(crowd),
            f"closed form over {len(crowd.offsets)} obstacles' independent triggers",
        )
    if name not in ("latched", "main"):
        problem = validation_problem(name, pem_path)  # a registered scenario that carries its exact answer
        return ExactAnswer(
            problem.exact_log_p, f"the {name} scenario's own exact answer", wall_s=time.perf_counter() - t0
        )
    pem = load_pem(pem_path)
    if name == "latched":
        lt = truth_latched.latched_log_failure_probability(pem.logit_at_gap, BrakingParams(latched_brake=True))
        return ExactAnswer(
            lt.log_p_fail,
            f"product of (1 - p_PEM) over steps {lt.first_step}..{lt.last_step} (deterministic simulator)",
            wall_s=time.perf_counter() - t0,
        )

    known = truth_known.known_log_failure_probability(pem.logit_at_gap, BrakingParams())
    if known is not None and not recompute:  # a shipped PEM: its enumeration (20-40 s) was kept
        return ExactAnswer(
            known,
            "exact enumeration kept for this PEM "
            "(pemviz.scenarios.braking.truth_known.KNOWN_BRAKING_LOG_P, bracket width < 0.25 %; "
            "tests/scenarios/test_truth.py recomputes it)",
            wall_s=time.perf_counter() - t0,
        )

    def on_result(r: truth.ExactResult) -> None:
        if progress is not None:
            progress(
                f"  truth: drop threshold {r.log_prune:g} nats -> p_fail {math.exp(r.log_p_fail):.5g} "
                f"(+ at most {math.exp(r.log_pruned_bound):.2g}), {r.wall_s:.1f} s"
            )

    ref = truth.braking_truth(pem.logit_at_gap, BrakingParams(), on_result=on_result)
    status = "converged" if ref.converged else "NOT converged"
    f = ref.final
    return ExactAnswer(
        ref.log_p_fail,
        f"exact enumeration, bracket [{math.exp(f.log_p_fail):.5g}, {math.exp(f.log_p_fail_upper):.5g}] "
        f"(width {f.relative_width:.2%}, {status})",
        ref.table(),
        time.perf_counter() - t0,
    )


def validation_problems() -> tuple[str, ...]:
    """The problems ``pemviz validate`` can run: :data:`~pemviz.scenarios.problems.PROBLEMS`, then every registered
    scenario with an exact answer (:attr:`pemviz.scenarios.registry.Scenario.exact`; plugins included) not named
    there."""
    from pemviz.scenarios import registry

    extra = [n for n in registry.registered() if n not in PROBLEMS and registry.get(n).exact]
    return (*PROBLEMS, *extra)


def problem_description(name: str) -> str:
    """What the problem ``name`` is, one line: its entry of :data:`~pemviz.scenarios.problems.PROBLEMS`, else the
    registered scenario's description (:attr:`pemviz.scenarios.registry.Scenario.description`)."""
    if name in PROBLEMS:
        return PROBLEMS[name]
    from pemviz.scenarios import registry

    return registry.get(name).description


def validation_problem(name: str, pem_path: str | None = None):
    """The :class:`~pemviz.core.problems.Problem` of ``name``: one of :data:`~pemviz.scenarios.problems.PROBLEMS`
    (:func:`~pemviz.scenarios.problems.build_problem`), else a registered scenario at its defaults with
    ``pem_path``'s PEM (:mod:`pemviz.scenarios.registry`).

    Raises:
        ValueError: an unknown name, or a registered scenario whose problem carries no exact answer."""
    if name in PROBLEMS:
        return build_problem(name, pem_path)
    from pemviz.config import ExperimentConfig
    from pemviz.scenarios import registry

    if name not in registry.registered():
        raise ValueError(f"unknown problem {name!r}; use one of {', '.join(validation_problems())}")
    problem = registry.get(name).problem(ExperimentConfig.of(scenario=name, pem=pem_path))
    if problem.exact_log_p is None:
        raise ValueError(f"the {name} scenario carries no exact answer: pemviz validate needs one")
    return problem
