"""A Monte Carlo reference shown beside an estimate where no exact answer is known: its interval against the beta
quantiles of Clopper & Pearson (1934), the line every sink prints, and which problems carry one."""

from __future__ import annotations

import math

import pytest
from pemviz.config import ExperimentConfig
from pemviz.core.estimate import Estimate, Reference
from pemviz.scenarios.problems import problem_for
from scipy.stats import beta

from conftest import run_cli


def an_estimate(mu: float, lo: float, hi: float) -> Estimate:
    return Estimate(
        2100, 50, math.log(mu), 40.0, 40.0, 20.0, (math.log(lo), math.log(hi)), 0.3, 0.0, "reliable", "50 failures"
    )


def test_the_reference_interval_is_clopper_pearsons_beta_quantiles():
    r = Reference(866, 10_000_000, "plain Monte Carlo")
    assert r.log_p == pytest.approx(math.log(8.66e-5), abs=1e-12)
    lo, hi = beta.ppf(0.025, 866, 10_000_000 - 866 + 1), beta.ppf(0.975, 866 + 1, 10_000_000 - 866)
    assert math.exp(r.log_ci[0]) == pytest.approx(lo, rel=1e-6)
    assert math.exp(r.log_ci[1]) == pytest.approx(hi, rel=1e-6)
    assert r.text() == "8.66e-05 [8.09e-05, 9.26e-05] (866 failures in 10,000,000 rollouts, plain Monte Carlo)"


def test_a_reference_without_a_failure_is_refused():
    with pytest.raises(ValueError, match="need 1 <= n_failures <= n, got 0 of 1000"):
        Reference(0, 1000)


def test_the_summary_compares_the_estimate_with_the_reference_when_no_exact_answer_is_known():
    r = Reference(866, 10_000_000, "plain Monte Carlo")
    near = an_estimate(9.0e-5, 7.0e-5, 1.2e-4)
    assert near.summary(None, r).endswith(
        "; reference 8.66e-05 [8.09e-05, 9.26e-05] (866 failures in 10,000,000 rollouts, plain Monte Carlo): "
        "relative error 0.0393, inside the interval"
    )  # |9.0 - 8.66| / 8.66 = 0.03926
    far = an_estimate(1.455e-16, 2.08e-17, 1.02e-15)
    # 8.66e-5 / 1.455e-16
    assert far.summary(None, r).endswith("11.8 orders of magnitude too low, OUTSIDE the interval")
    # an exact answer, where known, is the one shown
    assert "reference" not in near.summary(math.log(8.66e-5), r) and "exact 8.660e-05" in near.summary(
        math.log(8.66e-5), r
    )


def test_an_estimate_far_off_says_by_how_much():
    from pemviz.core.estimate import error_text

    truth = math.log(2e-15)
    assert error_text(math.log(2.05e-15), truth) == "relative error 0.025"
    assert error_text(math.log(3.9e-15), truth) == "relative error 0.95"  # within x2: a relative error
    assert error_text(math.log(8e-15), truth) == "4 times too high"
    assert error_text(math.log(2e-16), truth) == "1.0 orders of magnitude too low"
    assert error_text(math.log(2e-24), truth) == "9.0 orders of magnitude too low"
    assert error_text(-math.inf, truth) == "no failure seen"


def test_only_the_moderate_cut_in_with_the_shipped_pems_carries_the_reference():
    cut_in = problem_for(ExperimentConfig.of(scenario="cut-in"))
    assert (cut_in.reference.n_failures, cut_in.reference.n) == (1176, 14_800_000) and cut_in.exact_log_p is None
    assert problem_for(ExperimentConfig.of(scenario="cut-in", pem="ml-nn")).reference == cut_in.reference
    assert problem_for(ExperimentConfig.of(scenario="cut-in", pem="gbt")).reference is None  # drawn under ml-nn only
    assert problem_for(ExperimentConfig.of(scenario="cut-in-rare")).reference is None
    assert problem_for(ExperimentConfig.of()).reference is None  # the braking scenario has its exact answer


def test_a_cut_in_run_prints_its_estimate_beside_the_reference():
    proc = run_cli(
        "run", "--scenario", "cut-in", "--method", "mc", "--n", "200", "--seed", "3", "--no-record", timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    last = next(ln for ln in proc.stdout.splitlines() if ln.startswith("no failure seen in "))
    assert last.startswith("no failure seen in 200 rollouts: p < 1.50e-02 (95%, rule of three")  # no point estimate
    assert last.endswith(
        "; reference 7.95e-05 [7.50e-05, 8.41e-05] (1,176 failures in 14,800,000 rollouts, plain "
        "Monte Carlo, shipped PEMs): no failure seen, inside the interval"
    )


def test_the_config_knows_how_many_objects_each_scenario_perceives():
    from pemviz.config import objects_of
    from pemviz.settings import SCENARIOS

    for scenario in SCENARIOS:  # the record says what its problem perceives, before anything is loaded
        assert problem_for(ExperimentConfig.of(scenario=scenario)).n_objects == objects_of(scenario), scenario
    assert (objects_of("braking"), objects_of("cut-in"), objects_of("no-such-scene")) == (1, 5, 1)
