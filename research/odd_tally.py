"""What the ODD studies (``research/odd_*.py``) print of each seed and of the seeds together: the run's estimate against
the answer, its failures, ESS, k-hat and verdict with its reason, what it printed (a 95 % interval or a lower bound)
and whether that held; and, for every run, whether its interval ``log_ci`` (computed whatever the verdict) held.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class Tally:
    """The seeds' runs against the answer ``log_p`` (nats)."""

    log_p: float
    ratios: list[float] = field(default_factory=list)
    printed_holds: int = 0
    intervals: int = 0
    intervals_hold: int = 0
    any_ci_holds: int = 0
    reliable_off: int = 0
    nan: int = 0
    points: list[int] = field(default_factory=lambda: [0, 0, 0, 0, 0])
    """The map's points: [all, holding, printing an interval, those holding, reliable outside x2]."""

    def add(self, e: object) -> str:
        """Count the :class:`pemviz.core.estimate.Estimate` ``e`` and return its line."""
        from pemviz.core.estimate import Estimate

        assert isinstance(e, Estimate)
        r = math.exp(e.log_mu_hat - self.log_p)
        self.ratios.append(r)
        self.nan += not math.isfinite(e.log_mu_hat) or any(math.isnan(x) for x in e.log_ci)
        held = e.covers(self.log_p)
        self.printed_holds += held
        self.intervals += e.interval_backed
        self.intervals_hold += e.interval_backed and held
        ci_held = e.log_ci[0] <= self.log_p <= e.log_ci[1]
        self.any_ci_holds += ci_held
        self.reliable_off += e.verdict == "reliable" and not 0.5 < r < 2
        khat = "-" if math.isnan(e.khat) else f"{e.khat:.2f}"
        return (
            f"x{r:.3f}, {e.n_failures:,} failures of {e.n:,}, ESS {e.ess:.1f}, k-hat {khat}: {e.verdict} ({e.reason}); "
            f"printed {e.interval_text()} {'holds' if held else 'MISSES'}; its interval "
            f"{'holds' if ci_held else 'misses'}"
        )

    def add_point(self, e: object, log_truth: float) -> bool:
        """Count one point of the map, its :class:`pemviz.core.estimate.Estimate` ``e`` against ``log_truth`` (nats);
        whether what it printed holds it."""
        from pemviz.core.estimate import Estimate

        assert isinstance(e, Estimate)
        held = e.covers(log_truth)
        r = math.exp(e.log_mu_hat - log_truth)
        for i, counted in enumerate(
            (True, held, e.interval_backed, e.interval_backed and held, e.verdict == "reliable" and not 0.5 < r < 2)
        ):
            self.points[i] += counted
        return held

    def points_text(self) -> str:
        """The map's points together."""
        n, held, intervals, intervals_held, off = self.points
        return (
            f"the map's points: {held}/{n} holding, {intervals} printing an interval, of which {intervals_held} "
            f"holding, reliable outside x2 {off}"
        )

    def summary(self) -> str:
        """The seeds together: median relative error, within x2, printed intervals holding, and the rest."""
        x = np.array(self.ratios)
        n = x.size
        return (
            f"{n} seeds: median relative error {np.median(np.abs(x - 1)):.3f}, within x2 {np.sum((x > 0.5) & (x < 2))}"
            f"/{n}, printed intervals or bounds holding {self.printed_holds}/{n}, printed intervals "
            f"{self.intervals}/{n} of which holding {self.intervals_hold}, every run's interval (whatever its "
            f"verdict) holding {self.any_ci_holds}/{n}, reliable outside x2 {self.reliable_off}, nan {self.nan}"
        )
