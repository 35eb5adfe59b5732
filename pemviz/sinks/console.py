"""Console sink: progress per stage and the results table of ``pemviz run``."""

from __future__ import annotations

import math
import sys
from typing import TextIO

from pemviz.core.estimate import Estimate, Reference, format_probability
from pemviz.core.severity import FailureSeverity
from pemviz.engine.events import FinalEstimate, RunCancelled, RunStarted, StageFinished, StageResult, StageStarted
from pemviz.sinks import Sink, StageClock

__all__ = ["ConsoleSink", "HEADER", "estimate_cells", "final_lines", "next_step", "progress_line", "stage_row"]

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


def progress_line(label: str, n_rollouts: int, elapsed_s: float, expected_s: float,
                  run_left_s: float = math.nan) -> str:  # fmt: skip
    """``CE stage 3/10: 1000 rollouts ... (elapsed 12.3 s, this stage ~1.2 s, run ~8.4 s left)``: the stage's
    expected seconds and the whole run's left (:class:`pemviz.sinks.StageClock`), each left out where unknown."""
    eta = f", this stage ~{expected_s:.1f} s" if math.isfinite(expected_s) else ""
    left = f", run ~{run_left_s:.1f} s left" if math.isfinite(run_left_s) else ""
    return f"{label}: {n_rollouts} rollouts ... (elapsed {elapsed_s:.1f} s{eta}{left})"


def stage_row(res: StageResult) -> str:
    """One table row: stage, kind, gamma_kappa, the estimate's cells (:func:`estimate_cells`), wall time (s)."""
    return f"{res.stage:>7d} {res.kind:>8} {_num(res.gamma, '9.4f'):>9} {estimate_cells(res.estimate)} {res.wall_s:>7.2f}"


NOT_RARE = 1e-5
"""A failure probability at or above this is not rare: plain Monte Carlo sees 100 failures in 10^7 rollouts."""


MC_AFFORDABLE = 10**8
"""The most rollouts :func:`next_step` suggests plain Monte Carlo for."""


def next_step(e: Estimate, config, exact_log_p: float | None = None, reference: Reference | None = None) -> str | None:
    """What to do after a run whose verdict is not ``reliable``, in one line (None for a reliable one): plain Monte
    Carlo with a precision target where p is not rare (:data:`NOT_RARE`, judged from the exact answer, the reference,
    or the estimate), else more budget or a precision target (``--rel-error``); for splitting, which has no final batch
    to add to, more particles or the committor's graded score (``--ams-score committor``)."""
    if e.verdict == "reliable" or config is None:
        return None
    known = exact_log_p if exact_log_p is not None else (reference.log_p if reference is not None else None)
    guess = known if known is not None else (e.log_mu_hat if e.n_failures else None)
    method = getattr(config, "method", "adaptive")
    if method == "mc":
        if guess is not None and guess > -math.inf:
            need = math.ceil(1.96**2 / (0.2**2 * math.exp(guess)))  # 20 % relative half-width: ~96 failures
            if need > MC_AFFORDABLE:
                return (f"p ~ {format_probability(guess, 2)} is too rare for plain Monte Carlo (about {need:.1e} "
                        "rollouts for a 20 % interval): an importance-sampling method (--method adaptive), with its "
                        "verdict")  # fmt: skip
            return (f"more rollouts: --rel-error 0.2 samples until the interval is within 20 % (about {need:,} "
                    "rollouts at this p; cap them with --max-sims or --max-time)")  # fmt: skip
        return (f"more rollouts (--n {10 * e.n}) lower the bound ten-fold; where p is rare, an importance-sampling "
                "method (--method adaptive) with its verdict")  # fmt: skip
    if method == "tilt":  # the scene's own proposal: more of its batches, pooled alike
        return ("more rollouts: --rel-error 0.2 adds tilted batches until the interval is within 20 % (cap them with "
                "--max-sims or --max-time); heavy-tailed weights (k-hat > 0.7) can still hide a rare large weight, so "
                "compare with plain Monte Carlo (--method mc --rel-error 0.2) where p is not rare")
    if guess is not None and guess >= math.log(NOT_RARE):
        return (f"p ~ {format_probability(guess, 2)} is not rare: plain Monte Carlo gets it right, e.g. --method mc "
                "--rel-error 0.2 --max-time 600")  # fmt: skip
    n = getattr(config, "n_per_stage", 100)
    if method == "ams":  # no final batch to add to: more particles, or a graded score where the robustness ties
        more = f"more particles (--n {4 * n})"
        if getattr(config, "ams_score", "robustness") == "robustness":
            return (f"{more}, or particles ranked by the scenario's committor where it has one (--ams-score "
                    "committor): where the robustness is flat every particle ties and the run dies out; the verdict "
                    "says whether to trust the result")  # fmt: skip
        return f"{more}; the verdict says whether to trust the result"
    return (f"more budget (--n {4 * n}) or a precision target (--rel-error 0.1 --max-sims 100000: final batches are "
            "added until the interval is within 10 %); the verdict says whether to trust the result")


def scenario_params_text(cfg) -> str:
    """The scenario's parameters that differ from its defaults, as the header line gives them after the scenario's
    name: e.g. `` (cut_in_gap_m=19.5 m)``; ``""``: none."""
    pairs = getattr(cfg, "scenario_params", ())
    if not pairs:
        return ""
    from pemviz.scenarios.parameters import changed_parameters, parameters_text

    changed = changed_parameters(cfg.scenario, pairs)
    return f" ({parameters_text(cfg.scenario, changed)})" if changed else ""


def final_lines(event: FinalEstimate, config=None, exact_log_p: float | None = None, reference: Reference | None = None,
                failure_severity: FailureSeverity | None = None) -> list[str]:  # fmt: skip
    """The lines under the table: mu_hat with its log and the run's size, the estimate's summary with the exact answer
    or reference, the severity curve and, with ``failure_severity``, the failures by impact speed with their shares of
    p (:meth:`pemviz.core.severity.FailureSeverity.line`), why the run stopped and what to do next (the console's,
    ``--junit``'s and ``--report``'s)."""
    e = event.estimate
    point = "no failure seen" if e.n_failures == 0 else f"mu_hat = {format_probability(e.log_mu_hat, 4)}"
    lines = [f"{point} (log mu_hat = {e.log_mu_hat:.4f} nats) from {event.n_simulations} simulations in "
             f"{event.wall_s:.1f} s", e.summary(exact_log_p, reference)]  # fmt: skip
    if event.look_ahead:
        lines.append("look-ahead: each rollout weighs up to the state from which the scenario computes the failure "
                     "probability exactly, times that probability (conditional Monte Carlo); the failures counted are "
                     "the rollouts that can still fail there")  # fmt: skip
    if event.severity is not None and len(event.severity.points) > 1:
        lines += event.severity.lines()
    if failure_severity is not None and failure_severity.n_failures:
        lines.append(failure_severity.line())
    if event.pem_spread is not None:
        lines += event.pem_spread.lines()
    if event.stop is not None:
        lines.append(f"stop: {event.stop}")
    if event.prepared is not None:
        lines.append(f"proposal: {event.prepared}")
    advice = next_step(e, config, exact_log_p, reference)
    if advice is not None:
        lines.append(f"next: {advice}")
    return lines


class ConsoleSink(Sink):
    """Prints a line when each stage starts (progress, to ``progress``) and the table rows (to ``out``)."""

    def __init__(self, out: TextIO | None = None, progress: TextIO | None = None) -> None:
        self.out = out or sys.stdout
        self.progress = progress or sys.stderr
        self.clock = StageClock()
        self.plan = None
        """The run's :class:`~pemviz.core.plan.RunPlan` (from :class:`~pemviz.engine.events.RunStarted`)."""
        self.config = None
        self.exact_log_p: float | None = None
        self.reference: Reference | None = None
        self.failures = None
        """A listener that has grouped the final estimate's failures before this sink hears of it
        (:class:`pemviz.sinks.population.FailureGroups`, run before it): its grouping's severity is printed
        (:func:`final_lines`); None: not printed."""

    def __call__(self, event) -> None:
        self.clock(event)
        super().__call__(event)

    def on_run_started(self, event: RunStarted) -> None:
        cfg = self.config = event.config
        self.exact_log_p, self.reference, self.plan = event.exact_log_p, event.reference, event.plan
        print(
            f"pemviz: {cfg.method} on the {event.problem.name} scenario{scenario_params_text(cfg)}, spec "
            f"{event.formula}, metric {cfg.metric}, " + (
                f"K={self.plan.n_ce} N={cfg.n_per_stage} N_e={cfg.n_final} sigma={cfg.quantile_level} "
                f"alpha={cfg.smoothing}" if self.plan.n_ce else f"N={cfg.n_per_stage}") + f" seed={cfg.seed}",
            file=self.out,
        )
        print(HEADER, file=self.out)

    def on_stage_started(self, event: StageStarted) -> None:
        label = self.plan.label(event.stage, event.kind)
        expected = self.clock.expected_s(event.kind, event.n_rollouts)
        line = progress_line(label, event.n_rollouts, self.clock.elapsed_s(), expected, self.clock.run_left_s())
        print(f"  {line}", file=self.progress, flush=True)

    def on_stage_finished(self, event: StageFinished) -> None:
        print(stage_row(event.result), file=self.out, flush=True)

    def on_final_estimate(self, event: FinalEstimate) -> None:
        e = event.estimate
        print(f"{'final':>7} {'':>8} {'':>9} {estimate_cells(e)} {event.wall_s:>7.2f}", file=self.out)
        grouping = getattr(self.failures, "grouping", None)
        severity = getattr(grouping, "severity", None)
        print("\n".join(final_lines(event, self.config, self.exact_log_p, self.reference, severity)), file=self.out)
        self.out.flush()

    def on_run_cancelled(self, event: RunCancelled) -> None:
        print(f"run cancelled after {len(event.stages)} stages: {event.reason}", file=self.out, flush=True)
