"""The map of where p_ODD comes from, said after the final estimate of a run over an operating design domain: for
each drawn parameter, its bins with p(failure | bin), the bin's interval and verdict, and its share of p_ODD, then
one line naming the region that carries most of it (:func:`pemviz.core.odd.odd_map`). From the run's final stage
(its final batch; plain Monte Carlo's one batch), whose rollouts carry their parameters as observation columns."""

from __future__ import annotations

import dataclasses
import sys
from typing import Any, TextIO

import numpy as np

from pemviz.core.estimate import format_probability
from pemviz.core.odd import MapBin, odd_map
from pemviz.engine.events import FinalEstimate, RolloutChunk
from pemviz.estimators.base import log_p_before_failure
from pemviz.sinks import Sink


class OddMapSink(Sink):
    """Gathers the final stage's rollouts (parameters, importance weights, failures) and prints the map after the
    final estimate; :attr:`bins` holds it (empty before, or without failures)."""

    def __init__(self, problem: Any, out: TextIO | None = None) -> None:
        self.problem, self.out = problem, out
        self.odd = problem.odd
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self._stage: int | None = None
        self.bins: list[MapBin] = []
        self.rollouts = 0

    def on_rollout_chunk(self, event: RolloutChunk) -> None:
        if event.kind != "final":
            return
        if self._stage != event.stage:  # the last final stage is the map's (a precision target adds batches)
            self._stage, self._parts = event.stage, []
        b = event.batch
        cols = [tuple(b.observation_names).index(name) for name in self.odd.names]
        failed = self.problem.failed(b)
        self._parts.append(
            (
                b.observations[:, 0][:, cols],
                np.asarray(event.log_weight, dtype=np.float64),
                failed,
                log_p_before_failure(self.problem, b),
            )
        )

    def on_final_estimate(self, event: FinalEstimate) -> None:
        if not self._parts:
            return
        values, log_w, failed, log_p = (np.concatenate(x) for x in zip(*self._parts, strict=True))
        self.rollouts = len(log_w)
        cap = event.verdict_cap  # the run's own cap holds for its bins too (they are its final stage's weights)
        self.bins = [
            dataclasses.replace(b, estimate=b.estimate.at_most(cap)) if cap else b
            for b in odd_map(self.odd, values, log_w, failed, log_p)
        ]
        for line in self.lines():
            print(line, file=self.out or sys.stdout)

    def lines(self) -> list[str]:
        """The map's lines: a header, a line per bin, the region that carries most of p_ODD."""
        if not self.bins:
            return []
        out = [
            f"odd map ({self.odd.text()}; the final stage's {self.rollouts:,} rollouts): p(failure | bin), "
            "its 95 % interval or lower bound, its verdict, its share of p_ODD"
        ]
        for b in self.bins:
            e = b.estimate
            said = format_probability(e.log_mu_hat) if e.n_failures else "no failure"
            out.append(
                f"  {b.label:32s} P(bin) {b.probability:.2f}  p {said:>10s} {e.interval_text():>26s}  "
                f"{e.verdict:10s} share {100 * b.share:5.1f} %"
            )
        top = max(self.bins, key=lambda b: b.share)
        if top.share > 0:
            out.append(f"most of p_ODD: {top.label} ({100 * top.share:.0f} % of it, P(bin) {top.probability:.2f})")
        return out

    def document(self) -> dict[str, Any]:
        """The map for the result document: the ODD and each bin's range, probability, estimate and share."""
        return {
            "odd": self.odd.to_json(),
            "rollouts": self.rollouts,
            "bins": [
                {
                    "parameter": b.name,
                    "lo": b.lo,
                    "hi": b.hi,
                    "probability": b.probability,
                    "log_p": b.estimate.log_mu_hat if b.estimate.n_failures else None,
                    "log_ci": [_finite(x) for x in b.estimate.shown_log_ci],
                    "verdict": b.estimate.verdict,
                    "share": b.share,
                }
                for b in self.bins
            ],
        }


def _finite(x: float) -> float | None:
    """``x``, or None where it is not finite (JSON has no infinity): an interval without an upper end."""
    return float(x) if np.isfinite(x) else None
