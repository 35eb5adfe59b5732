"""Starts inside the failure set, fixed (``--param NAME=VALUE``) or drawn per rollout (``--param NAME~DIST``), on every
registered scenario's parameters: a run ends with an estimate (a rollout that fails at step 0 is a failure with its
weight: p = 1 for a fixed start inside the set, the share of such starts over an ODD) or with one line and exit 2,
never a traceback. The braking scene's latched-brake variant has its exact answer for any start
(:func:`pemviz.scenarios.braking.truth_latched.latched_log_failure_probability`)."""

from __future__ import annotations

import math
import re
import traceback
from pathlib import Path

import pemviz
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from pemviz.cli import main
from pemviz.commands import UsageError
from pemviz.scenarios.parameters import ParameterError
from pemviz.scenarios.registry import Scenario, get, registered

SMALL = ["--no-record", "--k", "1", "--n", "20", "--n-final", "20", "--plain-fallback", "0", "--retry-factor", "0"]
PACKAGE = Path(pemviz.__file__).resolve().parent
ESTIMATE = re.compile(r"^(mu_hat = |no failure seen)", re.M)
FAST = {"cut-in": ["--method", "mc"], "crossing": ["--method", "mc"]}
"""The scenes whose default method takes 20-30 s at any budget (the cut-in's tilt, the crossing's CE fits on its
state): run by plain Monte Carlo here; the others by their default (the cross-entropy sampler on braking, toy,
crowd)."""


def run(argv: list[str], monkeypatch, capsys) -> tuple[int, str, str]:
    """The exit status, stdout and stderr of ``pemviz run ARGV``, checked: an estimate (exit 0, 1 or 3) or a refusal
    raised by pemviz's own code (a ValueError or UsageError, not one from numpy inside it) that the command prints as
    one line, exit 2."""
    monkeypatch.setenv("PEMVIZ_DEBUG", "1")  # every exception reaches here, with where it was raised
    try:
        code = main(["run", *argv])
    except (ValueError, UsageError) as exc:
        where = Path(traceback.extract_tb(exc.__traceback__)[-1].filename).resolve()
        assert PACKAGE in where.parents, "".join(traceback.format_exception(exc))  # not numpy's, not torch's
        capsys.readouterr()
        monkeypatch.delenv("PEMVIZ_DEBUG")
        code = main(["run", *argv])
        out = capsys.readouterr()
        assert code == 2 and len(out.err.splitlines()) == 1, out.err
        assert out.err.startswith("pemviz run: error: ") and str(exc).splitlines()[0] in out.err
        return code, out.out, out.err
    out = capsys.readouterr()
    assert code in (0, 1, 3), out.err
    assert ESTIMATE.search(out.out), out.out[-2000:]
    return code, out.out, out.err


def mu_hat(out: str) -> tuple[float, tuple[float, float], str]:
    """The run's mu_hat, its interval (a lower bound alone: ``(a, inf)``) and its final line."""
    line = next(x for x in out.splitlines() if x.startswith("mu_hat = ") and "CI" in x)
    number = r"(\d\.\d+e[-+]\d+)"
    ci = re.search(rf"CI \[{number}, {number}\]", line)
    bound = (float(ci[1]), float(ci[2])) if ci else (float(re.search(rf"p >= {number}", line)[1]), math.inf)
    return float(line.split()[2].rstrip(",")), bound, line


# -- the two commands -------------------------------------------------------------------------------------


def test_a_fixed_start_inside_the_failure_set_is_p_1_with_its_interval(monkeypatch, capsys):
    code, out, _ = run(["--param", "gap0_m=1.5", *SMALL], monkeypatch, capsys)  # gap 1.5 m < the 2 m margin
    p, (lo, hi), line = mu_hat(out)
    assert code == 0 and p == 1.0 and 0.8 < lo < 1.0 == hi and ": reliable" in line, line
    assert "mu_hat = 1.0000e+00 (log mu_hat = 0.0000 nats)" in out


@pytest.mark.parametrize("law", ["uniform(1,30)", "uniform(1,3)"])
def test_a_drawn_start_inside_the_failure_set_counts_its_share(law, monkeypatch, capsys):
    code, out, _ = run(["--param", f"gap0_m~{law}", *SMALL], monkeypatch, capsys)
    p, (lo, hi), line = mu_hat(out)
    assert code == 0 and 0.0 < lo <= p < 1.0, line


@pytest.mark.parametrize("method", [["--k", "1", "--n", "50", "--n-final", "200"], ["--method", "mc", "--n", "400"]])
def test_over_an_odd_the_share_of_starts_already_failed_is_the_exact_answer(method, monkeypatch, capsys):
    from pemviz.pem import load_pem
    from pemviz.scenarios.braking.simulator import BrakingParams
    from pemviz.scenarios.braking.truth_latched import latched_log_failure_probability

    logit = load_pem(None).logit_at_gap
    p_gap = {  # the latched scene's p(gap0): 1 below the 2 m margin, below 1e-42 from it on (falling with the gap)
        g: latched_log_failure_probability(logit, BrakingParams(latched_brake=True, gap0_m=g)).log_p_fail
        for g in (1.0, 1.5, 1.999, 2.0, 2.5, 3.0)
    }
    assert [p_gap[g] for g in (1.0, 1.5, 1.999)] == [0.0] * 3 and max(p_gap[g] for g in (2.0, 2.5, 3.0)) < -96
    exact = 0.5  # P(gap0 < 2) under uniform(1, 3), plus less than 1e-42
    argv = ["--param", "latched_brake=true", "--param", "gap0_m~uniform(1,3)", *method]
    code, out, _ = run([*argv, "--no-record", "--plain-fallback", "0", "--retry-factor", "0"], monkeypatch, capsys)
    p, (lo, hi), line = mu_hat(out)
    assert code == 0 and abs(p - exact) < 0.15 and lo <= exact <= hi, line  # 400 plain rollouts: se 0.025


# -- a start in contact: refused in one line ----------------------------------------------------------------------


@pytest.mark.parametrize("param", ["gap0_m=0.7", "gap0_m~uniform(0.5,3)", "contact_gap_m=13"])
def test_a_braking_start_in_contact_is_one_line_exit_2(param, monkeypatch, capsys):
    code, out, err = run(["--param", param, *SMALL], monkeypatch, capsys)
    assert code == 2 and out == "" and "gap0_m must be above contact_gap_m" in err, err


# -- every registered scenario's parameters ------------------------------------------------------------------------


def accepted(scenario: Scenario, name: str, value: object) -> bool:
    try:
        scenario.build_params({name: value})
    except ParameterError:
        return False
    return True


def allowed_range(scenario: Scenario, name: str) -> tuple[float, float]:
    """The values of the number ``name`` the scenario's dataclass takes around its default, [lo, hi]: found by
    doubling the step from the default until a value is refused (at most 4 times the default's size beyond it: the
    runs stay short), then halving the gap to it."""
    p = next(x for x in scenario.parameters() if x.name == name)
    whole, d = p.kind == "int", float(p.default)
    ends = []
    for sign in (-1.0, 1.0):
        inside, step, outside = d, max(abs(d), 1.0) / 4, None
        while step <= 4 * max(abs(d), 1.0):
            t = d + sign * step
            t = float(round(t)) if whole else t
            if not accepted(scenario, name, int(t) if whole else t):
                outside = t
                break
            inside, step = t, step * 2
        for _ in range(40 if outside is not None else 0):  # bisect between inside and outside
            mid = (inside + outside) / 2
            mid = float(round(mid)) if whole else mid
            if mid in (inside, outside):
                break
            if accepted(scenario, name, int(mid) if whole else mid):
                inside = mid
            else:
                outside = mid
        ends.append(inside)
    return ends[0], ends[1]


@st.composite
def assignments(draw, scenario_name: str) -> str:
    """One ``--param`` of the scenario: a fixed value anywhere in its range, or (a parameter it may draw per rollout)
    a law over a sub-range: ``uniform(a, b)``, or ``choice`` of whole numbers."""
    scenario = get(scenario_name)
    p = draw(st.sampled_from(scenario.parameters()))
    if p.kind == "bool":
        return f"{p.name}={str(draw(st.booleans())).lower()}"
    lo, hi = allowed_range(scenario, p.name)
    if p.kind == "int":
        values = st.integers(int(lo), int(hi))
        if p.name in scenario.random_params and draw(st.booleans()):
            chosen = sorted(set(draw(st.lists(values, min_size=2, max_size=3))))
            if len(chosen) > 1:
                return f"{p.name}~choice({', '.join(map(str, chosen))})"
        return f"{p.name}={draw(values)}"
    values = st.floats(lo, hi, allow_nan=False, allow_infinity=False)
    if p.name in scenario.random_params and draw(st.booleans()):
        a, b = sorted((draw(values), draw(values)))
        if a < b:
            return f"{p.name}~uniform({a!r}, {b!r})"
    return f"{p.name}={draw(values)!r}"


EXAMPLES = {"braking": 5, "toy": 3, "crowd": 3, "cut-in": 2, "cut-in-rare": 3, "crossing": 2}
INSIDE = {
    "braking": ["gap0_m=1.5", "gap0_m~uniform(1.0, 3.0)", "crash_gap_m=20.0", "gap0_m=0.7"],
    "cut-in": ["cut_in_grace_s=0.0"],
}
"""Starts inside the failure set (and one in contact), run besides the drawn examples: the gap below the margin, the
margin above the gap, the cut-in's safe distance with no grace from step 0."""


@pytest.mark.parametrize("scenario_name", registered())
def test_any_start_of_any_scenario_is_an_estimate_or_one_line(scenario_name, monkeypatch, capsys):
    if not get(scenario_name).parameters():
        pytest.skip(f"{scenario_name} has no parameters")

    @settings(
        max_examples=EXAMPLES.get(scenario_name, 2),
        deadline=None,
        database=None,
        derandomize=True,  # the same examples in every run: CI cannot meet a draw no developer saw
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    )
    @given(param=assignments(scenario_name))
    def check(param: str) -> None:
        run(["--scenario", scenario_name, "--param", param, *SMALL, *FAST.get(scenario_name, [])], monkeypatch, capsys)

    for param in INSIDE.get(scenario_name, []):
        check = example(param=param)(check)
    check()
