"""A requirement on a failure probability, ``p < 1e-9``, decided by a sequential test that keeps its error rate.

The run looks at its estimate after each batch; look j uses the interval at level ``1 - alpha_j`` with ``alpha_j =
alpha * 6 / (pi^2 j^2)``, whose sum over every look is ``alpha`` (a union bound; an alpha-spending rule in the sense
of Lan & DeMets, "Discrete sequential boundaries for clinical trials", Biometrika 70(3), 1983), so the chance of a
wrong "met" or "violated" over any number of looks is at most ``alpha`` (given each interval's coverage). An
estimate whose verdict is not ``reliable`` decides only by its lower bound
(:meth:`pemviz.core.estimate.Estimate.lower_bound`). No I/O, no scenario."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pemviz.core.estimate import Estimate

ALPHA = 0.05
"""The error rate of a decision over every look: 1 - :data:`pemviz.core.confidence.CI_LEVEL` (the config imports this
module, which imports no numpy)."""
OUTCOMES = ("met", "violated", "undecided")
"""A requirement's outcome; ``pemviz run --require`` exits 0, 1 and 3 for them."""
EXIT_CODES = {"met": 0, "violated": 1, "undecided": 3}
"""The exit status of ``pemviz run`` for each outcome (2 stays bad input)."""
OPERATORS = ("<", "<=", ">", ">=")
_PATTERN = re.compile(r"^\s*p\s*(<=|>=|<|>)\s*([0-9.eE+-]+)\s*$")


class RequirementError(ValueError):
    """A requirement that is not ``p OP THRESHOLD`` with OP one of :data:`OPERATORS` and 0 < THRESHOLD < 1."""


@dataclass(frozen=True)
class Requirement:
    """``p OP threshold``: the failure probability p compared with ``threshold`` in (0, 1).

    Attributes:
        op: one of :data:`OPERATORS`.
        threshold: a probability in (0, 1)."""

    op: str
    threshold: float

    @property
    def log_threshold(self) -> float:
        """log(threshold), nats."""
        return math.log(self.threshold)

    @property
    def upper(self) -> bool:
        """Whether it bounds p from above (``<``, ``<=``): met when the whole interval lies below the threshold."""
        return self.op in ("<", "<=")

    def __str__(self) -> str:
        return f"p {self.op} {self.threshold:g}"


def parse_requirement(text: str) -> Requirement:
    """``"p < 1e-9"`` -> :class:`Requirement` ("<", 1e-9). Spaces are optional.

    Raises:
        RequirementError: not of the form ``p OP NUMBER``, or the number not in (0, 1)."""
    m = _PATTERN.match(text) if isinstance(text, str) else None
    if m is None:
        raise RequirementError(
            f"{text!r} is not a requirement: write p < T, p <= T, p > T or p >= T with T in (0, 1), " "e.g. 'p < 1e-9'"
        )
    try:
        threshold = float(m.group(2))
    except ValueError:
        raise RequirementError(f"{text!r}: {m.group(2)!r} is not a number") from None
    if not 0.0 < threshold < 1.0:
        raise RequirementError(f"{text!r}: the threshold must be a probability in (0, 1)")
    return Requirement(m.group(1), threshold)


def alpha_at_look(look: int, alpha: float = ALPHA) -> float:
    """``alpha_j = alpha 6 / (pi^2 j^2)`` for look j >= 1: the error spent at look j; the sum over j >= 1 is alpha.

    Raises:
        ValueError: ``look`` < 1."""
    if look < 1:
        raise ValueError(f"look must be >= 1, got {look}")
    return alpha * 6.0 / (math.pi**2 * look * look)


def interval_at_level(est: Estimate, level: float, plain_mc: bool) -> tuple[float, float]:
    """The interval of ``est`` at confidence ``level`` instead of its own :data:`CI_LEVEL`, as natural logs (lo,
    hi): Clopper-Pearson for plain Monte Carlo; under importance sampling the log-scale interval
    (:func:`pemviz.core.confidence.log_mean_interval`, its upper end widened by the weights' k-hat) with each side's
    distance from log mu_hat scaled by ``t_{N-1}((1 + level) / 2) / t_{N-1}((1 + CI_LEVEL) / 2)``; with no failure,
    (-inf, 0).

    Args:
        est: an estimate of :func:`pemviz.core.estimate.estimate`.
        level: in (0, 1).
        plain_mc: whether ``est`` comes from rollouts of the PEM itself (weights all 1)."""
    from scipy.special import stdtrit

    from pemviz.core.confidence import CI_LEVEL, clopper_pearson

    if plain_mc:
        lo, hi = clopper_pearson(int(est.n_failures), int(est.n), level)
        return (math.log(lo) if lo > 0 else -math.inf), math.log(hi) if hi > 0 else -math.inf
    if est.n_failures == 0 or est.n < 2 or not math.isfinite(est.log_mu_hat):
        return -math.inf, 0.0
    lo, hi = est.log_ci
    scale = float(stdtrit(est.n - 1, 0.5 + level / 2.0)) / float(stdtrit(est.n - 1, 0.5 + CI_LEVEL / 2.0))
    return est.log_mu_hat - (est.log_mu_hat - lo) * scale, est.log_mu_hat + (hi - est.log_mu_hat) * scale


@dataclass(frozen=True)
class Decision:
    """One look's decision.

    Attributes:
        outcome: one of :data:`OUTCOMES` (``undecided``: look again, or stop at a cap).
        look: j, 1 for the first look.
        level: the interval's confidence level at this look, ``1 - alpha_j``.
        log_ci: that interval, natural logs (lo, hi).
        why: one line: what decided, or why not."""

    outcome: str
    look: int
    level: float
    log_ci: tuple[float, float]
    why: str


def decide(est: Estimate, req: Requirement, look: int, plain_mc: bool, alpha: float = ALPHA) -> Decision:
    """Look ``look`` at ``est``: ``met`` when the interval at level ``1 - alpha_look`` (:func:`alpha_at_look`,
    :func:`interval_at_level`) lies wholly on the requirement's side of the threshold, ``violated`` when wholly on
    the other, else ``undecided``; an importance-sampling estimate whose verdict is not ``reliable`` decides only by
    its lower bound."""
    level = 1.0 - alpha_at_look(look, alpha)
    t = req.log_threshold
    if not plain_mc and est.verdict != "reliable":
        return _decide_on_bound(est, req, look, level)
    lo, hi = interval_at_level(est, level, plain_mc)
    shown = f"{level:.4g} interval [{math.exp(lo):.3g}, {math.exp(hi):.3g}] at look {look}"
    below = hi < t if req.op in ("<", ">=") else hi <= t  # p < t holds on [lo, hi] / p >= t fails on it
    above = lo >= t if req.op in ("<", ">=") else lo > t
    if req.upper:
        outcome = "met" if below else "violated" if above else "undecided"
    else:
        outcome = "met" if above else "violated" if below else "undecided"
    side = {"met": "holds", "violated": "fails", "undecided": "straddles the threshold"}[outcome]
    return Decision(outcome, look, level, (lo, hi), f"{req} {side} on the {shown}")


def _decide_on_bound(est: Estimate, req: Requirement, look: int, level: float) -> Decision:
    """A look at an importance-sampling estimate whose verdict backs no interval: only its lower bound at ``level``
    (:meth:`pemviz.core.estimate.Estimate.lower_bound`, whatever the weights' tail) may decide, and only one way: a
    bound at or above the threshold violates ``p < t`` (``p <= t``: above it) and meets ``p >= t`` (``p > t``: above
    it); nothing below the bound says p is small."""
    lo = est.lower_bound(1.0 - level)
    t = req.log_threshold
    above = lo >= t if req.op in ("<", ">=") else lo > t
    shown = (
        f"{level:.4g} lower bound p >= {math.exp(lo):.3g} at look {look} (the estimate is {est.verdict}: no "
        "upper bound)"
    )
    if above:
        outcome = "violated" if req.upper else "met"
        side = "fails" if req.upper else "holds"
        return Decision(outcome, look, level, (lo, math.inf), f"{req} {side} on the {shown}")
    why = f"the {shown} is below the threshold: it decides nothing"
    return Decision("undecided", look, level, (lo, math.inf), why)
