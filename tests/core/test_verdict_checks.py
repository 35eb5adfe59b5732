"""The verdict's checks (pemviz.core.verdict_checks) agree with the verdict itself (pemviz.core.estimate._verdict):
an estimate is reliable exactly when every check passed, and the worst failed check says the verdict it got; a check
that passed is never worded as failed."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from pemviz.core.estimate import VERDICTS, _verdict
from pemviz.core.verdict_checks import Check, verdict_checks


def worst_of(checks: list[Check]) -> str:
    """The best verdict the failed checks allow: ``reliable`` when none failed, else the worst of their
    :attr:`Check.fails_to` (its first word)."""
    failed = [c.fails_to.split(":")[0] for c in checks if c.passed is False]
    return max(failed, key=VERDICTS.index) if failed else "reliable"


def test_a_reliable_run_s_checks_read_as_passed():
    """The default braking run's figures (1,402 failures of 1,800, ESS 476.8, k-hat 0.21): each check says what it
    found, its rule and "passed"."""
    checks = verdict_checks(1800, 1402, 476.8, 0.21, "importance")
    assert [c.text() for c in checks] == [
        "1,402 failures: at least 10, passed",
        "ESS 476.8: at least 20 under importance sampling, passed",
        "k-hat 0.21: at most 0.69 (min(1 - 1 / log10 N, 0.7) at N = 1,800 rollouts), passed",
    ]
    assert worst_of(checks) == "reliable" and all(c.passed for c in checks)


def test_failed_checks_say_failed_with_their_rule():
    checks = verdict_checks(1000, 9, 1.8, None, "importance")
    assert [c.text() for c in checks] == [
        "9 failures: at least 10, failed (doubtful)",
        "ESS 1.8: at least 20 under importance sampling, failed (doubtful)",
        "k-hat not fitted (9 failures; the fit needs 25): a fitted k-hat at most 0.67 (min(1 - 1 / log10 N, 0.7) "
        "at N = 1,000 rollouts), failed (doubtful)",
    ]
    heavy = verdict_checks(1000, 300, 12.0, 0.9, "importance")[2]
    assert heavy.text().endswith("failed (unreliable: a few weights dominate)")
    assert verdict_checks(1000, 0, 0.0, None, "importance")[0].text() == (
        "0 failures: at least 10, failed (unreliable: no failure)"
    )


def test_plain_monte_carlo_and_splitting_say_which_checks_do_not_apply():
    plain = verdict_checks(20_000, 12, 12.0, None, "plain")
    assert plain[1].text() == "ESS 12.0: at least 10 (plain Monte Carlo: the failure count), passed"
    assert plain[2].text() == "k-hat -: not used (plain Monte Carlo: every weight is 1)" and plain[2].passed is None
    ams = verdict_checks(1000, 40, 3.2, None, "splitting")
    assert [c.passed for c in ams] == [True, None, None] and "failed" not in " ".join(c.text() for c in ams)


@settings(max_examples=400, deadline=None)
@given(
    n=st.integers(11, 10**7),
    frac=st.floats(0.0, 1.0),
    ess_frac=st.floats(0.0, 1.0),
    khat=st.one_of(st.none(), st.floats(-0.5, 2.0)),
    plain=st.booleans(),
)
def test_the_checks_decide_the_verdict(n, frac, ess_frac, khat, plain):
    """Over random figures (distinct failures and mean weight not at issue): the worst failed check is the verdict
    that the estimator gives, so "reliable" exactly when no check failed."""
    nf = max(1, int(frac * n))
    ess = float(nf) if plain else ess_frac * nf
    k = math.nan if plain or khat is None else khat
    verdict, reason = _verdict(n, nf, ess, k, np.zeros(4), plain, nf)
    checks = verdict_checks(n, nf, ess, None if math.isnan(k) else k, "plain" if plain else "importance")
    assert worst_of(checks) == verdict, (reason, [c.text() for c in checks])
    for c in checks:
        assert ("failed" in c.text()) == (c.passed is False), c.text()
