"""The importance-sampling estimate of a failure probability: mu_hat, its interval and a verdict (Innes &
Ramamoorthy 2022, eq. 6, in float64 log space). :func:`estimate` gives an :class:`Estimate` with diagnostics from
:mod:`pemviz.core.diagnostics` and interval and lower bound from :mod:`pemviz.core.confidence`;
:func:`format_probability` and :func:`relative_error` work on natural logs, exact far below float64's range."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from pemviz.core.confidence import CI_LEVEL, BettingEvidence, clopper_pearson, log_mean_interval, markov_lower_bound
from pemviz.core.diagnostics import effective_sample_size, pareto_khat

VERDICTS = ("reliable", "doubtful", "unreliable")
"""How far an estimate can be trusted; :attr:`Estimate.reason` says why in one line."""

MIN_FAILURES = 10
"""Fewer failing rollouts than this: the estimate rests on too few weights (verdict ``doubtful``)."""

MIN_ESS_RELIABLE = 2 * MIN_FAILURES
"""Under importance sampling, an ESS of the failure weights below this is never ``reliable`` (``doubtful``): with
fewer effective failures k-hat reads the tail of a handful of weights and can pass a proposal that misses part of
the failure mass (docs/validation.md)."""


def distinct_failures(log_weight: np.ndarray, log_p_total: np.ndarray) -> int:
    """The distinct failing rollouts among ``log_weight`` [F] and ``log_p_total`` [F] (nats): the distinct (log w,
    log p) pairs; a proposal collapsed onto a few paths repeats them (Rubinstein & Kroese, "The Cross-Entropy
    Method", 2004, Sec. 3.5)."""
    if log_weight.size == 0:
        return 0
    if np.isnan(log_weight).any() or np.isnan(log_p_total).any():  # NaN pairs: as numpy's unique of the pairs counts
        return int(np.unique(np.stack([log_weight, log_p_total]), axis=1).shape[1])
    order = np.lexsort((log_p_total, log_weight))  # equal pairs side by side (3 times as fast as unique of pairs)
    w, p = log_weight[order], log_p_total[order]
    return 1 + int(np.count_nonzero((w[1:] != w[:-1]) | (p[1:] != p[:-1])))


SEEN_TOLERANCE = 1e-9
"""nats: how far below the probability of the failures seen mu_hat must be to be called too low
(:meth:`Estimate.below_seen`): the two are sums of the same logs in another order."""

MAX_MEAN_WEIGHT = 20.0
"""The mean of N importance weights has expectation 1 when the weights belong to the proposal that drew the
rollouts, so by Markov's inequality it exceeds 20 with probability <= 0.05: a larger mean says the weights (the
log q of a logged file, say) do not match the sampler. (A mean far below 1 is normal for a proposal aimed at
the failures: it rarely draws the PEM's typical rollouts, whose weights carry the rest of the mass.)"""

KHAT_UNRELIABLE = 0.7
"""Pareto k-hat above which an importance-sampling estimate is unreliable (Vehtari, Simpson, Gelman, Yao, Gabry,
"Pareto Smoothed Importance Sampling", JMLR 25(72), 2024, Sec. 3.2): the weights' variance is so large that a
few weights decide the estimate, and no number of further rollouts of this size fixes it quickly."""


@dataclass(frozen=True)
class Estimate:
    """Importance-sampling estimate of the failure probability, its uncertainty and a verdict.

    Attributes:
        n: rollouts used.
        n_failures: rollouts that failed (crash: classic robustness < 0).
        log_mu_hat: log of mu_hat = min(1, (1/N) sum_i 1[fail_i] w_i) (nats, <= 0; -inf with no failure): a mean of
            weights above 1 is a probability of 1, cut as its interval is.
        nll_mean: mean over failures of -sum_{t < t_fail} log p_PEM(a_t | s_t) (nats; nan with no failure).
        nll_lme: -log-mean-exp over failures of the same sums (nats; nan with no failure).
        ess: effective sample size of the failure weights, (sum w)^2 / sum w^2 (0 with no failure).
        log_ci: the :data:`~pemviz.core.confidence.CI_LEVEL` confidence interval of mu_hat as natural logs (lo, hi)
            (:func:`estimate`).
        khat: Pareto k-hat of the tail of the importance-weighted failure indicator (nan with too few failures).
        log_mean_weight: log of the mean importance weight over all N rollouts (nats): about 0 when the weights
            belong to the proposal that drew the rollouts.
        verdict: one of :data:`VERDICTS`.
        reason: one line saying why."""

    n: int
    n_failures: int
    log_mu_hat: float
    nll_mean: float
    nll_lme: float
    ess: float
    log_ci: tuple[float, float] = (-math.inf, 0.0)
    khat: float = math.nan
    log_mean_weight: float = math.nan
    verdict: str = "unreliable"
    reason: str = ""
    plain_mc: bool = False
    evidence: BettingEvidence | None = field(default=None, compare=False, repr=False)
    markov_logs: tuple[float, ...] = ()

    @property
    def interval_backed(self) -> bool:
        """Whether the run backs its :data:`~pemviz.core.confidence.CI_LEVEL` interval ``log_ci``: plain Monte Carlo
        (its Clopper-Pearson interval is exact), or a ``reliable`` verdict. Otherwise the interval's coverage rests on
        a central limit the weights' tail may not obey (k-hat, ESS, a collapsed proposal), and what is shown is
        :attr:`log_lower_bound` with no upper bound."""
        return self.plain_mc or self.verdict == "reliable"

    def lower_bound(self, alpha: float = 1.0 - CI_LEVEL) -> float:
        """A lower confidence bound of p at level 1 - ``alpha`` that holds whatever the weights' tail, as a natural
        log (-inf: none): the one-sided Clopper-Pearson bound for plain Monte Carlo,
        :func:`pemviz.core.confidence.betting_lower_bound` of the run's terms under importance sampling,
        :func:`pemviz.core.confidence.markov_lower_bound` of run-level estimates (splitting).

        Raises:
            ValueError: ``alpha`` outside (0, 1)."""
        if not 0.0 < alpha < 1.0:
            raise ValueError(f"lower_bound: alpha must be in (0, 1), got {alpha}")
        if self.n_failures == 0:
            return -math.inf
        if self.plain_mc:
            from scipy.special import betaincinv

            return math.log(float(betaincinv(self.n_failures, self.n - self.n_failures + 1, alpha)))
        if self.evidence is not None:
            return self.evidence.lower_bound(alpha)
        if self.markov_logs:
            return markov_lower_bound(np.asarray(self.markov_logs, dtype=np.float64), alpha)
        return -math.inf

    @cached_property
    def log_lower_bound(self) -> float:
        """:meth:`lower_bound` at :data:`~pemviz.core.confidence.CI_LEVEL` (natural log; -inf: none)."""
        return self.lower_bound()

    @property
    def shown_log_ci(self) -> tuple[float, float]:
        """What the run stands behind, as natural logs (lo, hi): ``log_ci`` where :attr:`interval_backed`, else
        (:attr:`log_lower_bound`, +inf): a lower bound and no upper bound."""
        return self.log_ci if self.interval_backed else (self.log_lower_bound, math.inf)

    @property
    def mu_hat(self) -> float:
        """mu_hat as a float64 (underflows to 0.0 below ~1e-308; use ``log_mu_hat`` then)."""
        return math.exp(self.log_mu_hat) if self.log_mu_hat > -math.inf else 0.0

    @property
    def log10_mu_hat(self) -> float:
        return self.log_mu_hat / math.log(10.0)

    @property
    def rel_half_width(self) -> float:
        """The interval's half-width relative to mu_hat, (hi - lo) / (2 mu_hat), computed in log space: what a
        precision target (``--rel-error``) bounds; inf with no failure."""
        lo, hi = self.log_ci
        if not (self.log_mu_hat > -math.inf and math.isfinite(hi)):
            return math.inf
        low = math.exp(lo - self.log_mu_hat) if lo > -math.inf else 0.0
        return 0.5 * (math.exp(hi - self.log_mu_hat) - low)

    def covers(self, log_p: float) -> bool:
        """Whether what the run shows holds the probability whose natural log is ``log_p``: its interval where
        :attr:`interval_backed`, else its lower bound (:attr:`shown_log_ci`)."""
        lo, hi = self.shown_log_ci
        return lo <= log_p <= hi

    def holds_word(self, log_p: float, outside: str = "OUTSIDE") -> str:
        """``inside`` / ``OUTSIDE`` (the interval), or for a bound ``above`` / ``BELOW`` (``outside`` is the emphasised
        word for a miss; "below" in its case for a bound)."""
        if self.interval_backed:
            return "inside" if self.covers(log_p) else outside
        return "above" if self.covers(log_p) else outside.replace("OUTSIDE", "BELOW").replace("outside", "below")

    def holds_text(self, log_p: float, outside: str = "OUTSIDE") -> str:
        """``inside the interval`` / ``OUTSIDE the interval``, or for a bound ``above the lower bound`` / ``BELOW the
        lower bound`` (:meth:`holds_word`)."""
        what = "the interval" if self.interval_backed else "the lower bound"
        return f"{self.holds_word(log_p, outside)} {what}"

    def interval_text(self) -> str:
        """``[1.2e-15, 2.6e-15]``: the interval as probabilities; where the run does not back one
        (:attr:`interval_backed`), its lower bound: ``>= 3.1e-16, no upper``."""
        lo, hi = self.log_ci
        if self.interval_backed or self.n_failures == 0:
            return f"[{format_probability(lo, 2)}, {format_probability(hi, 2)}]"
        return f">= {format_probability(self.log_lower_bound, 2)}, no upper"

    def bound_text(self) -> str:
        """``p >= 3.1e-16 (95 % lower bound, whatever the weights' tail), no upper bound from this run``; ``no bound
        either way from this run`` where there is no lower bound either (an estimate that keeps no terms)."""
        if self.log_lower_bound == -math.inf:
            return "no bound either way from this run"
        return (
            f"p >= {format_probability(self.log_lower_bound, 2)} ({CI_LEVEL:.0%} lower bound, whatever the "
            "weights' tail), no upper bound from this run"
        )

    def below_seen(self, log_p_seen: float | None) -> Estimate:
        """This estimate, or, when mu_hat is below ``log_p_seen`` (nats: the probability of the distinct failures the
        run has drawn, a lower bound of p: :class:`pemviz.estimators.base.SeenFailures`), the same numbers with the
        verdict ``unreliable``: mu_hat is then certainly too low, whatever its weights look like (a proposal collapsed
        onto a few unlikely paths draws weights that pass every other check)."""
        if log_p_seen is None or not self.log_mu_hat < log_p_seen - SEEN_TOLERANCE:
            return self
        reason = (
            f"mu_hat is below {format_probability(log_p_seen)}, the probability of the failures this run drew: "
            "it misses most of them"
        )
        return dataclasses.replace(self, verdict="unreliable", reason=reason)

    def at_most(self, cap: tuple[str, str] | None) -> Estimate:
        """This estimate with its verdict no better than ``cap`` = (verdict, reason): what the sampler knows and the
        weights cannot show (e.g. a proposal never fitted to a failure). None, or a verdict already as bad: unchanged.
        """
        if cap is None or VERDICTS.index(self.verdict) >= VERDICTS.index(cap[0]):
            return self
        return dataclasses.replace(self, verdict=cap[0], reason=cap[1])

    def summary(self, exact_log_p: float | None = None, reference: Reference | None = None) -> str:
        """One line: mu_hat, its interval, ESS, k-hat, the verdict and its reason, and the exact answer or reference
        (:meth:`Reference.comparison`), e.g. ``mu_hat = 1.795e-15, 95 % CI [1.3e-15, 2.5e-15], ESS 10.2, k-hat 0.41:
        reliable (96 failures); exact 1.984e-15 (relative error 0.095, inside the interval)``."""
        khat = "-" if math.isnan(self.khat) else f"{self.khat:.2f}"
        if self.n_failures == 0:  # no point estimate: the bound, if the rollouts give one
            hi = self.log_ci[1]
            bound = (
                f"p < {format_probability(hi, 2)} ({CI_LEVEL:.0%}, rule of three: 3 / {self.n} rollouts of the "
                "PEM itself)"
                if hi < 0.0
                else self.reason or "this bounds nothing"
            )
            line = f"no failure seen in {self.n} rollouts: {bound}: {self.verdict} as an estimate"
        elif self.interval_backed:
            line = (
                f"mu_hat = {format_probability(self.log_mu_hat)}, {CI_LEVEL:.0%} CI {self.interval_text()}, "
                f"ESS {self.ess:.1f}, k-hat {khat}: {self.verdict} ({self.reason})"
            )
        else:
            line = (
                f"mu_hat = {format_probability(self.log_mu_hat)}, no {CI_LEVEL:.0%} CI from these weights: "
                f"{self.bound_text()}; ESS {self.ess:.1f}, k-hat {khat}: {self.verdict} ({self.reason})"
            )
        if exact_log_p is not None:
            error = error_text(self.log_mu_hat, exact_log_p)
            line += f"; exact {format_probability(exact_log_p)} ({error}, {self.holds_text(exact_log_p)})"
        elif reference is not None:
            line += f"; {reference.comparison(self)}"
        return line


@dataclass(frozen=True)
class Reference:
    """A failure probability known from a separate, much larger plain Monte Carlo run under the same PEMs, with its
    own Clopper-Pearson :data:`~pemviz.core.confidence.CI_LEVEL` interval: the answer an estimate is shown beside
    where no exact one is known (e.g. :data:`pemviz.scenarios.cut_in.scenario.MONTE_CARLO_REFERENCE`).

    Attributes:
        n_failures, n: failures among ``n`` rollouts drawn from the PEMs.
        source: a few words saying where they come from (e.g. ``plain Monte Carlo, benchmarks/cut_in_mc.py``).
    Raises:
        ValueError: ``n`` < 1 or ``n_failures`` outside 1..n (a reference without a failure bounds, it does not say)."""

    n_failures: int
    n: int
    source: str = "plain Monte Carlo"

    def __post_init__(self) -> None:
        if self.n < 1 or not 1 <= self.n_failures <= self.n:
            raise ValueError(f"Reference: need 1 <= n_failures <= n, got {self.n_failures} of {self.n}")

    @property
    def log_p(self) -> float:
        """Natural log of the reference failure probability, n_failures / n."""
        return math.log(self.n_failures) - math.log(self.n)

    @property
    def log_ci(self) -> tuple[float, float]:
        """The reference's own :data:`~pemviz.core.confidence.CI_LEVEL` interval
        (:func:`pemviz.core.confidence.clopper_pearson`) as natural logs."""
        lo, hi = clopper_pearson(self.n_failures, self.n)
        return math.log(lo), math.log(hi)

    def text(self) -> str:
        """e.g. ``8.66e-05 [8.09e-05, 9.26e-05] (866 failures in 10,000,000 rollouts, plain Monte Carlo)``."""
        lo, hi = self.log_ci
        return (
            f"{format_probability(self.log_p, 2)} [{format_probability(lo, 2)}, {format_probability(hi, 2)}] "
            f"({self.n_failures:,} failures in {self.n:,} rollouts, {self.source})"
        )

    def comparison(self, e: Estimate, outside: str = "OUTSIDE") -> str:
        """How ``e`` stands against this reference: its relative error and whether its interval holds the
        reference, e.g. ``reference 8.66e-05 [...] (...): 11.8 orders of magnitude too low, OUTSIDE the interval``
        (:func:`error_text`); ``outside`` is
        the word used when it does not (the panel and the recording emphasise it their way)."""
        return f"reference {self.text()}: {error_text(e.log_mu_hat, self.log_p)}, {e.holds_text(self.log_p, outside)}"


def error_text(log_mu_hat: float, log_truth: float) -> str:
    """How far mu_hat is from the truth, in words: ``relative error 0.0242`` within a factor of 2, else the factor
    (``3.4 times too high``) or, from 10 on, the orders of magnitude (``9.2 orders of magnitude too low``); ``no
    failure seen`` for mu_hat = 0 (natural logs in, exact far below float64's range)."""
    if log_mu_hat == -math.inf:
        return "no failure seen"
    ratio = log_mu_hat - log_truth
    if abs(ratio) <= math.log(2.0):
        return f"relative error {relative_error(log_mu_hat, log_truth):.3g}"
    way = "high" if ratio > 0 else "low"
    if abs(ratio) < math.log(10.0):
        return f"{math.exp(abs(ratio)):.2g} times too {way}"
    return f"{abs(ratio) / math.log(10.0):.1f} orders of magnitude too {way}"


def relative_error(log_mu_hat: float, log_truth: float) -> float:
    """|mu_hat - p| / p from natural logs, exact also far below float64's range (1.0 when mu_hat = 0)."""
    if log_mu_hat == -math.inf:
        return 1.0
    return abs(math.expm1(log_mu_hat - log_truth))


def estimate(
    log_weight: np.ndarray, failed: np.ndarray, log_p_total: np.ndarray, own_log_weight: np.ndarray | None = None
) -> Estimate:
    """mu_hat = logsumexp(log w over failures) - log N, at most 1, with its interval, diagnostics and verdict.

    Innes & Ramamoorthy (2022), eq. 6: mu_hat = (1/N) sum_i 1[fail_i] prod_t p(a_t | s_t) / q(a_t | s_t).

    The interval: with all weights 1 (plain Monte Carlo) the Clopper-Pearson interval of the failure count
    (:func:`pemviz.core.confidence.clopper_pearson`; 0 failures: p < 3 / N); under importance sampling the log-scale
    interval of the mean of 1[fail_i] w_i, its upper end widened by the weights' k-hat
    (:func:`pemviz.core.confidence.log_mean_interval`), cut at 1, and [0, 1]
    with 0 failures. The verdict (:data:`VERDICTS`) is ``unreliable`` with no failure, a nan weight, k-hat above
    :data:`KHAT_UNRELIABLE` with an ESS below :data:`MIN_ESS_RELIABLE`, or a mean importance weight above
    :data:`MAX_MEAN_WEIGHT`; ``doubtful`` with fewer than :data:`MIN_FAILURES` failures or distinct failing rollouts
    (:func:`distinct_failures`), a low ESS, or k-hat above min(1 - 1 / log10 S, 0.7) (Vehtari et al. 2024); else
    ``reliable``.

    Args:
        log_weight: float64 [N] importance log-weights sum_t (log p - log q) (nats).
        failed: bool [N] failure indicator.
        log_p_total: float64 [N] sum_t log p_PEM(a_t | s_t) over the steps before the failure (nats), for the NLL.
        own_log_weight: float64 [N] each rollout's own log p/q (nats) where ``log_weight`` carries pooling shifts,
            for the lower bound (:func:`pemviz.core.confidence.betting_lower_bound`); None: ``log_weight`` itself.
    Raises:
        ValueError: if the arrays do not have one entry per rollout, or N = 0."""
    from scipy.special import logsumexp

    log_weight = np.asarray(log_weight, dtype=np.float64)
    failed = np.asarray(failed, dtype=bool)
    log_p_total = np.asarray(log_p_total, dtype=np.float64)
    n = int(log_weight.size)
    if n == 0 or failed.shape != log_weight.shape or log_p_total.shape != log_weight.shape:
        raise ValueError(
            f"estimate: log_weight, failed and log_p_total need one entry per rollout (N >= 1), got shapes "
            f"{log_weight.shape}, {failed.shape}, {log_p_total.shape}"
        )
    lw = log_weight[failed]
    nf = int(lw.size)
    log_mean_w = float(logsumexp(log_weight)) - math.log(n)
    plain_mc = bool(np.all(log_weight == 0.0))
    if nf == 0:
        if plain_mc:
            bound = math.log(min(1.0, 3.0 / n))
            reason = f"0 failures in {n} rollouts of the PEM itself: only a bound, p < {3.0 / n:.2g} (rule of three)"
        else:
            bound = 0.0
            reason = "0 failures under importance sampling: this bounds nothing"
        return Estimate(
            n,
            0,
            -math.inf,
            math.nan,
            math.nan,
            0.0,
            (-math.inf, bound),
            math.nan,
            log_mean_w,
            "unreliable",
            reason,
            plain_mc,
        )
    with np.errstate(invalid="ignore", over="ignore"):  # an inf or nan weight gives nan numbers: unreliable below
        own = log_weight if own_log_weight is None else np.asarray(own_log_weight, dtype=np.float64)
        return _estimate(n, lw, nf, log_weight, failed, log_p_total, log_mean_w, plain_mc, own)


def _estimate(
    n: int,
    lw: np.ndarray,
    nf: int,
    log_weight: np.ndarray,
    failed: np.ndarray,
    log_p_total: np.ndarray,
    log_mean_w: float,
    plain_mc: bool,
    own_log_weight: np.ndarray,
) -> Estimate:
    """The rest of :func:`estimate`, with at least one failure."""
    from scipy.special import logsumexp

    lp = log_p_total[failed]
    log_sum = float(logsumexp(lw))
    ess = effective_sample_size(lw)
    nll_lme = -(float(logsumexp(lp)) - math.log(nf))
    log_y = np.where(failed, log_weight, -math.inf)
    if plain_mc:
        lo, hi = clopper_pearson(nf, n)
        log_ci = (math.log(lo) if lo > 0 else -math.inf, math.log(hi))
        khat = math.nan
    else:
        khat = pareto_khat(log_y)
        _, lo, hi = log_mean_interval(log_y, khat)
        log_ci = (min(lo, 0.0), min(hi, 0.0))  # p <= 1: the interval intersected with [0, 1] covers as often
    distinct = nf if plain_mc else distinct_failures(lw, lp)
    verdict, reason = _verdict(n, nf, ess, khat, log_weight, plain_mc, distinct)
    numbers = (log_sum, ess, log_ci[1], log_mean_w)
    if verdict == "reliable" and not all(math.isfinite(x) for x in numbers):  # a claim each number must back
        verdict, reason = "unreliable", "an estimate, interval bound, ESS or mean weight is not a finite number"
    evidence = None if plain_mc else BettingEvidence.of(np.where(failed, own_log_weight, -math.inf))
    return Estimate(
        n,
        nf,
        min(log_sum - math.log(n), 0.0),  # p <= 1: a mean of weights above 1 is cut there, as its interval
        float(-lp.mean()),
        nll_lme,
        ess,
        log_ci,
        khat,
        log_mean_w,
        verdict,
        reason,
        plain_mc,
        evidence,
    )


def khat_threshold(n: int) -> float:
    """The k-hat above which an importance-sampling estimate of ``n`` rollouts is at best ``doubtful``: the
    sample-size threshold min(1 - 1 / log10 n, :data:`KHAT_UNRELIABLE`) of Vehtari et al. (2024), Sec. 3.2 (0 for
    n <= 10)."""
    return min(1.0 - 1.0 / math.log10(n), KHAT_UNRELIABLE) if n > 10 else 0.0


def _verdict(
    n: int, nf: int, ess: float, khat: float, log_weight: np.ndarray, plain_mc: bool, distinct: int
) -> tuple[str, str]:
    """The verdict and its one-line reason (see :func:`estimate`)."""
    from scipy.special import logsumexp

    if not plain_mc and np.any(np.isnan(log_weight)):  # nan compares False: every check below would pass it
        return "unreliable", "the weights hold nan: a proposal drew what the PEM cannot"
    if not plain_mc and not math.isfinite(ess):
        return "unreliable", "the ESS is not a finite number"
    if not plain_mc and ess == 0.0:
        return "unreliable", (
            f"every one of the {nf} failures weighs 0: the proposal drew only failures the PEM "
            "cannot produce (p = 0)"
        )
    if not plain_mc:
        if khat > KHAT_UNRELIABLE and ess < MIN_ESS_RELIABLE:
            return "unreliable", f"k-hat {khat:.2f} > {KHAT_UNRELIABLE}: a few weights dominate"
        log_mean = float(logsumexp(log_weight)) - math.log(log_weight.size)
        if log_mean > math.log(MAX_MEAN_WEIGHT):
            return "unreliable", (
                f"mean importance weight {format_probability(log_mean, 2)} > {MAX_MEAN_WEIGHT:g}: the weights do not "
                "belong to the proposal that drew the rollouts"
            )
    if nf < MIN_FAILURES:
        return "doubtful", f"only {nf} failure{'s' if nf != 1 else ''}"
    if distinct < MIN_FAILURES:
        return "doubtful", (
            f"the {nf} failures are {distinct} distinct rollout{'s' if distinct != 1 else ''} "
            "drawn again and again: the proposal has collapsed onto them"
        )
    if not plain_mc:
        if ess < MIN_FAILURES:
            return "doubtful", f"ESS {ess:.1f} < {MIN_FAILURES}: a few weights carry the estimate"
        if khat > KHAT_UNRELIABLE:  # with a large ESS: clustered weights, or a tail the ESS does not see yet
            return "doubtful", f"k-hat {khat:.2f} > {KHAT_UNRELIABLE}: the weights' tail is heavy or clustered"
        if math.isnan(khat):  # fewer than 25 failures: no tail to fit, and "reliable" needs one (nan compares False)
            return "doubtful", f"k-hat needs 25 failures to fit the weights' tail ({nf} here): more rollouts needed"
        threshold = khat_threshold(n)
        if khat > threshold:
            return "doubtful", f"k-hat {khat:.2f} > {threshold:.2f}: more rollouts needed"
        if ess < MIN_ESS_RELIABLE:
            return "doubtful", (
                f"ESS {ess:.1f} < {MIN_ESS_RELIABLE}: too few effective failures to judge the " "weights' tail"
            )
    return "reliable", f"{nf} failures, ESS {ess:.1f}"


def format_probability(log_p: float, digits: int = 3) -> str:
    """``1.234e-15`` from a natural log, exact also far below float64's range (``0`` for -inf)."""
    if log_p == -math.inf:
        return "0"
    if math.isnan(log_p):
        return "nan"
    l10 = log_p / math.log(10.0)
    if abs(l10) > 1e9:  # the exponent itself would need more digits than fit on a line
        return f"10^({l10:.{digits}e})"
    exponent = math.floor(l10)
    mantissa = 10 ** (l10 - exponent)
    if round(mantissa, digits) >= 10:
        mantissa, exponent = mantissa / 10, exponent + 1
    return f"{mantissa:.{digits}f}e{exponent:+03d}"
