"""The Simulator protocol: a simulator written here (not in pemviz) plugs into the adaptive sampler, which
recovers its exact failure probability; pemviz's own scenarios implement the protocol; the user guide's example runs."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from pemviz import stl
from pemviz.config import ExperimentConfig
from pemviz.core.checks import check_simulator
from pemviz.core.problems import Problem
from pemviz.engine.experiment import Experiment
from pemviz.scenarios import simulate
from pemviz.scenarios.braking.simulator import BrakingScenario
from pemviz.scenarios.toy import ToyBraking, ToyParams
from scipy.special import log_expit

from conftest import doc_python_block

N_STEPS = 25


class ParkedCarAEB:
    """A user's simulator: a car at 10 m/s, 20 m behind a parked car; its automatic emergency brake
    (6 m/s^2, explicit Euler with dt = 0.1 s) engages for good at the first detection within 15 m."""

    observation_names = ("gap_m", "speed_mps")
    dt_s = 0.1

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.gap_m, self.speed_mps, self.braking = 20.0, 10.0, False

    def observation(self) -> np.ndarray:
        return np.array([self.gap_m, self.speed_mps])

    def step(self, detected: bool) -> None:
        if detected and self.gap_m < 15.0:
            self.braking = True
        self.gap_m -= self.speed_mps * self.dt_s
        self.speed_mps = max(0.0, self.speed_mps - (6.0 * self.dt_s if self.braking else 0.0))


class RangeDetector:
    """The user's perception model: logit p(detect | gap) = 2 + 0.1 (15 - gap) (p = 0.89 .. 0.92 near 14-11 m)."""

    def detect_logit(self, obs: np.ndarray) -> np.ndarray:
        return 2.0 + 0.1 * (15.0 - np.asarray(obs)[:, 0])


def exact_failure_probability(make: Callable[[], object], logit_fn, n_steps: int, window_m: float) -> float:
    """p_fail of a latched-brake simulator by enumeration, independent of pemviz's sampler.

    Before the brake engages the run is deterministic (gaps g_0, g_1, ...), and everything after is
    decided by the first step k < T - 1 with a detection inside the window (or none): P(k) =
    p(g_k) prod_{j<k, in window} (1 - p(g_j)); replaying the simulator with a detection at k alone tells
    whether that run fails (its gap drops below 2 m). p_fail = sum of P(k) over failing k (+ P(none)).
    """

    def replay(k: int | None) -> list[float]:
        sim = make()
        gaps = []
        for t in range(n_steps):
            gaps.append(float(sim.observation()[0]))
            sim.step(t == k)
        return gaps

    free = np.array(replay(None))
    logit = logit_fn(free[:, None])
    log_miss_so_far, total = 0.0, 0.0
    for k in [t for t in range(n_steps - 1) if free[t] < window_m] + [None]:
        log_p = log_miss_so_far if k is None else log_miss_so_far + float(log_expit(logit[k]))
        if k is not None:
            log_miss_so_far += float(log_expit(-logit[k]))
        if min(replay(k)) < 2.0:
            total += math.exp(log_p)
    return total


@pytest.mark.parametrize(
    "make, n_steps",
    [(ParkedCarAEB, N_STEPS), (lambda: ToyBraking(ToyParams(10, 5, 3, 0.9)), 10), (BrakingScenario, 100)],
    ids=["user-simulator", "toy", "highway-env-braking"],
)
def test_simulators_implement_the_protocol(make, n_steps):
    check_simulator(make, n_steps)


def test_exact_enumeration_matches_the_closed_form():
    # fail iff no detection at the un-braked gaps 14, 13, 12, 11 (from 11 m the car stops at 2.16 m)
    closed = math.prod(1.0 - 1.0 / (1.0 + math.exp(-(2.0 + 0.1 * (15.0 - g)))) for g in (14.0, 13.0, 12.0, 11.0))
    exact = exact_failure_probability(ParkedCarAEB, RangeDetector().detect_logit, N_STEPS, 15.0)
    assert exact == pytest.approx(closed, rel=1e-12)
    assert exact == pytest.approx(8.2478e-5, rel=1e-4)


def test_user_simulator_through_the_protocol_recovers_its_exact_failure_probability_within_30pct():
    def run(n, sampler, target, rng):
        return simulate(ParkedCarAEB, n, sampler, target, rng, N_STEPS)

    problem = Problem(
        "parked-car-aeb",
        run,
        RangeDetector(),
        stl.parse(f"G[0,{N_STEPS - 1}](d >= 2)"),
        signals={"d": "gap_m"},
        signal_ranges={"d": (0.0, 20.0)},
        h_scale=20.0,
        curve_grid=np.linspace(0.0, 20.0, 41),
        window=15.0,
    )
    config = ExperimentConfig.of(
        n_stages=4,
        n_per_stage=200,
        n_final=2000,
        quantile_level=0.9,
        smoothing=1.0,
        ce_epochs=200,
        pretrain_epochs=300,
        learning_rate=1e-2,
        seed=0,
    )
    result = Experiment(config, problem=problem).run()
    exact = exact_failure_probability(ParkedCarAEB, RangeDetector().detect_logit, N_STEPS, 15.0)
    est = result.final.estimate
    assert est.n_failures >= 20  # the proposal drives the final rollouts into the rare failure (MC: ~0.2)
    assert est.mu_hat == pytest.approx(exact, rel=0.30)


def guide_example() -> str:
    return doc_python_block("own-simulator.md", "## A simulator of your own")


def test_user_guide_example_is_under_30_lines_runs_and_estimates_its_exact_answer_within_3x(capsys):
    code = guide_example()
    assert len([line for line in code.splitlines() if line.strip()]) < 30
    namespace: dict = {"__name__": "guide_example"}
    exec(compile(code, "docs/own-simulator.md", "exec"), namespace)
    printed = capsys.readouterr().out
    est = namespace["estimate"]
    assert f"{est.n_failures}/{est.n} failures" in printed
    problem = namespace["problem"]
    exact = exact_failure_probability(namespace["MyCar"], problem.target.detect_logit, 64, 25.0)
    assert exact == pytest.approx(2.8576e-5, rel=1e-3)  # the number the guide quotes
    assert est.n_failures > 0 and exact / 3 < est.mu_hat < 3 * exact
    assert est.log_ci[0] < math.log(exact) < est.log_ci[1]  # the interval the estimate holds holds the exact answer
    guide = (Path(__file__).resolve().parents[2] / "docs" / "own-simulator.md").read_text()
    quoted = guide.split("It prints `", 1)[1].split("`", 1)[0]
    assert quoted == printed.splitlines()[0]  # the guide quotes this run's line exactly (the seed contract)
    # the stages backed no interval, so they ran once more at 4 N, whose weights back one: the guide quotes it
    lo, hi = (math.exp(b) for b in est.log_ci)
    assert not est.plain_mc and est.verdict == "reliable" and f"`95% CI [{lo:.2e}, {hi:.2e}]`" in guide
