"""The map of where p_ODD comes from for a run over an operating design domain: the final stage's parameters,
weights and failures gathered as they pass and binned after the final estimate (:func:`pemviz.core.odd.odd_map`),
carried as :attr:`pemviz.engine.events.FinalEstimate.odd_map`."""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from pemviz.core.odd import OddMap, odd_map
from pemviz.core.odd_pair import pair_map
from pemviz.engine.events import RolloutChunk

if TYPE_CHECKING:
    from pemviz.core.problems import Problem


class OddMapCollector:
    """The final stage's rollouts of a run over ``problem.odd`` (its last final stage: a precision target adds
    batches), kept as four arrays a chunk: parameters ``[n, D]``, log weights, failures, log p of the detections."""

    def __init__(self, problem: Problem) -> None:
        self.problem, self.odd = problem, problem.odd
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self._stage: int | None = None

    def add(self, event: RolloutChunk) -> None:
        """Keep a final stage's chunk (other stages' are ignored)."""
        from pemviz.estimators.base import log_p_before_failure

        if event.kind != "final":
            return
        if self._stage != event.stage:
            self._stage, self._parts = event.stage, []
        b = event.batch
        cols = [tuple(b.observation_names).index(name) for name in self.odd.names]
        self._parts.append(
            (
                b.observations[:, 0][:, cols],
                np.asarray(event.log_weight, dtype=np.float64),
                self.problem.failed(b),
                log_p_before_failure(self.problem, b),
            )
        )

    def result(self, cap: tuple[str, str] | None) -> OddMap | None:
        """The map of the kept rollouts, each bin's verdict at most the run's ``cap`` (verdict, reason); None without
        rollouts."""
        if not self._parts:
            return None
        values, log_w, failed, log_p = (np.concatenate(x) for x in zip(*self._parts, strict=True))
        bins = [
            dataclasses.replace(b, estimate=b.estimate.at_most(cap)) if cap else b
            for b in odd_map(self.odd, values, log_w, failed, log_p)
        ]
        pair = pair_map(self.odd, values, log_w, failed, log_p)
        if pair is not None and cap:
            pair = dataclasses.replace(pair, cells=tuple(tuple(e.at_most(cap) for e in row) for row in pair.cells))
        return OddMap(self.odd, len(log_w), tuple(bins), pair)
