"""Console sink: progress per stage and the results table of ``pemviz run``."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, TextIO

from pemviz.core.estimate import KHAT_UNRELIABLE, Estimate, Reference, format_probability, khat_threshold
from pemviz.core.severity import FailureSeverity
from pemviz.engine.cost import (
    LOAD_WORDS,
    MC_REL_ERROR,
    N_STEPS,
    Z_95,
    duration_text,
    mc_rollouts,
    range_text,
    run_cost,
    stage_cost,
)
from pemviz.engine.events import (
    Event,
    FinalEstimate,
    RunCancelled,
    RunStarted,
    StageFinished,
    StageResult,
    StageStarted,
)
from pemviz.methods import PLAIN_METHOD
from pemviz.plugins import resolve
from pemviz.scenarios.parameters import scenario_params_text
from pemviz.scenarios.registry import no_method_answers
from pemviz.sinks import Sink, StageClock

if TYPE_CHECKING:
    from pemviz.config import ExperimentConfig
    from pemviz.core.plan import RunPlan
    from pemviz.sinks.population import SharedGroups

__all__ = [
    "ConsoleSink",
    "HEADER",
    "McRoute",
    "estimate_cells",
    "final_lines",
    "mc_route",
    "next_step",
    "progress_line",
    "stage_row",
]

HEADER = (
    f"{'stage':>7} {'kind':>8} {'gamma':>9} {'failures':>10} {'mu_hat':>11} {'95% CI':>21} {'NLL':>8} {'ESS':>7} "
    f"{'k-hat':>6} {'verdict':>10} {'wall s':>7}"
)


def _num(x: float, fmt: str) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def estimate_cells(e: Estimate) -> str:
    """failures/N, mu_hat, its interval, mean NLL (nats), ESS, k-hat and verdict, aligned with :data:`HEADER`."""
    return (
        f"{f'{e.n_failures}/{e.n}':>10} {format_probability(e.log_mu_hat):>11} {e.interval_text():>21} "
        f"{_num(e.nll_mean, '8.2f'):>8} {_num(e.ess, '7.2f'):>7} {_num(e.khat, '6.2f'):>6} {e.verdict:>10}"
    )


def progress_line(
    label: str,
    n_rollouts: int,
    elapsed_s: float,
    expected_s: float,
    run_left_s: float = math.nan,
    run_most_s: float = math.nan,
    then: str = "",
    why: str = "",
) -> str:
    """``CE stage 3/10: 1000 rollouts ... (elapsed 12.3 s, this stage ~1.2 s, run ~8.4 s left, up to ~6.5 min)``: the
    stage's expected seconds and the whole run's left, as planned and at most (:class:`pemviz.sinks.StageClock`; the
    range in the words of the panel's cost line, :func:`pemviz.engine.cost.range_text`, with ``then`` saying what may
    follow, or ``why`` the upper end where nothing may), each left out where unknown."""
    eta = f", this stage ~{expected_s:.1f} s" if math.isfinite(expected_s) else ""
    left = f", run {range_text(run_left_s, run_most_s, then, ' left', why)}" if math.isfinite(run_left_s) else ""
    return f"{label}: {n_rollouts} rollouts ... (elapsed {elapsed_s:.1f} s{eta}{left})"


def stage_row(res: StageResult) -> str:
    """One table row: stage, kind, gamma_kappa, the estimate's cells (:func:`estimate_cells`), wall time (s)."""
    return (
        f"{res.stage:>7d} {res.kind:>8} {_num(res.gamma, '9.4f'):>9} {estimate_cells(res.estimate)} "
        f"{res.wall_s:>7.2f}"
    )


MC_AFFORDABLE = 10**8
"""The most rollouts :func:`next_step` suggests plain Monte Carlo for (at p ~ 1e-6 and below it needs more)."""

PERCENT = f"{100 * MC_REL_ERROR:.0f} %"
""":data:`MC_REL_ERROR` as the lines print it (``20 %``)."""

IS_MAX_SIMS = 100_000
"""The least ``--max-sims`` :func:`next_step` suggests with a precision target for an importance sampler (four times
the run's simulations, rounded up, where that is more)."""


def count_text(n: float) -> str:
    """``1,108,911`` (below 10^9), ``4.8e+16`` (above), ``more than 1e+300`` (inf): a number of rollouts."""
    if not math.isfinite(n):
        return "more than 1e+300"
    return f"{int(n):,}" if n < 1e9 else f"{n:.1e}"


def _round_up(n: float) -> int:
    """``n`` rounded up to two significant digits (100,400 -> 110,000)."""
    unit = 10 ** max(0, math.floor(math.log10(max(n, 1.0))) - 1)
    return int(math.ceil(n / unit) * unit)


def _rate_text(s_per: float, source: str) -> str:
    """``this run's 0.2 ms a rollout`` (a plain Monte Carlo run's measured seconds a rollout, ``s_per``), after another
    method ``~0.2 ms a plain rollout (measured here after the run)`` (the engine's probe) or ``~0.2 ms a plain rollout
    (this run's speed, by the cost model)``; ``source``: ``plain``, ``probed`` or ``model``."""
    rate = f"{s_per * 1e3:.2g} ms" if s_per < 1.0 else f"{s_per:.2g} s"
    if source == "plain":
        return f"this run's {rate} a rollout"
    if source == "probed":
        return f"~{rate} a plain rollout (measured here after the run)"
    return f"~{rate} a plain rollout (this run's speed, by the cost model)"


MC_CAP_MARGIN = 1.2
"""The ``--max-sims`` named for plain Monte Carlo is this many times the rollouts the normal approximation says a
20 % interval needs: the exact Clopper-Pearson interval the run stops on is a little wider."""


def plain_rollout_seconds(
    config: ExperimentConfig, s_per: float | None, n_simulations: int | None = None, n_steps: int | None = None
) -> float | None:
    """Seconds a plain Monte Carlo rollout takes on this machine, from a run of another method: its measured seconds
    ``s_per`` a simulation (of ``n_simulations``; None: ``config.n_simulations``) times the cost model's ratio of a
    plain rollout to the run's plan (:func:`pemviz.engine.cost.run_cost`); an over-estimate after a cross-entropy run
    (its wall time holds costs the model leaves out). None unmeasured; ``s_per`` itself for a plain Monte Carlo run."""
    if s_per is None or config.method_record.plain:
        return s_per
    from pemviz.estimators import run_plan  # the estimators import torch: only when a run is advised

    steps = n_steps or N_STEPS
    sims = n_simulations if n_simulations else int(config.n_simulations)
    run = run_cost(config, run_plan(config), steps).seconds / max(1, int(sims))
    big = 100_000
    plain = stage_cost(config.replace(method=PLAIN_METHOD), "final", big, steps).seconds / big
    return s_per * plain / run if run > 0 and plain > 0 else s_per


@dataclass(frozen=True)
class McRoute:
    """Plain Monte Carlo with a precision target (``--method mc --rel-error 0.2 --max-sims N``) sized for a scene.

    Attributes:
        log_p: the failure probability it is sized for (nats).
        source: where that comes from (``the exact answer``, ``the reference``, ``this run's mu_hat`` ...).
        upper: p is an importance-sampling run's own estimate, not ``reliable``: usually too low (Vehtari et al.,
            "Pareto Smoothed Importance Sampling", JMLR 25(72), 2024, Sec. 3), so :attr:`n` is an upper estimate.
        n: rollouts for a 20 % interval at ``log_p`` (:func:`mc_rollouts`).
        seconds: their time at the run's measured seconds a simulation (None: not measured).
        log_floor: with ``upper``, the run's 95 % lower bound of p (nats) where it is below ``log_p``; None: none.
        n_floor: rollouts for a 20 % interval at ``log_floor`` (:attr:`n` without one)."""

    log_p: float
    source: str
    upper: bool
    n: float
    seconds: float | None
    log_floor: float | None = None
    n_floor: float = math.nan

    def fits(self, max_time_s: float | None) -> bool:
        """Whether :attr:`n` is at most :data:`MC_AFFORDABLE` rollouts and, with ``max_time_s`` (seconds; None: no
        cap) and a measured time, within it."""
        return self.n <= MC_AFFORDABLE and (max_time_s is None or self.seconds is None or self.seconds <= max_time_s)

    def cap(self, config: ExperimentConfig) -> int:
        """The ``--max-sims`` to give it: :attr:`n_floor` (:attr:`n` without a floor), at most :data:`MC_AFFORDABLE`
        but at least :attr:`n` and the config's ``--n`` (the run's planned rollouts, which ``--max-sims`` may not be
        below)."""
        floor = self.n_floor if self.log_floor is not None else self.n
        return int(math.ceil(MC_CAP_MARGIN * max(self.n, min(floor, MC_AFFORDABLE), config.n_per_stage)))

    def command(self, cap: int) -> str:
        """``--method mc --rel-error 0.2 --max-sims 1108911``."""
        return f"--method mc --rel-error {MC_REL_ERROR:g} --max-sims {cap}"

    def text(self, s_per: float | None, source: str, floor: bool = True) -> str:
        """``p ~ 8.66e-05, the reference: 1,108,911 rollouts for a 20 % interval, ~59 min at this run's ...``; with
        :attr:`log_floor` and ``floor``, the rollouts at it too (``; up to 18,343 at its 95 % lower bound p >=
        5.21e-03, ~34 s``)."""
        time = ""
        if self.seconds is not None and math.isfinite(self.seconds):
            assert s_per is not None  # the seconds were measured at s_per a rollout
            time = f", ~{duration_text(self.seconds)} at {_rate_text(s_per, source)}"
        line = (
            f"p ~ {format_probability(self.log_p, 2)}, {self.source}: {count_text(self.n)} rollouts for a "
            f"{PERCENT} interval{time}"
        )
        if floor and self.log_floor is not None:
            line += (
                f"; up to {count_text(self.n_floor)} at its 95 % lower bound p >= "
                f"{format_probability(self.log_floor, 2)}{_time(self.n_floor, s_per)}"
            )
        return line


def mc_route(
    e: Estimate,
    plain: bool,
    exact_log_p: float | None = None,
    reference: Reference | None = None,
    s_per: float | None = None,
) -> McRoute | None:
    """Plain Monte Carlo sized from the exact answer, else the reference, else the run's own estimate: mu_hat, or
    where the run does not back its interval (``Estimate.interval_backed``) its 95 % lower bound
    (``Estimate.log_lower_bound``) when that is higher, and that lower bound as :attr:`McRoute.log_floor` when it is
    lower; None with no failure and no known p. ``plain``: the run is plain Monte Carlo
    (:attr:`pemviz.methods.Method.plain`); ``s_per``: its measured seconds a simulation
    (None: not measured)."""
    lower, floor = getattr(e, "log_lower_bound", -math.inf), None
    backed = getattr(e, "interval_backed", True)
    if exact_log_p is not None:
        log_p, source = exact_log_p, "the exact answer"
    elif reference is not None:
        log_p, source = reference.log_p, "the reference"
    elif e.n_failures and e.log_mu_hat > -math.inf:
        log_p, source = e.log_mu_hat, "this run's mu_hat"
        if not backed and lower > log_p:
            log_p, source = lower, "this run's 95 % lower bound"
        elif not backed and lower > -math.inf:
            floor = lower
    else:
        return None
    if not log_p > -math.inf:
        return None
    n = mc_rollouts(log_p)
    upper = source.startswith("this run's") and not plain
    n_floor = mc_rollouts(floor) if floor is not None and upper else math.nan
    return McRoute(log_p, source, upper, n, n * s_per if s_per is not None else None, floor if upper else None, n_floor)


def _time(n: float, s_per: float | None) -> str:
    """``, ~26 s``: ``n`` simulations at ``s_per`` seconds each; ``""`` unmeasured."""
    if s_per is None or not math.isfinite(n * s_per):
        return ""
    return f", ~{duration_text(n * s_per)}"


@dataclass(frozen=True)
class AdviceText:
    """What a method's own route (:attr:`pemviz.methods.Method.more_budget`) is given: the run's ``n_simulations``
    and ``wall_s`` (seconds), ``s_per`` (seconds a simulation; None: unmeasured), ``within_s`` (seconds the route
    must fit in; None: any), ``committor`` (whether the scene has a learned committor, ``--ams-score committor``;
    None: not known), and the wording helpers."""

    n_simulations: int | None = None
    s_per: float | None = None
    wall_s: float | None = None
    within_s: float | None = None
    committor: bool | None = None

    time = staticmethod(_time)

    def tail(self) -> str:
        """`` --max-time 60`` for a route that must fit in ``within_s`` seconds, else ``""``."""
        return f" --max-time {self.within_s:g}" if self.within_s is not None else ""

    def cap(self, config: ExperimentConfig) -> int | None:
        """The ``--max-sims`` a precision target is given: four times the run's simulations rounded up, at least
        :data:`IS_MAX_SIMS`; with ``within_s`` what fits in it (None: not half as much again as the run)."""
        m = max(IS_MAX_SIMS, _round_up(4 * (self.n_simulations or 0)))
        if self.within_s is None:
            return m
        if self.s_per is None:
            return None
        m = int(self.within_s / self.s_per)
        if m <= 1.5 * (self.n_simulations or 0) or m < config.n_simulations:
            return None
        return int(float(f"{m:.2g}"))

    def importance_route(self, config: ExperimentConfig, sims: int | None = None) -> str | None:
        """An importance sampler's route: a run at 4 N (``sims`` simulations; None: 4 N) or a precision target, each
        with its time at ``s_per`` seconds a simulation; with ``within_s`` the target alone, if it fits."""
        m = self.cap(config)
        if m is None:
            return None
        target = (
            f"a precision target (--rel-error 0.1 --max-sims {m}{self.tail()}: final batches up to "
            f"{m:,} simulations{_time(m, self.s_per)})"
        )
        if self.within_s is not None:
            return target
        n = config.n_per_stage
        sims = 4 * n if sims is None else sims
        return f"more budget (--n {4 * n}: {sims:,} simulations{_time(sims, self.s_per)}) or {target}"


def _more_budget(
    config: ExperimentConfig,
    n_simulations: int | None,
    s_per: float | None,
    wall_s: float | None,
    within_s: float | None = None,
    committor: bool | None = None,
) -> str | None:
    """The method's own route (:attr:`pemviz.methods.Method.more_budget`; an importance sampler's by
    default: a larger run or a precision target), with simulations and time at ``s_per`` seconds a simulation; with
    ``within_s`` (seconds) only what fits in it (None: nothing more fits)."""
    text = AdviceText(n_simulations, s_per, wall_s, within_s, committor)
    method = config.method_record
    if method.more_budget is not None:
        return resolve(method.more_budget)(config, text)
    return text.importance_route(config)


def next_step(
    e: Estimate,
    config: ExperimentConfig | None,
    exact_log_p: float | None = None,
    reference: Reference | None = None,
    n_simulations: int | None = None,
    wall_s: float | None = None,
    plain_s: float | None = None,
    committor: bool | None = None,
) -> str | None:
    """What to do after a run whose verdict is not ``reliable``, in one line (None for a reliable one): the cheapest
    route that would decide it, with its rollouts and its time on this machine.

    Plain Monte Carlo is always considered: a run sized for a 20 % interval (:func:`mc_rollouts`, about 96 / p
    rollouts; p from :func:`mc_route`) decides it, timed at this run's seconds a simulation. Where it is at most
    :data:`MC_AFFORDABLE` rollouts and fits ``config.stop.max_time_s`` the line names it, then the sampler's own route;
    else it says why not and what is left (more budget, splitting's committor score, or no route within the time).
    Every flag it names is one of ``pemviz run``'s.

    Args:
        e: the run's estimate.
        config: its :class:`~pemviz.config.ExperimentConfig` (None: no advice).
        exact_log_p: the scenario's exact log p (nats), where known.
        reference: its plain Monte Carlo reference, where known.
        n_simulations: the run's simulations (None: the line gives no times).
        wall_s: the run's wall-clock seconds (None: the line gives no times).
        plain_s: a plain rollout's seconds measured here after the run (the engine's probe,
            :attr:`pemviz.engine.events.FinalEstimate.plain_rollout_s`); None: from the run's own speed.
        committor: whether the scene has a learned committor (:class:`AdviceText`), for splitting's route."""
    if e.verdict == "reliable" or config is None:
        return None
    # a scene at whose rarity no method shipped answers: that, and the bound
    beyond = no_method_answers(config.scenario, config.scenario_params, e)
    if beyond is not None:
        return beyond
    method = config.method_record
    s_per = wall_s / n_simulations if n_simulations and wall_s is not None and wall_s > 0 else None
    mc_s = plain_s if plain_s is not None else plain_rollout_seconds(config, s_per, n_simulations)
    rate = "plain" if method.plain else "probed" if plain_s is not None else "model"  # how mc_s was had
    max_time = config.stop.max_time_s
    plain = method.plain or (method.weighted and getattr(e, "plain_mc", False))  # or the plain rollouts after it
    route = mc_route(e, plain, exact_log_p, reference, mc_s)
    # the most rollouts plain Monte Carlo may be given: affordable, and within the time
    budget = min(float(MC_AFFORDABLE), max_time / mc_s) if max_time is not None and mc_s is not None else MC_AFFORDABLE
    if plain:
        return _after_mc(e, config, route, s_per, max_time)
    heavy = f" (k-hat {e.khat:.2f} > {KHAT_UNRELIABLE}: more weights of the same tail may not fix it, and a precision "
    heavy = heavy + "target stops adding them after two such looks)" if e.khat > KHAT_UNRELIABLE else ""  # HEAVY_LOOKS
    low = "heavy-tailed weights make this run's estimate usually too low"
    if e.khat <= khat_threshold(e.n):  # a fitted tail that passed: the run is doubted on other grounds
        low = f"this run's estimate may be too low ({e.verdict}; its weights' tail not heavy, k-hat {e.khat:.2f})"
    low = low if method.weighted else "splitting's estimate is skewed, most runs low"  # splitting: most runs below p
    rest = _more_budget(config, n_simulations, s_per, wall_s, committor=committor)
    if route is None:  # no failure and no known p: nothing to size plain Monte Carlo on
        return f"{rest}; the verdict says whether to trust the result"
    tail = f" --max-time {max_time:g}" if max_time is not None else ""
    if route.fits(max_time):
        cap = route.cap(config)
        upper = f"; an upper estimate: {low}, and the run stops early where p is larger" if route.upper else ""
        return (
            f"plain Monte Carlo decides it: {route.command(cap)}{tail} ({route.text(mc_s, rate)}){upper}; or "
            f"{rest}, with its verdict{heavy}"
        )
    if route.upper and budget > (n_simulations or 0):  # p unknown, sized on an estimate that is usually too low:
        # capped at the budget, plain Monte Carlo stops early where p is larger and decides any p the cap resolves
        cap = max(int(float(f"{budget:.2g}")), config.n_per_stage)
        least = Z_95**2 / (MC_REL_ERROR**2 * cap + Z_95**2)  # the p at which mc_rollouts(p) = cap
        return (
            f"p is not known ({route.text(mc_s, rate, floor=False)}: an upper estimate, as {low}); plain Monte "
            f"Carlo capped ({route.command(cap)}"
            f"{tail}: up to {cap:,} rollouts{_time(cap, mc_s)}) decides it where p >= {least:.2g}, stopping "
            f"early where p is larger; or {rest}, with its verdict{heavy}"
        )
    if route.n > MC_AFFORDABLE and (max_time is None or not route.upper):
        return (
            f"{route.text(mc_s, rate)}: too rare for plain Monte Carlo; what is left is {rest}, with its "
            f"verdict{heavy}"
        )
    within = _more_budget(config, n_simulations, s_per, wall_s, within_s=max_time, committor=committor)
    why = f"plain Monte Carlo does not fit in --max-time {max_time:g} ({route.text(mc_s, rate)})"
    if within is None:
        cap = route.cap(config)
        assert route.seconds is not None  # a route that does not fit in the time has a measured one
        return (
            f"{why}, and this run's sampler has no more time in it: no route within --max-time {max_time:g} s "
            f"would decide it; plain Monte Carlo would, given ~{duration_text(route.seconds)} "
            f"({route.command(cap)} --max-time {math.ceil(route.seconds)})"
        )
    return f"{why}; within it only {within} is left, with its verdict{heavy}"


def _after_mc(
    e: Estimate, config: ExperimentConfig, route: McRoute | None, s_per: float | None, max_time: float | None
) -> str:
    """:func:`next_step` after a plain Monte Carlo run: more rollouts sized for a 20 % interval, or where p is too
    rare for that or its time is past ``max_time`` (seconds), an importance-sampling method; with no failure and no
    known p, ten times the rollouts (and the rollouts a 20 % interval needs at least, from the rule-of-three bound).
    After an importance sampler's stages (the plain rollouts of ``--plain-fallback``) the commands name ``--method
    mc`` and ten times those rollouts."""
    after_stages = not config.method_record.plain
    n = e.n if after_stages else config.n_per_stage
    if route is None:
        hi = e.log_ci[1]
        floor = ""
        if -math.inf < hi < 0.0:
            least = mc_rollouts(hi)
            floor = (
                f"; p < {format_probability(hi, 2)} here, so a {PERCENT} interval needs at least "
                f"{count_text(least)} rollouts{_time(least, s_per)}"
            )
        what, then = (
            "rollouts (",
            "where p is rare, an importance-sampling method (--method adaptive), with its verdict",
        )
        if after_stages:  # neither the stages nor the plain rollouts after them saw a failure
            what, then = ("plain rollouts (--method mc ", "the stages before them saw no failure either")
        return f"more {what}--n {10 * n}{_time(10 * n, s_per)}) lower the bound ten-fold{floor}; {then}"
    if route.n > MC_AFFORDABLE:
        return (
            f"{route.text(s_per, 'plain')}: too rare for plain Monte Carlo; an importance-sampling method "
            "(--method adaptive), with its verdict"
        )
    command = route.command(route.cap(config))
    command = command if after_stages else command.replace("--method mc ", "")
    if not route.fits(max_time):
        assert route.seconds is not None  # within MC_AFFORDABLE: it does not fit the time it measured
        return (
            f"plain Monte Carlo does not fit in --max-time {max_time:g} ({route.text(s_per, 'plain')}): a longer "
            f"--max-time ({command} --max-time {math.ceil(route.seconds)}), or an importance-sampling method "
            "(--method adaptive), with its verdict"
        )
    return f"more rollouts: {command} samples until the interval is within {PERCENT} ({route.text(s_per, 'plain')})"


ODD_STAGES_ALONE = (
    "over an operating design domain the stages run alone: neither their retry nor plain Monte Carlo follows "
    "(--plain-fallback acts on one scene), so this run's verdict is the stages'; plain Monte Carlo over the ODD: "
    "--method mc --n N (a scene of your own may make it its default there: odd_defaults)"
)


def _stages_alone_over_odd(config: ExperimentConfig, e: Estimate) -> bool:
    """Whether a run over an ODD ended without the interval it would have gone on for at one scene: a weighted
    method whose stages a plain fallback follows at one scene (``Method.then``), its verdict not ``reliable``."""
    method = config.method_record
    return bool(
        config.over_odd and e.verdict != "reliable" and method.then is not None and config.fallback.plain_fallback > 0
    )


def final_lines(
    event: FinalEstimate,
    config: ExperimentConfig | None = None,
    exact_log_p: float | None = None,
    reference: Reference | None = None,
    failure_severity: FailureSeverity | None = None,
    committor: bool | None = None,
) -> list[str]:
    """The lines under the table: mu_hat with its log and the run's size, the estimate's summary with the exact answer
    or reference, the severity curve and, with ``failure_severity``, the failures by impact speed with their shares of
    p (:meth:`pemviz.core.severity.FailureSeverity.line`), why the run stopped and what to do next
    (:func:`next_step`, timed by the event's ``n_simulations`` and ``wall_s``) (the console's, ``--junit``'s and
    ``--report``'s)."""
    e = event.estimate
    point = "no failure seen" if e.n_failures == 0 else f"mu_hat = {format_probability(e.log_mu_hat, 4)}"
    lines = [
        f"{point} (log mu_hat = {e.log_mu_hat:.4f} nats) from {event.n_simulations} simulations in "
        f"{event.wall_s:.1f} s",
        e.summary(exact_log_p, reference),
    ]
    if event.look_ahead:
        lines.append(
            "look-ahead: each rollout weighs up to the state from which the scenario computes the failure "
            "probability exactly, times that probability (conditional Monte Carlo); the failures counted are "
            "the rollouts that can still fail there"
        )
    if event.severity is not None and len(event.severity.points) > 1:
        lines += event.severity.lines()
    if failure_severity is not None and failure_severity.n_failures:
        lines.append(failure_severity.line())
    if event.pem_spread is not None:
        lines += event.pem_spread.lines()
    if event.stop is not None:
        lines.append(f"stop: {event.stop}")
    elif config is not None and _stages_alone_over_odd(config, e):
        lines.append(f"stop: {ODD_STAGES_ALONE}")
    if event.prepared is not None:
        lines.append(f"proposal: {event.prepared}")
    advice = next_step(
        e, config, exact_log_p, reference, event.n_simulations, event.wall_s, event.plain_rollout_s, committor
    )
    if advice is not None:
        lines.append(f"next: {advice}")
    return lines


class ConsoleSink(Sink):
    """Prints a line when each stage starts (progress, to ``progress``) and the table rows (to ``out``)."""

    def __init__(self, out: TextIO | None = None, progress: TextIO | None = None) -> None:
        self.out = out or sys.stdout
        self.progress = progress or sys.stderr
        self.clock = StageClock()
        self.plan: RunPlan | None = None
        """The run's :class:`~pemviz.core.plan.RunPlan` (from :class:`~pemviz.engine.events.RunStarted`)."""
        self.config: ExperimentConfig | None = None
        self.exact_log_p: float | None = None
        self.reference: Reference | None = None
        self.failures: SharedGroups | None = None
        """A listener that has grouped the final estimate's failures before this sink hears of it
        (:class:`pemviz.sinks.population.FailureGroups`, run before it): its grouping's severity is printed
        (:func:`final_lines`); None: not printed."""

    def __call__(self, event: Event) -> None:
        self.clock(event)
        super().__call__(event)

    def on_run_started(self, event: RunStarted) -> None:
        cfg = self.config = event.config
        self.exact_log_p, self.reference, self.plan = event.exact_log_p, event.reference, event.plan
        self.committor = getattr(event.problem, "committor", None)
        params = scenario_params_text(cfg.scenario, cfg.scenario_params)
        print(
            f"pemviz: {cfg.method} on the {event.problem.name} scenario{params}, spec "
            f"{event.formula}, metric {cfg.metric}, "
            + (
                f"K={self.plan.n_ce} N={cfg.n_per_stage} N_e={cfg.adaptive.n_final} "
                f"sigma={cfg.adaptive.quantile_level} alpha={cfg.adaptive.smoothing}"
                if self.plan.n_ce
                else f"N={cfg.n_per_stage}"
            )
            + f" seed={cfg.seed}",
            file=self.out,
        )
        print(HEADER, file=self.out)

    def on_stage_started(self, event: StageStarted) -> None:
        assert self.plan is not None  # the run has started
        label = self.plan.label(event.stage, event.kind)
        clock = self.clock
        expected = clock.expected_s(event.kind, event.n_rollouts, event.stage)
        then = clock.follow.text() if clock.follow is not None and not clock.done else ""  # the first line says why
        why = LOAD_WORDS if clock.follow is None and not clock.done else ""
        left, most = clock.run_left_s(), clock.run_most_s()
        line = progress_line(label, event.n_rollouts, clock.elapsed_s(), expected, left, most, then, why)
        print(f"  {line}", file=self.progress, flush=True)

    def on_stage_finished(self, event: StageFinished) -> None:
        print(stage_row(event.result), file=self.out, flush=True)

    def on_final_estimate(self, event: FinalEstimate) -> None:
        e = event.estimate
        print(f"{'final':>7} {'':>8} {'':>9} {estimate_cells(e)} {event.wall_s:>7.2f}", file=self.out)
        grouping = getattr(self.failures, "grouping", None)
        severity = getattr(grouping, "severity", None)
        lines = final_lines(event, self.config, self.exact_log_p, self.reference, severity, self.committor)
        print("\n".join(lines), file=self.out)
        self.out.flush()

    def on_run_cancelled(self, event: RunCancelled) -> None:
        print(f"run cancelled after {len(event.stages)} stages: {event.reason}", file=self.out, flush=True)
