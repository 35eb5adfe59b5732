"""Console sink: progress per stage and the results table of ``pemviz run``."""

from __future__ import annotations

import math
import sys
from typing import TextIO

from pemviz.engine import (
    Event,
    FinalEstimate,
    RunCancelled,
    RunStarted,
    StageFinished,
    StageResult,
    StageStarted,
)
from pemviz.sampling import Estimate, format_probability

HEADER = (
    f"{'stage':>7} {'kind':>8} {'gamma':>9} {'failures':>10} {'mu_hat':>11} {'95% CI':>21} {'NLL':>8} {'ESS':>7} "
    f"{'k-hat':>6} {'verdict':>10} {'wall s':>7}"
)


def _num(x: float, fmt: str) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


def _estimate_cells(e: Estimate) -> str:
    """failures/N, mu_hat, its interval, mean NLL (nats), ESS, k-hat and verdict, aligned with :data:`HEADER`."""
    return (
        f"{f'{e.n_failures}/{e.n}':>10} {format_probability(e.log_mu_hat):>11} {e.interval_text():>21} "
        f"{_num(e.nll_mean, '8.2f'):>8} {_num(e.ess, '7.2f'):>7} {_num(e.khat, '6.2f'):>6} {e.verdict:>10}"
    )


def stage_row(res: StageResult) -> str:
    """One table row: stage, kind, gamma_kappa, the estimate's cells (:func:`_estimate_cells`), wall time (s)."""
    return f"{res.stage:>7d} {res.kind:>8} {_num(res.gamma, '9.4f'):>9} {_estimate_cells(res.estimate)} {res.wall_s:>7.2f}"


class ConsoleSink:
    """Prints a line when each stage starts (progress, to ``progress``) and the table rows (to ``out``)."""

    def __init__(self, out: TextIO | None = None, progress: TextIO | None = None) -> None:
        self.out = out or sys.stdout
        self.progress = progress or sys.stderr
        self.n_stages = 0
        self.exact_log_p: float | None = None

    def __call__(self, event: Event) -> None:
        if isinstance(event, RunStarted):
            cfg = event.config
            self.exact_log_p = event.exact_log_p
            self.n_stages = cfg.n_stages + 2 if cfg.method == "adaptive" else 1
            print(
                f"pemviz: {cfg.method} on the braking scenario, spec {event.formula}, metric {cfg.metric}, "
                f"K={cfg.n_stages} N={cfg.n_per_stage} N_e={cfg.n_final} sigma={cfg.quantile_level} "
                f"alpha={cfg.smoothing} seed={cfg.seed}",
                file=self.out,
            )
            print(HEADER, file=self.out)
        elif isinstance(event, StageStarted):
            done = event.stage if self.n_stages > 1 else 0
            print(
                f"  [{done}/{self.n_stages}] stage {event.stage} ({event.kind}): {event.n_rollouts} rollouts ...",
                file=self.progress,
                flush=True,
            )
        elif isinstance(event, StageFinished):
            print(stage_row(event.result), file=self.out, flush=True)
        elif isinstance(event, FinalEstimate):
            e = event.estimate
            print(f"{'final':>7} {'':>8} {'':>9} {_estimate_cells(e)} {event.wall_s:>7.2f}", file=self.out)
            print(
                f"mu_hat = {format_probability(e.log_mu_hat, 4)} (log mu_hat = {e.log_mu_hat:.4f} nats) "
                f"from {event.n_simulations} simulations in {event.wall_s:.1f} s",
                file=self.out,
            )
            print(e.summary(self.exact_log_p), file=self.out, flush=True)
        elif isinstance(event, RunCancelled):
            print(f"run cancelled after {len(event.stages)} stages: {event.reason}", file=self.out, flush=True)
