"""The scenario registry and the conformance kit (pemviz.testing): every registered scenario and every method of
METHODS passes the kit (a new one is checked without a new test), and each of the kit's checks fails, naming itself,
on something broken on purpose."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from pemviz.estimators.fixed import FixedSampler
from pemviz.io.rollouts import read_rollouts
from pemviz.methods import BUILTIN_METHODS as METHODS
from pemviz.scenarios import builtin, register, registered
from pemviz.scenarios.problems import build_problem
from pemviz.scenarios.registry import get as get_scenario
from pemviz.scenarios.registry import unregister
from pemviz.scenarios.toy import ToyBraking
from pemviz.settings import SCENARIOS
from pemviz.testing import RUN_ROLLOUTS, ConformanceError, check_estimator, check_scenario

from conftest import doc_python_block

KNOWN_FAILURES: dict[str, str] = {}
"""Scenarios the kit finds at fault, with the failure it reports (none now). A naive50 run of a cut-in draws
detections of cars the camera cannot see (log p = -inf: an impossible event under the PEM, weight 0); its rollout
file holds them and re-estimates to the run's numbers, so the cut-in scenarios pass the kit."""


# -- the registry ---------------------------------------------------------------------------------------------------


def test_the_registry_holds_the_run_scenarios_and_the_toys_and_refuses_a_second_of_a_name():
    assert {*SCENARIOS, "toy", "crowd"} <= set(registered())
    toy = get_scenario("toy")
    assert toy.exact and get_scenario("crowd").exact and not get_scenario("cut-in").exact
    assert [p.name for p in toy.parameters()] == ["total", "braking", "safe"]
    assert toy.problem().exact_log_p == build_problem("toy").exact_log_p
    assert toy.problem(params={"total": 10, "braking": 5, "safe": 3}).exact_log_p == pytest.approx(math.log(1e-3))
    assert get_scenario("crowd").problem().exact_log_p == build_problem("crowd").exact_log_p
    assert get_scenario("cut-in-rare").default_params().cut_in_gap_m == 22.5  # the rare setting, not the dataclass's
    with pytest.raises(ValueError, match="'no_such' is not a parameter of the toy scenario; use one of total"):
        toy.build_params({"no_such": 1})
    with pytest.raises(ValueError, match="need 1 <= safe <= braking < total"):
        toy.problem(params={"safe": 60})
    with pytest.raises(KeyError, match="no scenario named 'nope'; registered: braking"):
        get_scenario("nope")
    with pytest.raises(ValueError, match="a scenario named 'toy' is registered already"):
        register(toy)
    mine = register(dataclasses.replace(toy, name="my-toy"))
    try:
        assert registered()[-1] == "my-toy" and get_scenario("my-toy") is mine
    finally:
        unregister("my-toy")
    assert "my-toy" not in registered()


def test_listing_the_scenarios_loads_no_problem_pem_or_torch():
    code = (
        "import sys; from pemviz.scenarios import registered; print(','.join(registered())); "
        "print([m for m in ('torch', 'pemviz.core.problems', 'pemviz.scenarios.problems', 'pemviz.pem') "
        "if m in sys.modules])"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split("\n")
    assert out[0].split(",")[:5] == ["braking", "cut-in", "cut-in-rare", "toy", "crowd"] and out[1] == "[]"


# -- everything pemviz has passes ------------------------------------------------------------------------------------


WITH_FEATURES = {"crossing", "toy", "cut-in", "cut-in-rare"}
"""The registered scenarios that report state features (pemviz.core.features), which the kit checks."""


CHECKED: dict[tuple[str, str], object] = {}
"""("scenario" or "estimator", name) -> the report of the kit's run above on it (its default arguments but a folder):
the user guide's example below prints the braking and the adaptive ones instead of running the same checks again."""


@pytest.mark.parametrize("name", registered())
def test_every_registered_scenario_passes_the_kit(name, tmp_path):
    if name in KNOWN_FAILURES:
        with pytest.raises(ConformanceError, match=KNOWN_FAILURES[name]):
            check_scenario(name)
        pytest.xfail(f"{name}: the kit finds it at fault, as KNOWN_FAILURES says")
    report = CHECKED["scenario", name] = check_scenario(name, folder=tmp_path)
    twin = () if get_scenario(name).simulator is None else ("twin",)
    drawing = () if get_scenario(name).drawing is None else ("drawing",)
    features = ("features",) if name in WITH_FEATURES else ()
    assert report.passed == (
        "schema",
        "problem",
        "determinism",
        *features,
        *twin,
        *drawing,
        "rollout-file",
        "recording",
    )
    files = [tmp_path / f"{name}-{method}.parquet" for method in ("naive50", "adaptive")]
    assert any(f.is_file() for f in files)
    for f in filter(Path.is_file, files):  # the kit's runs are small: no retry or plain Monte Carlo (1e6 rollouts)
        assert read_rollouts(f).observations.shape[0] <= 4 * RUN_ROLLOUTS


@pytest.mark.parametrize("method", METHODS)
def test_every_method_passes_the_kit(method):
    report = CHECKED["estimator", method] = check_estimator(method)
    weighted = method != "ams"  # splitting keeps no importance weights: no rollout file to estimate from
    assert report.passed == ("interface", "unbiased", "verdicts", *(("rollout-file",) * weighted), "recording")
    assert [name for name, _ in report.skipped] == ([] if weighted else ["rollout-file"])
    assert weighted or "without importance weights" in report.skipped[0][1]


def test_the_user_guide_s_kit_examples_run_as_written(capsys, monkeypatch):
    """The guide's examples, exec'd as written; its calls of the kit with one argument that the tests above made
    already (``check_scenario("braking")``, ``check_estimator("adaptive")``, 17 s) return those runs' reports."""
    import pemviz.testing

    for kind, check in (("scenario", pemviz.testing.check_scenario), ("estimator", pemviz.testing.check_estimator)):

        def reuse(name, *args, _kind=kind, _check=check, **kwargs):
            known = CHECKED.get((_kind, name)) if not args and not kwargs else None
            return known if known is not None else _check(name, *args, **kwargs)

        monkeypatch.setattr(pemviz.testing, f"check_{kind}", reuse)
    exec(doc_python_block("own-simulator.md", "## The conformance kit"), {"__name__": "guide"})
    try:
        exec(doc_python_block("own-simulator.md", "### A scenario of your own in the registry"), {"__name__": "guide"})
    finally:
        if "short-toy" in registered():
            unregister("short-toy")
    out = capsys.readouterr().out.splitlines()
    assert out[0] == (
        "scenario braking: 7 checks passed (schema, problem, determinism, twin, drawing, rollout-file, " "recording)"
    )
    assert out[1] == "estimator adaptive: 5 checks passed (interface, unbiased, verdicts, rollout-file, recording)"
    assert len(out) == 4
    assert out[2].startswith("scenario short-toy: 7 checks passed (schema, problem, determinism, features,")
    assert out[3] == "  skipped drawing: the problem has no drawing object: only its signals are drawn"


# -- each check fails on something broken ----------------------------------------------------------------------------

TOY = get_scenario("toy")


@dataclass(frozen=True)
class Unchecked:
    """A parameters dataclass without a range check."""

    speed_mps: float = 1.0


def unchecked_toy(config, params):
    return builtin.toy(config, None)


def noisy_toy(config, params):
    """The toy, whose rollouts move by a number the seed does not decide."""
    problem, own = builtin.toy(config, params), np.random.default_rng()

    def simulate(n, sampler, target, rng):
        batch = problem.simulate(n, sampler, target, rng)
        return batch.with_changes(observations=batch.observations + own.random(batch.observations.shape))

    return dataclasses.replace(problem, simulate=simulate)


def failing_factory(config, params):
    raise RuntimeError("no road")


class LateToy(ToyBraking):
    """A single toy simulator that brakes one unit later than the batched twin."""

    def step(self, detected: bool) -> None:
        super().step(detected and self.distance < self.params.braking)


@dataclass(frozen=True)
class Told:
    """An outcome (:class:`pemviz.core.drawing.Outcome`)."""

    failed: bool
    contact: bool = False
    short: str = "failed"
    rank: float = 0.0


@dataclass(frozen=True)
class AlwaysFailed:
    """A drawing object whose outcome says every rollout failed."""

    dt_s: float = 1.0

    def outcome(self, batch, i):
        return Told(True)


def always_failed(params):
    return AlwaysFailed()


def drawn_toy(config, params):
    """The toy, drawn by :class:`AlwaysFailed`."""
    return dataclasses.replace(builtin.toy(config, params), drawing=AlwaysFailed())


@pytest.mark.parametrize(
    "changes, message",
    [
        (
            dict(params=Unchecked, factory=unchecked_toy, simulator=None),
            r"schema: no far value of any parameter \(speed_mps: -1e12, 1e12\) is refused",
        ),
        (dict(factory=failing_factory), r"problem: the factory raised RuntimeError: no road"),
        (
            dict(factory=noisy_toy),
            r"determinism: seed 0, rollouts drawn by the target \(PEM\): the same seed again gives "
            r"other rollouts: observations\[0, 0, 0\] \(rollout 0, step 0\)",
        ),
        (
            dict(simulator=LateToy),
            r"twin: rollouts drawn by the target \(PEM\): the single simulator, then the batched "
            r"twin: observations\[\d+, 51, 0\] \(rollout \d+, step 51\): 49\.0 then 50\.0",
        ),
        (
            dict(factory=drawn_toy, drawing=always_failed),
            r"drawing: rollout 0 drawn by the target \(PEM\): outcome\(batch, 0\) is "
            r"Told\(failed=True.*failure event says "
            r"failed=False",
        ),
    ],
    ids=["schema", "problem", "determinism", "twin", "drawing"],
)
def test_each_scenario_check_fails_on_a_broken_scenario(changes, message):
    broken = dataclasses.replace(TOY, name="broken-toy", **changes)
    with pytest.raises(ConformanceError, match=r"^check_scenario\('broken-toy'\): " + message):
        check_scenario(broken)


def reestimated_off(monkeypatch):
    """The rollout file's estimate 1e-6 (relative) off the run's."""
    from pemviz.io import rollout_estimate

    original = rollout_estimate.estimate_rollouts

    def off(*args, **kwargs):
        result = original(*args, **kwargs)
        est = dataclasses.replace(result.estimate, log_mu_hat=result.estimate.log_mu_hat + 1e-6)
        return dataclasses.replace(result, estimate=est)

    monkeypatch.setattr(rollout_estimate, "estimate_rollouts", off)


def recording_fails(monkeypatch):
    """The recording sink raises at the run's answer."""
    from pemviz.sinks.recording import RerunSink

    def broken(self, event):
        raise OSError("disk full")

    monkeypatch.setattr(RerunSink, "on_final_estimate", broken)


@pytest.mark.parametrize(
    "break_it, message",
    [
        (reestimated_off, r"rollout-file: re-estimated from toy-adaptive\.parquet: log mu_hat = "),
        (recording_fails, r"recording: the recording sink raised OSError at FinalEstimate: disk full"),
    ],
    ids=["rollout-file", "recording"],
)
def test_each_file_check_of_a_scenario_fails_on_a_broken_file(break_it, message, monkeypatch):
    break_it(monkeypatch)
    with pytest.raises(ConformanceError, match=r"^check_scenario\('toy'\): " + message):
        check_scenario("toy")


def short_weights(monkeypatch):
    original = FixedSampler.observe
    monkeypatch.setattr(FixedSampler, "observe", lambda self, *args: original(self, *args)[:-1])


def doubled(monkeypatch):
    """mu_hat twice the estimator's: caught by ``unbiased`` where the estimates spread little (mixed-50's, coupled by
    Array-RQMC on the toy: below 1 %; plain Monte Carlo's i.i.d. 2 failures in 2,000 spread too widely for it)."""
    original = FixedSampler.result

    def result(self):
        est, used = original(self)
        return dataclasses.replace(est, log_mu_hat=est.log_mu_hat + math.log(2.0)), used

    monkeypatch.setattr(FixedSampler, "result", result)


def always_reliable(monkeypatch):
    """Every final estimate called reliable, whatever it is."""
    original = FixedSampler.result

    def result(self):
        est, used = original(self)
        return dataclasses.replace(est, verdict="reliable"), used

    monkeypatch.setattr(FixedSampler, "result", result)


@pytest.mark.parametrize(
    "break_it, method, message",
    [
        (short_weights, "mc", r"interface: check_estimator: observe\(\) at stage 1 must return float64 \[2000\]"),
        (
            doubled,
            "mixed50",
            r"unbiased: the mean of 8 estimates \(seeds 0\.\.7\) is 2\.00\d times the exact 0\.001 "
            r"\(\|log mean - log p\| = 0\.69\d nats\); allowed 1 \+- 0\.2",
        ),
        (
            always_reliable,
            "mc",
            r"verdicts: an estimate with 0 failures of 2000 and log mu_hat = -inf is called reliable",
        ),
        (
            reestimated_off,
            "mc",
            r"rollout-file: re-estimated from mc-seed0\.parquet: log mu_hat = -\d+\.\d+ \((\d+) failures of "
            r"2000\); the run's own: -\d+\.\d+ \(\1 of 2000\); allowed \|mu / mu_run - 1\| <= 1e-09",
        ),
        (recording_fails, "mc", r"recording: the recording sink raised OSError at FinalEstimate: disk full"),
    ],
    ids=["interface", "unbiased", "verdicts", "rollout-file", "recording"],
)
def test_each_estimator_check_fails_on_a_broken_estimator(break_it, method, message, monkeypatch):
    break_it(monkeypatch)
    with pytest.raises(ConformanceError, match=rf"^check_estimator\('{method}'\): " + message):
        check_estimator(method)


def test_the_kit_refuses_what_it_cannot_check():
    with pytest.raises(ValueError, match="unknown method 'bogus'"):
        check_estimator("bogus")
    never = dataclasses.replace(build_problem("toy-1e-3"), exact_log_p=None)
    with pytest.raises(ValueError, match="has no exact answer"):
        check_estimator("mc", problem=never)
    with pytest.raises(KeyError, match="no scenario named 'nope'"):
        check_scenario("nope")
