"""pemviz.core.checks: a correct simulator and estimator pass; each broken one fails with a message naming its fault."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
from pemviz.config import ExperimentConfig
from pemviz.core.checks import CheckError, check_estimator, check_simulator
from pemviz.estimators import build_estimator
from pemviz.scenarios.toy import ToyBraking, ToyParams
from pemviz.scenarios.toy.problem import toy_problem

from .test_simulator_protocol import ParkedCarAEB


class Car(ParkedCarAEB):
    """A correct simulator (the protocol test's), with snapshot / restore."""

    def snapshot(self) -> tuple:
        return (self.gap_m, self.speed_mps, self.braking)

    def restore(self, state: tuple) -> None:
        self.gap_m, self.speed_mps, self.braking = state


class SpeedFirst(Car):
    """The first column is the window's, whatever its name: a simulator whose first column is not a gap passes."""

    observation_names = ("speed_mps", "gap_m")

    def observation(self) -> np.ndarray:
        return super().observation()[::-1].copy()


class SameNameTwice(Car):
    observation_names = ("gap_m", "gap_m")


class Float32(Car):
    def observation(self) -> np.ndarray:
        return super().observation().astype(np.float32)


class NoReset(Car):
    def reset(self) -> None:
        if not hasattr(self, "gap_m"):
            super().reset()


class Noisy(Car):
    rng = np.random.default_rng()

    def step(self, detected: bool) -> None:
        super().step(detected)
        self.gap_m += 1e-3 * self.rng.standard_normal()


class ShallowSnapshot(Car):
    def snapshot(self) -> tuple:
        return (0.0, 0.0, True)


class Crashes(Car):
    def step(self, detected: bool) -> None:
        if self.gap_m < 12.0:
            raise IndexError("no road left")
        super().step(detected)


def test_correct_simulators_pass():
    check_simulator(Car, 40)
    check_simulator(lambda: ToyBraking(ToyParams(10, 5, 3, 0.9)), 10)
    check_simulator(SpeedFirst, 40)


@pytest.mark.parametrize(
    "make, message",
    [
        (SameNameTwice, "observation_names must be distinct (a signal reads its column by name), got 'gap_m' more"),
        (Float32, "observation() at the start must be a float64 numpy array of shape (2,)"),
        (NoReset, "reset() does not go back to the start"),
        (Noisy, "not deterministic: the same detections give observation"),
        (ShallowSnapshot, "restore(snapshot()) taken at step 20"),
        (Crashes, r"step\((True|False)\) at step 9 raised IndexError: no road left"),
    ],
    ids=["same-name-twice", "float32", "no-reset", "random", "snapshot", "raises"],
)
def test_broken_simulators_fail_with_the_rule_they_break(make, message):
    pattern = message if message.startswith("step") else re.escape(message)  # the gap first drops below 12 m at step 9
    with pytest.raises(CheckError, match="^check_simulator: " + pattern):
        check_simulator(make, 40, seed=1)


TOY = toy_problem(ToyParams(10, 5, 3, 0.9))  # p_fail = 0.1^3 = 1e-3
MC = ExperimentConfig.of(method="mc", n_per_stage=4000, seed=3)


def test_pemviz_s_estimators_pass_on_the_toy_and_meet_its_exact_answer():
    est = check_estimator(lambda pb: build_estimator(MC, pb), TOY, max_relative_error=0.6)
    assert est.n == 4000 and 0 < est.n_failures < 20  # ~4 failures expected at p = 1e-3
    adaptive = ExperimentConfig.of(n_stages=2, n_per_stage=200, n_final=400, ce_epochs=50, pretrain_epochs=50)
    est = check_estimator(lambda pb: build_estimator(adaptive, pb), TOY, max_relative_error=0.5)
    assert est.n_failures > 50  # the proposal finds the failures plain Monte Carlo barely sees


class Wrap:
    """An estimator delegating to pemviz's Monte Carlo, with one fault switched on."""

    def __init__(self, problem, fault: str) -> None:
        self.inner, self.fault = build_estimator(MC, problem), fault
        self.rng = self.inner.rng if fault != "unseeded" else np.random.default_rng()
        self.inner.rng = self.rng

    def next_stage(self):
        plan = self.inner.next_stage()
        if plan is None and self.fault == "endless":
            return dataclasses.replace(self._last, stage=self._last.stage + 1)
        self._last = plan or getattr(self, "_last", None)
        return plan

    def observe(self, batch, failed, robustness):
        log_w = self.inner.observe(batch, failed, robustness) if not self._done() else batch.log_weight()
        return log_w[:-1] if self.fault == "short-weights" else log_w

    def _done(self) -> bool:
        return getattr(self, "_finished", False)

    def finish(self):
        out = self.inner.finish() if not self._done() else self._out
        self._finished, self._out = True, out
        return out

    def result(self):
        est, used = self.inner.result()
        return (est, used + (7,)) if self.fault == "phantom-stage" else (est, used)


@pytest.mark.parametrize(
    "fault, message",
    [
        ("short-weights", r"observe\(\) at stage 1 must return float64 \[4000\] importance log-weights"),
        ("endless", r"next_stage\(\) still plans batches after 5 stages"),
        ("phantom-stage", r"result\(\) says it uses stages \[7\], which were never drawn"),
        ("unseeded", r"two runs disagree"),
    ],
)
def test_broken_estimators_fail_with_the_rule_they_break(fault, message):
    with pytest.raises(CheckError, match="^check_estimator: " + message):
        check_estimator(lambda pb: Wrap(pb, fault), TOY, max_stages=5)


def test_an_estimate_far_from_the_exact_answer_fails_and_bad_arguments_are_refused():
    with pytest.raises(CheckError, match=r"relative error; allowed 0.01"):
        check_estimator(lambda pb: build_estimator(MC, pb), TOY, max_relative_error=0.01)
    with pytest.raises(ValueError, match="metric 'loose'"):
        check_estimator(lambda pb: build_estimator(MC, pb), TOY, metric="loose")
    with pytest.raises(ValueError, match="n_steps must be an integer >= 1"):
        check_simulator(Car, 0)


@pytest.mark.parametrize("method", ["mc", "naive50", "mixed50", "adaptive", "ams", "tilt", "state"])
def test_every_method_passes_the_estimator_check_on_the_toy(method):
    """Every method of :data:`pemviz.methods.BUILTIN_METHODS` passes ``check_estimator`` (its interface, its estimate's
    consistency, the same bits twice) on the toy, within a factor 2 of the toy's exact 1e-3 at seed 3 (10,000
    rollouts a stage: plain Monte Carlo's relative standard deviation 0.32)."""
    from pemviz.methods import BUILTIN_METHODS as METHODS

    # a new method joins this test
    assert set(METHODS) == {"mc", "naive50", "mixed50", "adaptive", "ams", "tilt", "state"}
    cfg = ExperimentConfig.of(
        method=method,
        seed=3,
        n_stages=2,
        n_per_stage=10_000,
        n_final=2000,
        ce_epochs=50,
        pretrain_epochs=50,
    )
    est = check_estimator(lambda pb: build_estimator(cfg, pb), TOY, max_relative_error=1.0)
    assert est.n_failures > 0
