"""Console sink: progress per stage and the results table of ``pemviz run``."""

from __future__ import annotations

import math
import sys
import time
from typing import TextIO

from pemviz.engine import (
    Event,
    FinalEstimate,
    RolloutsSampled,
    RunCancelled,
    RunStarted,
    StageFinished,
    StageResult,
    StageStarted,
    stage_label,
)
from pemviz.estimate import Estimate, format_probability

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


def expected_stage_s(done: list[StageResult], kind: str, n_rollouts: int, sample_s_per_rollout: float = math.nan) -> float:
    """Expected seconds of a stage of ``n_rollouts`` rollouts (nan when nothing comparable has run yet).

    A CE stage takes as long as the last CE stage did (sampling plus the proposal update). The final batch
    only samples: ``n_rollouts`` times the seconds per rollout measured while the last CE stage sampled
    (``sample_s_per_rollout``). Pretraining predicts neither (its time is the fit of a few rollouts).
    """
    if kind == "final":
        return n_rollouts * sample_s_per_rollout
    alike = [r for r in done if r.kind == kind]
    return alike[-1].wall_s if alike else math.nan


def progress_line(label: str, n_rollouts: int, elapsed_s: float, expected_s: float) -> str:
    """``CE stage 3/10: 1000 rollouts ... (elapsed 12.3 s, this stage ~1.2 s)``."""
    eta = f", this stage ~{expected_s:.1f} s" if math.isfinite(expected_s) else ""
    return f"{label}: {n_rollouts} rollouts ... (elapsed {elapsed_s:.1f} s{eta})"


def stage_row(res: StageResult) -> str:
    """One table row: stage, kind, gamma_kappa, the estimate's cells (:func:`estimate_cells`), wall time (s)."""
    return f"{res.stage:>7d} {res.kind:>8} {_num(res.gamma, '9.4f'):>9} {estimate_cells(res.estimate)} {res.wall_s:>7.2f}"


class ConsoleSink:
    """Prints a line when each stage starts (progress, to ``progress``) and the table rows (to ``out``)."""

    def __init__(self, out: TextIO | None = None, progress: TextIO | None = None) -> None:
        self.out = out or sys.stdout
        self.progress = progress or sys.stderr
        self.n_stages = 0
        self.n_ce = 0
        self.t0 = time.perf_counter()
        self.done: list[StageResult] = []
        self.stage_t0 = self.t0
        self.sample_s_per_rollout = math.nan
        self.exact_log_p: float | None = None

    def __call__(self, event: Event) -> None:
        if isinstance(event, RunStarted):
            cfg = event.config
            self.exact_log_p = event.exact_log_p
            self.n_stages = cfg.n_stages + 2 if cfg.method == "adaptive" else 1
            self.n_ce = cfg.n_stages
            self.t0 = time.perf_counter()
            self.done = []
            print(
                f"pemviz: {cfg.method} on the braking scenario, spec {event.formula}, metric {cfg.metric}, "
                f"K={cfg.n_stages} N={cfg.n_per_stage} N_e={cfg.n_final} sigma={cfg.quantile_level} "
                f"alpha={cfg.smoothing} seed={cfg.seed}",
                file=self.out,
            )
            print(HEADER, file=self.out)
        elif isinstance(event, StageStarted):
            self.stage_t0 = time.perf_counter()
            label = stage_label(event.stage, event.kind, self.n_ce)
            expected = expected_stage_s(self.done, event.kind, event.n_rollouts, self.sample_s_per_rollout)
            line = progress_line(label, event.n_rollouts, time.perf_counter() - self.t0, expected)
            print(f"  {line}", file=self.progress, flush=True)
        elif isinstance(event, RolloutsSampled) and event.kind == "ce":
            self.sample_s_per_rollout = (time.perf_counter() - self.stage_t0) / max(1, event.n_total or event.batch.n)
        elif isinstance(event, StageFinished):
            self.done.append(event.result)
            print(stage_row(event.result), file=self.out, flush=True)
        elif isinstance(event, FinalEstimate):
            e = event.estimate
            print(f"{'final':>7} {'':>8} {'':>9} {estimate_cells(e)} {event.wall_s:>7.2f}", file=self.out)
            print(
                f"mu_hat = {format_probability(e.log_mu_hat, 4)} (log mu_hat = {e.log_mu_hat:.4f} nats) "
                f"from {event.n_simulations} simulations in {event.wall_s:.1f} s",
                file=self.out,
            )
            print(e.summary(self.exact_log_p), file=self.out, flush=True)
        elif isinstance(event, RunCancelled):
            print(f"run cancelled after {len(event.stages)} stages: {event.reason}", file=self.out, flush=True)
