"""The verdict's checks one by one, each with what it found, its rule and whether it passed, as a report prints them
beside the verdict (:func:`pemviz.core.estimate.estimate` decides from the same thresholds): at least
:data:`~pemviz.core.estimate.MIN_FAILURES` failures, an ESS of at least
:data:`~pemviz.core.estimate.MIN_ESS_RELIABLE` and a Pareto k-hat at most the sample-size threshold of Vehtari,
Simpson, Gelman, Yao & Gabry ("Pareto Smoothed Importance Sampling", JMLR 25(72), 2024, Sec. 3.2); plain Monte Carlo
needs the failures alone; splitting keeps no weights."""

from __future__ import annotations

import math
from dataclasses import dataclass

from pemviz.core.estimate import KHAT_UNRELIABLE, MIN_ESS_RELIABLE, MIN_FAILURES, khat_threshold

SAMPLINGS = ("importance", "plain", "splitting")
"""How an estimate's rollouts were drawn: importance sampling (weights p / q), plain Monte Carlo (the PEM itself,
every weight 1) or splitting (AMS: no weights)."""

KHAT_MIN_FAILURES = 25
"""Failures below which no k-hat is fitted (:func:`pemviz.core.diagnostics.pareto_khat`)."""


@dataclass(frozen=True)
class Check:
    """One check of the verdict.

    Attributes:
        name: what is checked (``failures``, ``effective sample size``, ``Pareto k-hat``).
        found: what the run has, in words (``1,402 failures``).
        rule: what the check asks (``at least 10``).
        passed: True or False; None where the check does not apply to the sampling (``not used``).
        fails_to: the verdict at best when it fails (one of :data:`pemviz.core.estimate.VERDICTS`), ``""`` where it
            cannot fail."""

    name: str
    found: str
    rule: str
    passed: bool | None
    fails_to: str = ""

    def text(self) -> str:
        """``1,402 failures: at least 10, passed``; ``9 failures: at least 10, failed (doubtful)``; a check that does
        not apply: ``-: not used (plain Monte Carlo: every weight is 1)``."""
        if self.passed is None:
            return f"{self.found}: {self.rule}"
        return f"{self.found}: {self.rule}, " + ("passed" if self.passed else f"failed ({self.fails_to})")


def verdict_checks(n: int, n_failures: int, ess: float | None, khat: float | None, sampling: str) -> list[Check]:
    """The failures, ESS and k-hat checks of an estimate (module docstring), from its figures alone.

    Args:
        n: rollouts used (>= 1).
        n_failures: the failing ones.
        ess: effective sample size of the failure weights (None or nan: not a finite number).
        khat: Pareto k-hat of the weights' tail (None or nan: not fitted).
        sampling: one of :data:`SAMPLINGS`.
    Returns:
        Three checks: failures, effective sample size, Pareto k-hat.
    Raises:
        ValueError: an unknown ``sampling``."""
    if sampling not in SAMPLINGS:
        raise ValueError(f"verdict_checks: sampling must be one of {', '.join(SAMPLINGS)}, got {sampling!r}")
    ess_f = math.nan if ess is None else float(ess)
    khat_f = math.nan if khat is None else float(khat)
    failures = Check(
        "failures",
        f"{n_failures:,} failure{'s' if n_failures != 1 else ''}",
        f"at least {MIN_FAILURES}",
        n_failures >= MIN_FAILURES,
        "doubtful" if n_failures else "unreliable: no failure",
    )
    return [failures, _ess_check(n_failures, ess_f, sampling), _khat_check(n, n_failures, ess_f, khat_f, sampling)]


def _ess_check(n_failures: int, ess: float, sampling: str) -> Check:
    name = "effective sample size"
    if sampling == "splitting":
        return Check(name, f"ESS {ess:.1f}", "not a check of splitting (1 / the estimate's relative variance)", None)
    found = "ESS not a finite number" if not math.isfinite(ess) else f"ESS {ess:.1f}"
    if sampling == "plain":  # every weight 1: the ESS is the failure count
        rule = f"at least {MIN_FAILURES} (plain Monte Carlo: the failure count)"
        return Check(name, found, rule, ess >= MIN_FAILURES, "doubtful")
    worst = "unreliable" if not math.isfinite(ess) or (n_failures and ess == 0.0) else "doubtful"
    return Check(name, found, f"at least {MIN_ESS_RELIABLE} under importance sampling", ess >= MIN_ESS_RELIABLE, worst)


def _khat_check(n: int, n_failures: int, ess: float, khat: float, sampling: str) -> Check:
    name = "Pareto k-hat"
    if sampling == "plain":
        return Check(name, "k-hat -", "not used (plain Monte Carlo: every weight is 1)", None)
    if sampling == "splitting":
        return Check(name, "k-hat -", "not used (splitting keeps no importance weights)", None)
    threshold = khat_threshold(n)
    rule = f"at most {threshold:.2f} (min(1 - 1 / log10 N, {KHAT_UNRELIABLE}) at N = {n:,} rollouts)"
    if math.isnan(khat):
        found = f"k-hat not fitted ({n_failures:,} failures; the fit needs {KHAT_MIN_FAILURES})"
        return Check(name, found, "a fitted k-hat " + rule, False, "doubtful")
    worst = "unreliable: a few weights dominate" if khat > KHAT_UNRELIABLE and ess < MIN_ESS_RELIABLE else "doubtful"
    return Check(name, f"k-hat {khat:.2f}", rule, khat <= threshold, worst)
