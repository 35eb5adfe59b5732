"""The lower bound a run prints where its weights back no interval (pemviz.core.confidence.betting_lower_bound): by
hand, against an independent root finder, its coverage under heavy-tailed and adapted weights where the CLT interval
fails, and what it decides for `--require`."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from pemviz.core.confidence import BET_FRACTIONS, betting_lower_bound, log_mean_interval, markov_lower_bound
from pemviz.core.estimate import estimate
from pemviz.core.requirement import decide, parse_requirement
from scipy.optimize import brentq
from scipy.special import logsumexp

from conftest import run_cli


def wealth(xs: np.ndarray, m: float) -> float:
    """The bettors' mean wealth (1/J) sum_j prod_i (1 - l_j + l_j x_i / m), written out in plain float64."""
    return float(np.mean([np.prod(1.0 - lam + lam * xs / m) for lam in BET_FRACTIONS]))


def test_one_term_by_hand():
    # n = 1, X = x: (1/30) sum_j (1 - l_j + l_j x / m) = 20 solves to m = S x / (570 + S), S = sum_j l_j = 1 - 2^-30
    s = float(BET_FRACTIONS.sum())
    assert s == pytest.approx(1.0 - 2.0**-30, rel=1e-15)
    for x in (20.0, 3.7e-9, 1e-200):
        exact = math.log(s * x / (570.0 + s))
        got = betting_lower_bound(np.array([math.log(x)]))
        assert exact - 0.0102 <= got <= exact + 1e-6  # the terms are rounded down to 0.01 nats: never above


def test_many_terms_against_an_independent_root_finder():
    rng = np.random.default_rng(3)
    xs = np.where(rng.random(400) < 0.2, rng.lognormal(0.0, 2.0, 400), 0.0)
    log_xs = np.full(400, -np.inf)
    log_xs[xs > 0] = np.log(xs[xs > 0])
    root = brentq(lambda m: wealth(xs, m) - 20.0, 1e-6, xs.max(), xtol=1e-14)
    got = betting_lower_bound(log_xs)
    assert math.log(root) - 0.0102 <= got <= math.log(root) + 1e-6
    assert got < math.log(xs.mean())  # below the estimate; a tighter alpha gives a lower bound
    assert betting_lower_bound(log_xs, alpha=0.001) < got


def test_no_failure_bounds_nothing_and_alpha_is_checked():
    assert betting_lower_bound(np.full(10, -np.inf)) == -math.inf
    with pytest.raises(ValueError, match="alpha must be in"):
        betting_lower_bound(np.zeros(3), alpha=1.0)


def heavy_run(rng: np.random.Generator, n: int, log_p: float, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """n importance-sampling rollouts whose failure weights are lognormal with sigma nats of spread (a k-hat far
    above 0.7 for sigma >= 3), half of them failing, E[1[fail] w] = p exactly."""
    failed = rng.random(n) < 0.5
    log_w = rng.normal(0.0, sigma, n) - 0.5 * sigma**2 + log_p + math.log(2.0)
    return log_w, failed


@pytest.mark.parametrize("sigma", [1.0, 4.0])
def test_the_bound_holds_under_a_heavy_tail_where_the_clt_interval_does_not(sigma):
    rng = np.random.default_rng(11)
    log_p, runs = math.log(7.85e-5), 300
    held = clt = tail = shown = 0
    for _ in range(runs):
        log_w, failed = heavy_run(rng, 400, log_p, sigma)
        e = estimate(log_w, failed, np.zeros(400))
        held += e.log_lower_bound <= log_p
        _, lo, hi = log_mean_interval(np.where(failed, log_w, -np.inf))  # symmetric: t on both sides
        clt += lo <= log_p <= hi
        tail += e.log_ci[0] <= log_p <= e.log_ci[1]  # the upper end widened by the weights' k-hat
        shown += e.covers(log_p)  # what the run prints: its interval where backed, else its bound
    assert held / runs >= 0.95 and shown / runs >= 0.95
    if sigma >= 4.0:  # the weights' tail breaks the symmetric CLT interval; the verdict does not print it
        assert clt / runs < 0.6
        assert tail / runs == pytest.approx(284 / 300)  # the k-hat's upper end (k-hat > 0.9 here) holds p


def test_the_bound_holds_when_a_stage_adapts_to_the_last():
    # p = P(Z > 3.5), Z ~ N(0, 1); stage 1 draws from N(0, 1), stage 2 from N(theta, 1) with theta the mean of stage 1's
    # largest draws: exact weights p(z) / q(z), the terms' conditional mean is p at every rollout
    rng = np.random.default_rng(5)
    log_p = float(np.log(0.5 * math.erfc(3.5 / math.sqrt(2.0))))
    held = 0
    for _ in range(300):
        z1 = rng.normal(size=100)
        theta = float(np.sort(z1)[-10:].mean())
        z2 = rng.normal(theta, 1.0, 100)
        log_w = np.concatenate([np.zeros(100), -theta * z2 + 0.5 * theta**2])
        failed = np.concatenate([z1 > 3.5, z2 > 3.5])
        e = estimate(log_w, failed, np.zeros(200))
        held += e.n_failures == 0 or e.log_lower_bound <= log_p
    assert held >= 285


def test_an_unbacked_estimate_prints_its_bound_and_a_backed_one_its_interval():
    rng = np.random.default_rng(2)
    log_w, failed = heavy_run(rng, 400, math.log(1e-6), 5.0)
    e = estimate(log_w, failed, np.zeros(400))
    assert e.verdict != "reliable" and not e.interval_backed
    assert e.interval_text() == f">= {format(math.exp(e.log_lower_bound), '.2e').replace('e-0', 'e-0')}, no upper"
    assert e.shown_log_ci == (e.log_lower_bound, math.inf)
    assert "no 95% CI from these weights: p >= " in e.summary() and "no upper bound from this run" in e.summary()
    mc = estimate(np.zeros(1000), np.arange(1000) < 40, np.zeros(1000))  # plain Monte Carlo: always its interval
    assert mc.interval_backed and mc.interval_text().startswith("[") and mc.shown_log_ci == mc.log_ci
    # its lower bound is the one-sided Clopper-Pearson bound: P(Binomial(1000, L) >= 40) = 0.05
    from scipy.stats import binom

    assert binom.sf(39, 1000, math.exp(mc.log_lower_bound)) == pytest.approx(0.05, rel=1e-6)


def test_markov_is_the_bound_of_an_estimate_kept_whole():
    from pemviz.core.estimate import Estimate

    e = Estimate(
        100, 12, math.log(3e-7), 1.0, 1.0, 4.0, (-20.0, -10.0), verdict="doubtful", markov_logs=(math.log(3e-7),)
    )
    assert e.log_lower_bound == pytest.approx(math.log(0.05 * 3e-7), rel=1e-12)
    assert e.log_lower_bound == markov_lower_bound(np.array([math.log(3e-7)]))


@pytest.mark.parametrize(
    "text, outcome",
    [("p < 1e-13", "violated"), ("p < 1e-11", "undecided"), ("p >= 1e-13", "met"), ("p > 1e-11", "undecided")],
)
def test_require_decides_on_the_bound_one_way_only(text, outcome):
    rng = np.random.default_rng(2)
    log_w, failed = heavy_run(rng, 400, math.log(1e-10), 5.0)
    e = estimate(log_w, failed, np.zeros(400))
    # unreliable; its bound at the first look's level is 10^-12.09, its estimate 10^-10.90 (p = 1e-10)
    assert not e.interval_backed and -13 * math.log(10) < e.lower_bound(0.0304) < -11 * math.log(10) < e.log_mu_hat
    d = decide(e, parse_requirement(text), look=1, plain_mc=False)
    assert d.outcome == outcome and d.log_ci[1] == math.inf
    assert "lower bound" in d.why


def test_require_on_a_run_that_prints_only_a_bound_exits_1_above_and_3_below(tmp_path):
    # K = 3 stages of 100 and 200 final rollouts on braking, seed 0: doubtful (ESS 11), 95 % lower bound 1.14e-15
    common = ("run", "--k", "3", "--n", "100", "--n-final", "200", "--seed", "0", "--no-record", "--max-sims", "600")
    above = run_cli(*common, "--require", "p < 1e-15", cwd=tmp_path)  # the exact p is 1.984e-15: violated, rightly
    assert above.returncode == 1, above.stderr[-2000:]
    violated = r"^stop: requirement violated: p < 1e-15 fails on the 0\.9696 lower bound p >= 1\.1\de-15 at look 1"
    assert re.search(violated, above.stdout, re.M), above.stdout[-1500:]
    below = run_cli(*common, "--require", "p < 1e-14", cwd=tmp_path)
    assert below.returncode == 3, below.stderr[-2000:]
    assert "is below the threshold: it decides nothing" in below.stdout
    assert "no 95% CI from these weights: p >= 1.14e-15" in below.stdout


def test_pooled_stage_weights_bet_on_each_rollout_s_own_term():
    from pemviz.estimators.pooling import pool

    rng = np.random.default_rng(4)
    parts = [(rng.normal(-20.0, 3.0, 200), rng.random(200) < 0.3, np.zeros(200)) for _ in range(3)]
    raw = np.concatenate([np.where(f, lw, -np.inf) for lw, f, _ in parts])
    lam = np.array([1.0, 4.0, 9.0]) / 14.0
    e = pool(parts, lam)
    assert e.log_lower_bound == pytest.approx(betting_lower_bound(raw), abs=1e-9)
    assert float(logsumexp(raw)) > e.log_lower_bound


def test_every_output_of_a_run_that_backs_no_interval_shows_its_bound_and_no_upper_end(tmp_path):
    # the same doubtful braking run (95 % lower bound 1.14e-15): the JSON, the JUnit case and the report
    import json

    from junitparser import JUnitXml

    out = {k: tmp_path / f"r.{k}" for k in ("json", "xml", "html")}
    proc = run_cli(
        "run",
        "--k",
        "3",
        "--n",
        "100",
        "--n-final",
        "200",
        "--seed",
        "0",
        "--no-record",
        "--max-sims",
        "600",
        "--require",
        "p < 1e-14",
        "--json",
        str(out["json"]),
        "--junit",
        str(out["xml"]),
        "--report",
        str(out["html"]),
        cwd=tmp_path,
    )
    assert proc.returncode == 3, proc.stderr[-2000:]
    doc = json.loads(out["json"].read_text())["estimate"]
    assert doc["interval"] == "lower_bound95" and doc["ci95"][1] is None and doc["log_ci95"][1] is None
    assert doc["ci95"][0] == pytest.approx(1.1448e-15, rel=1e-3) == doc["lower_bound95"]
    case = next(iter(next(iter(JUnitXml.fromfile(str(out["xml"]))))))
    assert "lower bound p >= 1.11e-15" in case.result[0].message and "decides nothing" in case.result[0].message
    page = out["html"].read_text()
    assert "p &gt;= 1.145e-15, no upper bound from this run" in page or "p >= 1.145e-15, no upper bound" in page
    assert "95 % lower bound (whatever the weights" in page
