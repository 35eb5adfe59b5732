"""A requirement on p (``pemviz run --require``): the parser, the alpha-spending sequential test, its error rate on
plain Monte Carlo with a known p, the braking scene's outcomes against its exact answer 1.984e-15, and the files a
CI job reads (the JSON against the schema in the docs, the JUnit file through a JUnit reader)."""

from __future__ import annotations

import json
import math
import re
import shlex
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from pemviz.core.confidence import CI_LEVEL, clopper_pearson
from pemviz.core.estimate import Estimate, estimate
from pemviz.core.requirement import (
    ALPHA,
    Requirement,
    RequirementError,
    alpha_at_look,
    decide,
    interval_at_level,
    parse_requirement,
)

from conftest import REPO, result_schema, run_cli

CI_PAGE = REPO / "docs" / "ci.md"


@pytest.mark.parametrize(
    "text, op, t",
    [("p < 1e-9", "<", 1e-9), ("p<=0.5", "<=", 0.5), (" p >2.5E-3 ", ">", 2.5e-3), ("p >= 1e-300", ">=", 1e-300)],
)
def test_parse_requirement(text, op, t):
    assert parse_requirement(text) == Requirement(op, t)


@pytest.mark.parametrize(
    "text",
    [
        "p < 0",
        "p < 1",
        "p < 2",
        "q < 1e-9",
        "p = 1e-9",
        "p < abc",
        "p < 1e-9 and more",
        "",
        "p <",
        "p < nan",
        "p < -1e-9",
    ],
)
def test_bad_requirements_raise_one_error(text):
    with pytest.raises(RequirementError):
        parse_requirement(text)


@given(op=st.sampled_from(["<", "<=", ">", ">="]), t=st.floats(1e-300, 0.999999, allow_nan=False))
def test_a_requirement_prints_as_it_parses(op, t):
    req = parse_requirement(f"p {op} {t!r}")
    assert req == Requirement(op, t) and parse_requirement(str(req)).op == op


@given(st.text(max_size=40))
def test_any_text_parses_or_raises_requirement_error(text):
    try:
        req = parse_requirement(text)
    except RequirementError:
        return
    assert 0.0 < req.threshold < 1.0 and req.op in ("<", "<=", ">", ">=")


def test_the_looks_spend_alpha_and_no_more():
    # sum over j of 6 / (pi^2 j^2) = 1 (Euler): the error of every look together is alpha
    assert math.isclose(sum(alpha_at_look(j) for j in range(1, 200_001)), ALPHA, rel_tol=1e-5)
    assert math.isclose(alpha_at_look(1), 0.05 * 6 / math.pi**2) and math.isclose(
        1 - alpha_at_look(2), 0.99240091, rel_tol=1e-8
    )
    with pytest.raises(ValueError):
        alpha_at_look(0)


def is_estimate(seed: int = 0, n: int = 2000) -> Estimate:
    rng = np.random.default_rng(seed)
    failed = rng.random(n) < 0.3
    log_w = rng.normal(-20.0, 0.5, n)
    return estimate(log_w, failed, np.full(n, -10.0))


def test_the_interval_at_the_run_s_own_level_is_the_printed_one():
    e = is_estimate()
    assert np.allclose(interval_at_level(e, CI_LEVEL, plain_mc=False), e.log_ci, rtol=0, atol=1e-12)
    lo, hi = interval_at_level(e, 0.999, plain_mc=False)
    assert lo < e.log_ci[0] < e.log_mu_hat < e.log_ci[1] < hi
    mc = estimate(np.zeros(1000), np.arange(1000) < 7, np.zeros(1000))
    assert np.allclose(np.exp(interval_at_level(mc, CI_LEVEL, plain_mc=True)), clopper_pearson(7, 1000), rtol=1e-12)
    # no failure in 1000 rollouts of the PEM: the exact one-sided bound at level 0.99 is 1 - 0.005^(1/1000)
    for k, n, level in ((0, 50, 0.9), (1, 10, 0.99), (50, 50, 0.95), (123, 100_000, 0.9924)):  # against scipy.stats
        from scipy.stats import binomtest

        ci = binomtest(k, n).proportion_ci(confidence_level=level, method="exact")
        assert np.allclose(clopper_pearson(k, n, level), (ci.low, ci.high), rtol=1e-8, atol=1e-15)  # scipy root-finds
    none = estimate(np.zeros(1000), np.zeros(1000, bool), np.zeros(1000))
    assert math.isclose(
        math.exp(interval_at_level(none, 0.99, plain_mc=True)[1]), 1 - 0.005 ** (1 / 1000), rel_tol=1e-9
    )


def test_decisions_by_hand():
    e = is_estimate()  # reliable, about 0.3 e^-20 = 6.2e-10 [...]
    mu = math.exp(e.log_mu_hat)
    assert e.verdict == "reliable"
    assert decide(e, Requirement("<", mu * 2), 1, False).outcome == "met"
    assert decide(e, Requirement("<", mu / 2), 1, False).outcome == "violated"
    assert decide(e, Requirement(">", mu / 2), 1, False).outcome == "met"
    assert decide(e, Requirement(">=", mu * 2), 1, False).outcome == "violated"
    assert decide(e, Requirement("<", mu), 1, False).outcome == "undecided"
    # a threshold just outside the 95 % interval but inside the wider one of look 1 (96.96 %): undecided
    t = math.exp(e.log_ci[1] + 0.1 * (interval_at_level(e, 1 - alpha_at_look(1), False)[1] - e.log_ci[1]))
    assert decide(e, Requirement("<", t), 1, False).outcome == "undecided"
    # an interval whose verdict is not reliable decides nothing
    bad = Estimate(e.n, 3, e.log_mu_hat, 1.0, 1.0, 2.0, e.log_ci, 0.9, 0.0, "doubtful", "3 failures")
    assert decide(bad, Requirement("<", mu * 100), 1, False).outcome == "undecided"


def sequential_mc(p: float, t: float, rng: np.random.Generator, n0: int = 1000, cap: int = 2_000_000) -> str:
    """The sequential test on plain Monte Carlo draws of a known p: batches doubling from n0 until decided or cap."""
    failures, n, look = 0, 0, 0
    batch = n0
    while n < cap:
        failures += int(rng.binomial(batch, p))
        n += batch
        look += 1
        e = Estimate(
            n,
            failures,
            math.log(max(failures, 1e-300) / n),
            0.0,
            0.0,
            float(failures),
            (0.0, 0.0),
            math.nan,
            0.0,
            "reliable",
            "",
        )
        d = decide(e, Requirement("<", t), look, plain_mc=True)
        if d.outcome != "undecided":
            return d.outcome
        batch = n
    return "undecided"


def test_the_sequential_test_keeps_its_error_rate_on_a_known_p():
    """p = 1e-3 against p < 1.25e-3 and against p < 0.8e-3: 400 sequential runs each, looks after every doubling.
    A wrong decision (violated when p < t holds, met when it does not) is at most 5 % by design; its binomial 99 %
    upper bound over 400 runs allows 9 wrong (0.05 x 400 = 20 would fail)."""
    rng = np.random.default_rng(7)
    wrong_high = sum(sequential_mc(1e-3, 1.25e-3, rng) == "violated" for _ in range(400))
    wrong_low = sum(sequential_mc(1e-3, 0.8e-3, rng) == "met" for _ in range(400))
    assert wrong_high <= 9 and wrong_low <= 9, (wrong_high, wrong_low)
    # the naive rule (the 95 % interval at every look, the same doubling batches) errs more often: the reason for
    # the spending
    naive_wrong = 0
    for _ in range(400):
        failures = n = 0
        batch = 1000
        while n < 2_000_000:
            failures += int(rng.binomial(batch, 1e-3))
            n += batch
            lo, hi = clopper_pearson(failures, n, CI_LEVEL)
            if hi < 1.25e-3 or lo >= 1.25e-3:
                naive_wrong += lo >= 1.25e-3
                break
            batch = n
    assert naive_wrong > wrong_high, (naive_wrong, wrong_high)


def schema() -> dict:
    return result_schema()


@pytest.mark.parametrize("require, code, outcome", [("p < 1e-13", 0, "met"), ("p < 1e-16", 1, "violated")])
def test_braking_requirements_against_the_exact_answer(tmp_path, require, code, outcome):
    """The exact answer is 1.984e-15: p < 1e-13 holds, p < 1e-16 does not (seed 0; benchmarks/requirement_gate.py
    runs 10 seeds of each)."""
    jsonschema = pytest.importorskip("jsonschema")
    proc = run_cli("run", "--require", require, "--no-record", "--json", str(tmp_path / "r.json"), cwd=tmp_path)
    assert proc.returncode == code, proc.stderr[-2000:]
    assert f"stop: requirement {outcome}: {require} " in proc.stdout
    doc = json.loads((tmp_path / "r.json").read_text())
    jsonschema.validate(doc, schema())
    assert doc["requirement"]["outcome"] == outcome and doc["requirement"]["exit_code"] == code
    assert doc["exact"]["p"] == pytest.approx(1.984e-15, rel=1e-3) and doc["seed"] == 0
    assert doc["estimate"]["log_ci95"][0] < doc["exact"]["log_p"] < doc["estimate"]["log_ci95"][1]


def test_a_close_threshold_is_undecided_at_a_cap_and_the_junit_file_says_so(tmp_path):
    junitparser = pytest.importorskip("junitparser")
    jsonschema = pytest.importorskip("jsonschema")
    proc = run_cli(
        "run",
        "--require",
        "p < 2e-15",
        "--max-sims",
        "3000",
        "--no-record",
        "--json",
        str(tmp_path / "r.json"),
        "--junit",
        str(tmp_path / "r.xml"),
        cwd=tmp_path,
    )
    assert proc.returncode == 3, proc.stderr[-2000:]
    assert "stop: requirement undecided within budget: --max-sims 3,000 reached" in proc.stdout
    jsonschema.validate(json.loads((tmp_path / "r.json").read_text()), schema())
    xml = junitparser.JUnitXml.fromfile(str(tmp_path / "r.xml"))
    suites = list(xml) if isinstance(xml, junitparser.JUnitXml) else [xml]
    cases = [case for suite in suites for case in suite]
    assert len(cases) == 1 and cases[0].name == "p < 2e-15" and cases[0].classname == "pemviz.braking"
    (result,) = cases[0].result
    assert isinstance(result, junitparser.Error) and result.type == "undecided"
    assert suites[0].errors == 1 and suites[0].failures == 0 and suites[0].tests == 1


@pytest.mark.parametrize(
    "args, message",
    [
        (
            ["--require", "p < 2"],
            "--require: require = 'p < 2' is invalid: 'p < 2': the threshold must be a probability",
        ),
        (["--require", "p < 1e-9", "--rel-error", "0.1"], "give one stop rule"),
        (["--require", "p < 1e-9", "--method", "ams"], "method ams has no final batch to add to"),
        (["--junit", "x.xml"], "--junit writes a requirement as a test case: give one with --require"),
        (["--json", "x.txt"], "--json"),
        (
            ["--save-rollouts", "b.parquet", "--json", "b.rollouts.json"],
            "--json and --save-rollouts (its sidecar) both write b.rollouts.json",
        ),
        (["--save", "r.rrd", "--json", "r.result.json"], "--json and --save (its result document) both write"),
    ],
)
def test_bad_requirement_flags_are_one_line(tmp_path, args, message):
    proc = run_cli("run", *args, *([] if "--save" in args else ["--no-record"]), cwd=tmp_path)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert message in proc.stderr, proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_distinct_outputs_pass_and_a_clash_names_both_flags(tmp_path):
    """Every output a run can write, with distinct names, passes; the same file reached by two flags (a report's
    Markdown twin given as --json's name would need a .json twin, so a recording's result document is used) fails."""
    from pemviz.commands import UsageError
    from pemviz.commands.run_outputs import RunOutputs, check_distinct

    check_distinct(
        RunOutputs(
            tmp_path / "r.rrd", tmp_path / "b.parquet", tmp_path / "r.json", tmp_path / "r.xml", tmp_path / "r.html"
        )
    )  # r.result.json, b.rollouts.json, r.md: all distinct
    check_distinct(RunOutputs(None, tmp_path / "b.parquet", tmp_path / "b.json"))  # --json b.json: its own
    with pytest.raises(UsageError, match=r"--json and --save \(its result document\) both write .*r.result.json"):
        check_distinct(RunOutputs(tmp_path / "r.rrd", json=tmp_path / "r.result.json"))
    with pytest.raises(UsageError, match=r"--json and --save-rollouts \(its sidecar\) both write"):
        check_distinct(RunOutputs(rollouts=tmp_path / "x" / ".." / "b.parquet", json=tmp_path / "b.rollouts.json"))


def test_the_ci_page_s_job_runs_as_written(tmp_path):
    """The `pemviz` commands of the CI page's job, run in a fresh folder: exit 0 and the three artifacts written."""
    jsonschema = pytest.importorskip("jsonschema")
    job = re.search(r"<!-- ci job -->\n```yaml\n(.*?)```", CI_PAGE.read_text(), re.S).group(1)
    commands = [line.split("run:", 1)[1].strip() for line in job.splitlines() if line.strip().startswith("run: pemviz")]
    assert commands and all(c.startswith("pemviz run --require") for c in commands)
    for command in commands:  # `pemviz` as this interpreter's module: the venv need not be on the PATH
        argv = [sys.executable, "-m", "pemviz.cli", *shlex.split(command)[1:]]
        proc = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-2000:]
    artifacts = re.search(r"path: \|\n((?:\s+\S+\n)+)", job).group(1).split()
    assert artifacts == ["gate.rrd", "gate.json", "gate.xml", "gate.html", "gate.md"]
    for name in artifacts:  # every artifact the job keeps was written
        assert (tmp_path / name).stat().st_size > 0, name
    doc = json.loads((tmp_path / "gate.json").read_text())
    jsonschema.validate(doc, schema())
    assert doc["recording"].endswith("gate.rrd") and doc["requirement"]["outcome"] == "met"
