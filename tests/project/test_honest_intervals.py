"""The claims study (``benchmarks/honest_intervals.py``): each printed claim judged against the answer, on hand-made
runs whose verdicts are worked out here by hand, and one real run per kind of claim."""

import math

import pytest

from conftest import REPO, load_script

study = load_script(REPO / "benchmarks" / "honest_intervals.py")
Outcome = study.Outcome
LN2 = math.log(2.0)


def test_an_interval_is_off_by_more_than_x2_only_beyond_twice_its_ends():
    truth = math.log(1e-5)
    inside = Outcome("s", "m", 0, truth, truth, "interval", truth - 0.1, truth + 0.1, "reliable")
    near = Outcome("s", "m", 0, truth, truth + 0.5, "interval", truth + 0.2, truth + 0.6, "doubtful")  # x1.22 above
    far = Outcome("s", "m", 0, truth, truth + 1.5, "interval", truth + LN2 + 0.01, truth + 2.0, "doubtful")
    assert inside.holds and not inside.interval_off_x2
    assert not near.holds and not near.interval_off_x2  # a miss, but by less than x2
    assert not far.holds and far.interval_off_x2
    bound = Outcome("s", "m", 0, truth, truth + 5.0, "bound", truth + 3.0, math.inf, "unreliable")
    assert not bound.holds and not bound.interval_off_x2  # a bound that misses is counted as a bound, not an interval


def test_the_table_counts_each_goal_and_says_whether_all_are_met():
    t = math.log(1e-5)
    good = [Outcome("a", "adaptive", s, t, t, "interval", t - 0.1, t + 0.1, "reliable") for s in range(3)]
    good += [Outcome("a", "tilt", s, t, t - 1.0, "bound", t - 2.0, math.inf, "unreliable") for s in range(3)]
    rows, met = study.table(good)
    assert met and "printed lower bounds holding the answer: 3 of 3 (100.0%; goal >= 95 %)" in rows
    assert "| a | adaptive | 3 | 3 (3; 0) | 0 (0) | 0 | 0 | 0 |" in rows
    wrong = good + [Outcome("a", "ams", 0, t, t + 1.0, "interval", t + 0.8, t + 1.2, "reliable")]  # x2.7, reliable
    rows, met = study.table(wrong)
    assert not met and "'reliable' with the estimate outside x2: 1 (goal 0)" in rows
    assert "printed 95 % intervals off the answer by more than x2: 1 of 4 (goal 0)" in rows  # its low end is x2.2
    missed = good + [Outcome("a", "ams", 0, t, t + 2.0, "bound", t + 1.0, math.inf, "doubtful")]
    rows, met = study.table(missed)
    assert not met and "printed lower bounds holding the answer: 3 of 4 (75.0%; goal >= 95 %)" in rows


def test_a_real_run_of_each_claim(monkeypatch):
    """braking's default: a reliable interval; the crowd's default at seed 0 (plain Monte Carlo after its stages capped
    at 10 times their simulations, 72,000 rollouts, where the default draws 1,000,000): its stages doubtful, their
    retry at N = 400 unreliable, then plain Monte Carlo's exact interval, 2 failures: 2.78e-5 [3.36e-6, 1.00e-4]
    around the exact 3.40e-5 (2,100 + 5,100 + 72,000 simulations), the Clopper-Pearson interval of those counts."""
    from scipy.stats import beta

    braking = study.one_run("braking", "adaptive", 0)
    assert braking.claim == "interval" and braking.verdict == "reliable" and braking.holds
    default_config = study.default_config

    def capped(scene, seed, flags=()):
        return default_config(scene, seed, (*flags, "--plain-fallback", "10") if scene == "crowd" else flags)

    monkeypatch.setattr(study, "default_config", capped)
    crowd = study.one_run("crowd", "adaptive", 0)
    assert crowd.claim == "interval" and crowd.holds and crowd.sims == 7_200 + 72_000
    n = 72_000
    k = round(math.exp(crowd.log_mu) * n)  # plain Monte Carlo's mu_hat: its failures over its rollouts
    assert k == 2 and math.exp(crowd.log_mu) == pytest.approx(k / n, rel=1e-12)
    assert math.exp(crowd.lo) == pytest.approx(beta.ppf(0.025, k, n - k + 1), rel=1e-9)
    assert math.exp(crowd.hi) == pytest.approx(beta.ppf(0.975, k + 1, n - k), rel=1e-9)
    refused = study.one_run("crowd", "tilt", 0)
    assert refused.refused is not None and "no tilted proposal" in refused.refused
