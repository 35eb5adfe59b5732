"""Severity: how deep the failures go, as an exceedance curve P(failure and min_t s_t < x) over levels x of a signal.

For a signal s (e.g. the braking gap, metres) and levels x from the spec's margin down to 0, each point is estimated
from the run's importance-weighted rollouts: with E_x the event and tau_x the step at which it is decided (the later
of the failure step and the first step with s < x), mu_hat_x = (1/N) sum_i 1[E_x,i] w_i(tau_x,i), w_i(k) = prod_{t <
k} p / q; optional stopping at tau_x keeps each term unbiased (Innes & Ramamoorthy 2022, eq. 6, with the failure
step replaced by tau_x). A problem states its scale (:class:`SeverityScale`); the engine fills a
:class:`SeverityCurve`.

Each rollout's own severity (:func:`rollout_severity`): its minimum distance and its impact speed, the closing speed
into contact; weighed by the failures' shares of p they give p(severity | failure) (:class:`FailureSeverity`)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np
from scipy.special import logsumexp

from pemviz.core.estimate import Estimate, error_text, format_probability

if TYPE_CHECKING:  # annotations only
    from pemviz.core.rollouts import RolloutBatch


@dataclass(frozen=True)
class SeverityScale:
    """Which signal measures a failure's severity and at which levels the curve is estimated.

    Attributes:
        signal: the STL signal name (e.g. ``d``, the braking scenario's gap).
        label: what the signal is, for people (``gap``, ``clearance``).
        unit: its unit (``m``).
        levels: the levels x below the failure itself, descending; the event at x is "failure and min_t s_t < x".
        margin: the level at which the spec itself fails on this signal (e.g. 2 m), or None where the failure is not
            a level of it.
        contact: the distance at or below which the objects are in contact (:func:`contact_level`): 0 where the
            boxes meet, more where the scene stops its objects short of 0.
        target_flag: the ``pemviz run`` flag that makes a level the failure itself (``margin``), or None."""

    signal: str
    label: str
    unit: str
    levels: tuple[float, ...]
    margin: float | None = None
    contact: float = 0.0
    target_flag: str | None = None

    def __post_init__(self) -> None:
        if any(b >= a for a, b in zip(self.levels, self.levels[1:], strict=False)):
            raise ValueError(f"severity levels must be strictly descending, got {self.levels}")

    def level_text(self, x: float) -> str:
        """``gap < 1 m``: the level by its distance alone. Contact is one level, :func:`contact_level`, which the
        impact-speed line states (``contact: gap <= 0.7 m``); a level's row does not repeat the word."""
        return f"{self.label} < {x:g} {self.unit}".replace("  ", " ")


def level_events(
    signal: np.ndarray, failed: np.ndarray, fail_step: np.ndarray, levels: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Which rollouts reach each severity level, and the step at which that is decided.

    Args:
        signal: s_t of each rollout, float64 [N, T] (e.g. metres).
        failed: the failure event, bool [N].
        fail_step: the step of each rollout's failure, int [N] (T where it does not fail).
        levels: x, float64 [L].
    Returns:
        ``hit`` bool [L, N]: failed and min_t s_t < x; ``step`` int [L, N]: for a hit, max(failure step, first t with
        s_t < x), the step at which E_x is decided (T where there is no hit).
    Raises:
        ValueError: shapes that do not match."""
    signal = np.asarray(signal, dtype=np.float64)
    n, t = signal.shape
    failed, fail_step = np.asarray(failed, dtype=bool), np.asarray(fail_step)
    if failed.shape != (n,) or fail_step.shape != (n,):
        raise ValueError(f"level_events: failed {failed.shape} and fail_step {fail_step.shape} need shape ({n},)")
    levels = np.asarray(levels, dtype=np.float64).reshape(-1)
    if levels.size == 0:
        return np.zeros((0, n), bool), np.zeros((0, n), np.int64)
    below = signal[None, :, :] < levels[:, None, None]  # [L, N, T]
    reached = below.any(axis=2)
    first = np.where(reached, below.argmax(axis=2), t)
    hit = reached & failed[None, :]
    step = np.where(hit, np.maximum(first, fail_step[None, :]), t)
    return hit, step


@dataclass(frozen=True)
class SeverityPoint:
    """One point of the exceedance curve: P(failure and min s < ``level``) and where it comes from.

    Attributes:
        level: x (the scale's unit); None for the failure itself (the run's estimate).
        estimate: its estimate, interval, ESS and verdict (from the same rollouts as the run's estimate).
        exact_log_p: the exact log probability (nats) where it is known, else None."""

    level: float | None
    estimate: Estimate
    exact_log_p: float | None = None

    @property
    def reached(self) -> bool:
        """True when the run's rollouts reach the level often enough to trust the point (a ``reliable`` verdict)."""
        return self.estimate.verdict == "reliable"


SHOWN = ("interval", "estimate and bound", "bound", "no bound", "not reached")
"""What a run shows of a point of its severity curve (:meth:`SeverityCurve.shown`)."""


@dataclass(frozen=True)
class SeverityCurve:
    """The exceedance curve of a run: the failure itself, then each level of the scale (:class:`SeverityScale`).

    Attributes:
        scale: the signal and its levels.
        points: the failure first (``level`` None, or the scale's margin), then one per level, descending."""

    scale: SeverityScale
    points: tuple[SeverityPoint, ...]

    def failure_level_text(self) -> str:
        """How the first point (the failure) reads: ``gap < 2 m (the spec's margin)`` or ``the spec's failure``."""
        m = self.scale.margin
        if m is None:
            return "the spec's failure"
        return f"{self.scale.level_text(m)}, the spec's margin"

    def point_text(self, point: SeverityPoint) -> str:
        """What a point's level is, in words: the first point :meth:`failure_level_text`, the others
        :meth:`SeverityScale.level_text`."""
        if point is self.points[0]:
            return self.failure_level_text()
        assert point.level is not None  # every point after the failure is a level of the scale
        return self.scale.level_text(point.level)

    def title(self) -> str:
        """``severity: P(min gap < x), from the same rollouts`` (with "failure and" where the failure is not a
        level)."""
        s = self.scale
        event = f"min {s.label} < x" if s.margin is not None else f"failure and min {s.label} < x"
        return f"severity: P({event}), from the same rollouts"

    def shown(self, point: SeverityPoint) -> str:
        """What the run shows of a point (:data:`SHOWN`): ``interval``, an estimate with the interval the run backs
        (plain Monte Carlo, or a ``reliable`` verdict); ``estimate and bound``, the failure itself where the weights
        back no interval (its estimate beside its 95 % lower bound); ``bound``, a level reached but not estimated (its
        lower bound alone); ``no bound``, reached with no bound either way; ``not reached``, no rollout reached it."""
        e = point.estimate
        if point is self.points[0]:
            return "interval" if e.interval_backed or e.n_failures == 0 else "estimate and bound"
        if point.reached:
            return "interval"
        if e.n_failures == 0:
            return "not reached"
        return "bound" if e.log_lower_bound > -math.inf else "no bound"

    def says(self, point: SeverityPoint) -> str:
        """What the run says of a point, the one text the console's line and the report's row both show: the
        estimate, its interval (or lower bound), ESS, verdict and the exact answer where known; a level the run does
        not estimate says why, what it does back, and how to reach it (the scale's ``target_flag``, or more
        rollouts)."""
        e, s, shown = point.estimate, self.scale, self.shown(point)
        if shown in ("interval", "estimate and bound"):
            text = f"{format_probability(e.log_mu_hat)} {e.interval_text()}  ESS {e.ess:.1f}  {e.verdict}"
            if point.exact_log_p is not None:  # "inside" / "OUTSIDE" an interval; "above" / "BELOW" a lower bound
                text += (
                    f"; exact {format_probability(point.exact_log_p)} "
                    f"({error_text(e.log_mu_hat, point.exact_log_p)}, {e.holds_word(point.exact_log_p)})"
                )
            return text
        assert point.level is not None  # only a level of the scale is not estimated
        how = (
            f"pemviz run --{s.target_flag} {point.level:g} targets it"
            if s.target_flag
            else "more rollouts (a larger budget, or --rel-error)"
        )
        if shown == "not reached":
            return f"not reached by this run (0 of {e.n:,} rollouts): {how}"
        bound = (
            f"p >= {format_probability(e.log_lower_bound, 2)} (95 % lower bound), no upper bound"
            if shown == "bound"
            else "no bound either way"
        )
        return (
            f"reached by {e.n_failures:,} of {e.n:,} rollouts, not estimated (ESS {e.ess:.1f}, {e.verdict}): "
            f"{bound}; {how}"
        )

    def rows(self) -> list[tuple[str, str]]:
        """(the point's level in words, what the run says of it: :meth:`says`) for each point."""
        return [(self.point_text(point), self.says(point)) for point in self.points]

    def lines(self) -> list[str]:
        """The curve as console lines: :meth:`title`, then one line per point (:meth:`rows`), e.g.
        ``  gap < 1 m        5.689e-19 [3.75e-19, 8.64e-19]  ESS 21.8  reliable; exact 4.670e-19 (relative error
        0.218, inside)``."""
        rows = self.rows()
        width = max(len(label) for label, _ in rows)
        return [self.title()] + [f"  {label.ljust(width)}  {text}" for label, text in rows]

    def markdown(self) -> str:
        """The curve as a Markdown table under :meth:`title` (for the recording's description)."""
        rows = "\n".join(f"| {label} | {text} |" for label, text in self.rows())
        return f"{self.title()}\n\n| level | estimate |\n|---|---|\n{rows}\n"


# -- per-rollout severity and its importance-weighted distribution among the failures ----------------


def severity_of_signal(signal: np.ndarray, contact: float, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Each rollout's minimum distance and impact speed from its distance signal alone.

    The impact speed is the closing speed over the step into contact, ``(s[t-1] - s[t]) / dt`` at the first step t
    with ``s[t] <= contact``: with explicit Euler steps, the delta-v of crash-severity practice (Evans, "Driver
    injury and fatality risk in two-car crashes versus mass ratio inferred using Newtonian mechanics", Accident
    Analysis & Prevention 26(5), 1994).

    Args:
        signal: s_t of each rollout, float64 [N, T] (metres), T >= 1.
        contact: the distance at or below which the cars touch (metres).
        dt_s: seconds per step (> 0).
    Returns:
        ``(min_distance, impact_speed)``, float64 [N] each: min_t s_t (metres) and the impact speed (m/s, > 0), NaN
            exactly where the rollout never reaches contact.
    Raises:
        ValueError: ``signal`` not [N, T >= 1], a non-finite value in it, ``dt_s`` not positive, or a rollout in
            contact at step 0."""
    s = np.asarray(signal, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] == 0:
        raise ValueError(f"severity_of_signal: signal must be float [N, T >= 1], got shape {s.shape}")
    if not np.isfinite(s).all():
        row = int(np.flatnonzero(~np.isfinite(s).all(axis=1))[0])
        raise ValueError(f"severity_of_signal: rollout {row} has a non-finite distance; the signal must be finite")
    if not (math.isfinite(dt_s) and dt_s > 0):
        raise ValueError(f"severity_of_signal: dt_s must be a positive number of seconds, got {dt_s!r}")
    n = s.shape[0]
    touched = s <= contact
    hit = touched.any(axis=1)
    first = np.where(hit, touched.argmax(axis=1), 0)
    if (hit & (first == 0)).any():
        row = int(np.flatnonzero(hit & (first == 0))[0])
        raise ValueError(
            f"severity_of_signal: rollout {row} is in contact at step 0 ({s[row, 0]:g} <= {contact:g}): "
            "no step into contact, no closing speed"
        )
    rows = np.flatnonzero(hit)
    impact = np.full(n, np.nan)
    impact[rows] = (s[rows, first[rows] - 1] - s[rows, first[rows]]) / dt_s
    return s.min(axis=1), impact


def contact_level(problem: object) -> float:
    """The distance at or below which a problem's objects touch (metres), as its severity scale states it
    (:attr:`SeverityScale.contact`: 0 where the boxes meet, or e.g. 0.7 m where a scene's controller stops the ego).

    Raises:
        ValueError: a problem without a severity scale."""
    scale = getattr(problem, "severity", None)
    if scale is None:
        raise ValueError(f"problem {getattr(problem, 'name', problem)!r} has no severity scale")
    return float(scale.contact)


class SeverityProblem(Protocol):
    """What :func:`rollout_severity` reads of a problem (:class:`pemviz.core.problems.Problem`)."""

    @property
    def name(self) -> str: ...

    @property
    def signals(self) -> Mapping[str, str]: ...

    @property
    def severity(self) -> SeverityScale | None: ...


def rollout_severity(problem: SeverityProblem, batch: RolloutBatch) -> tuple[np.ndarray, np.ndarray]:
    """Each rollout's severity, whatever the scene: its minimum distance along the problem's severity signal
    (:attr:`SeverityScale.signal`, metres) and its impact speed at or below :func:`contact_level`
    (:func:`severity_of_signal`).

    Args:
        problem: a :class:`pemviz.core.problems.Problem` with a severity scale.
        batch: N rollouts (:class:`pemviz.core.rollouts.RolloutBatch`) with the signal's column.
    Returns:
        ``(min_distance, impact_speed)``: float64 [N] each, metres and m/s; the impact speed is NaN exactly where
            the rollout never reaches contact.
    Raises:
        ValueError: a problem without a severity scale or a step (``dt_s``), a rollout in contact at step 0;
            KeyError: the batch lacks the signal's column."""
    contact = contact_level(problem)
    scale = problem.severity
    assert scale is not None  # contact_level raised ValueError otherwise
    column = problem.signals.get(scale.signal, scale.signal)
    dt = getattr(problem, "dt_s", None)
    if dt is None:
        raise ValueError(f"problem {problem.name!r} states no step (dt_s): the impact speed cannot be read")
    return severity_of_signal(batch.signal(column), contact, float(dt))


IMPACT_SPEED_EDGES_MPS = (2.0, 5.0)
"""The impact-speed bins of :class:`FailureSeverity` after "no contact": [0, 2), [2, 5) and [5, inf) m/s (a
low-speed nudge, a moderate impact, a collision that injures: the risk of injury grows steeply with delta-v above
about 5 m/s, Gabauer & Gabler 2008)."""


def share_text(x: float) -> str:
    """A share of p as a percentage, ``97.2 %``; never ``100 %`` for a share below 1, nor ``0 %`` above 0, but a share
    within 1e-12 of 1 (the rounding of a sum of shares) is 100 %."""
    if x <= 0.0 or x >= 1.0 - 1e-12:
        return f"{100 * max(0.0, min(1.0, x)):g} %"
    p = 100.0 * x
    if p < 99.5:
        return f"{p:.3g} %"
    d = 1
    while round(p, d) >= 100.0 and d < 15:
        d += 1
    return f"{p:.{d}f} %"


@dataclass(frozen=True)
class FailureSeverity:
    """p(severity | failure): the failures' severity weighed by their shares of the estimate's p.

    Each failure's share pi_i = w_i / sum_j w_j of mu_hat (:class:`pemviz.core.population.FailureShares`) makes
    sum_i pi_i 1[impact speed of i in bin b] an estimate of P(impact speed in b | failure) (Owen, "Monte Carlo
    theory, methods and examples", 2013, Sec. 9.2). Failures whose rollout was not kept are left out and the shares
    renormalised (:attr:`covered`).

    Attributes:
        scale: the severity signal (its label and unit name the distance).
        contact: the distance at or below which the cars touch (metres).
        log_share: float64 [F] each failure's log share of mu_hat (nats).
        min_distance: float64 [F] its min distance (metres; NaN where not kept).
        impact_speed: float64 [F] its impact speed (m/s; NaN where no contact or not kept).
        kept: bool [F] whether its rollout was located.
        edges: the impact-speed bin edges after "no contact" (m/s, ascending, > 0)."""

    scale: SeverityScale
    contact: float
    log_share: np.ndarray
    min_distance: np.ndarray
    impact_speed: np.ndarray
    kept: np.ndarray
    edges: tuple[float, ...] = IMPACT_SPEED_EDGES_MPS

    @property
    def n_failures(self) -> int:
        """F, every failure of the estimate."""
        return int(self.log_share.size)

    @property
    def n(self) -> int:
        """K <= F, the failures whose severity is known (kept)."""
        return int(np.count_nonzero(self.kept))

    @property
    def covered(self) -> float:
        """The share of mu_hat the kept failures carry (1 when all were kept; 0 when none)."""
        if self.n == self.n_failures:  # every failure kept: 1 exactly, not a sum of shares rounded by the CPU
            return 1.0
        return min(1.0, float(np.exp(logsumexp(self.log_share[self.kept])))) if self.n else 0.0

    def own_log_share(self) -> np.ndarray:
        """float64 [K] each kept failure's log share among the kept ones (nats; logsumexp 0)."""
        own = self.log_share[self.kept]
        return own - float(logsumexp(own)) if own.size else own

    def labels(self) -> list[str]:
        """The bins in words: ``no contact``, ``0-2 m/s``, ``2-5 m/s``, ``> 5 m/s``."""
        lo = (0.0, *self.edges)
        return (
            ["no contact"]
            + [f"{a:g}-{b:g} m/s" for a, b in zip(lo, self.edges, strict=False)]
            + [f"> {self.edges[-1]:g} m/s"]
        )

    def bounds(self) -> list[tuple[float | None, float | None]]:
        """Each bin's impact speeds [lo, hi) in m/s: (None, None) for no contact, hi None for the last."""
        lo = (0.0, *self.edges)
        return [(None, None)] + list(zip(lo, (*self.edges, None), strict=False))

    def bin_of(self) -> np.ndarray:
        """int [K] each kept failure's bin: 0 no contact, then 1 + the impact-speed interval it falls in."""
        speed = self.impact_speed[self.kept]
        contact = np.isfinite(speed)
        return np.where(
            contact, 1 + np.searchsorted(np.asarray(self.edges), np.where(contact, speed, 0.0), side="right"), 0
        )

    def counts(self) -> np.ndarray:
        """int [B] the kept failures in each bin."""
        return np.bincount(self.bin_of(), minlength=len(self.edges) + 2)

    def shares(self) -> np.ndarray:
        """float64 [B] each bin's share of the kept failures' p (adding up to 1 where K > 0), summed in log space."""
        b, own = self.bin_of(), self.own_log_share()
        out = np.zeros(len(self.edges) + 2)
        for k in np.unique(b).tolist():
            out[k] = math.exp(float(logsumexp(own[b == k])))
        return out

    def median_min_distance(self) -> float:
        """The share-weighted median of the kept failures' min distances (metres): the smallest one whose cumulative
        share (the failures at or below it) reaches 1/2.

        Raises:
            ValueError: no kept failure."""
        if self.n == 0:
            raise ValueError("median_min_distance: no failure's severity is known")
        dist = self.min_distance[self.kept]
        order = np.argsort(dist, kind="stable")
        cum = np.cumsum(np.exp(self.own_log_share()[order]))
        return float(dist[order][min(int(np.searchsorted(cum, 0.5)), self.n - 1)])

    def line(self) -> str:
        """The console's line: each bin's share of p and (its failures), then the share-weighted median min distance:
        ``failures by impact speed, share of p (failures; contact: gap <= 0.7 m): no contact 97.2 % (1,380), 0-2 m/s
        1.9 % (15), 2-5 m/s 0.8 % (6), > 5 m/s 0.1 % (1); median min gap 1.62 m``."""
        s = self.scale
        head = f"failures by impact speed, share of p (failures; contact: {s.label} <= {self.contact:g} {s.unit})"
        if self.n == 0:
            return f"{head}: none of the {self.n_failures:,} failures' rollouts was kept"
        bins = ", ".join(
            f"{label} {share_text(x)} ({c:,})"
            for label, x, c in zip(self.labels(), self.shares(), self.counts(), strict=False)
        )
        kept = (
            ""
            if self.n == self.n_failures
            else f" (the {self.n:,} kept of {self.n_failures:,} failures: {share_text(self.covered)} of p)"
        )
        return f"{head}: {bins}; median min {s.label} {self.median_min_distance():.2f} {s.unit}{kept}"


def failure_severity(
    scale: SeverityScale,
    contact: float,
    log_share: np.ndarray,
    min_distance: np.ndarray,
    impact_speed: np.ndarray,
    kept: np.ndarray | None = None,
    edges: tuple[float, ...] = IMPACT_SPEED_EDGES_MPS,
) -> FailureSeverity:
    """The failures' severity distribution, p(severity | failure), from their shares.

    Args:
        scale: the severity signal.
        contact: its contact level (metres, :func:`contact_level`).
        log_share: float64 [F] each failure's log share of mu_hat (nats, :class:`pemviz.core.population.FailureShares`).
        min_distance: float64 [F] each failure's min distance (metres, :func:`rollout_severity`; read where ``kept``).
        impact_speed: float64 [F] each failure's impact speed (m/s; read where ``kept``).
        kept: bool [F] the failures whose rollout was located (None: all).
        edges: the impact-speed bin edges (m/s, ascending, > 0).
    Returns:
        The distribution, with NaN min distance and impact speed where not kept.
    Raises:
        ValueError: arrays of unequal length, a kept failure without a finite min distance or with an impact speed
            that is not positive, or bad edges."""
    log_share = np.asarray(log_share, dtype=np.float64)
    f = log_share.size
    kept = np.ones(f, dtype=bool) if kept is None else np.asarray(kept, dtype=bool)
    dist, speed = np.asarray(min_distance, dtype=np.float64), np.asarray(impact_speed, dtype=np.float64)
    if not log_share.shape == dist.shape == speed.shape == kept.shape == (f,):
        raise ValueError(
            f"failure_severity: log_share {log_share.shape}, min_distance {dist.shape}, impact_speed "
            f"{speed.shape} and kept {kept.shape} must all be [F]"
        )
    if not np.isfinite(dist[kept]).all():
        raise ValueError("failure_severity: a kept failure has no finite min distance")
    if (speed[kept] <= 0).any() or np.isinf(speed[kept]).any():
        raise ValueError("failure_severity: an impact speed must be a positive number of m/s (NaN: no contact)")
    if not edges or any(e <= 0 for e in edges) or any(b <= a for a, b in zip(edges, edges[1:], strict=False)):
        raise ValueError(f"failure_severity: edges must be positive and ascending, got {edges}")
    return FailureSeverity(
        scale,
        float(contact),
        log_share.copy(),
        np.where(kept, dist, np.nan),
        np.where(kept, speed, np.nan),
        kept.copy(),
        tuple(float(e) for e in edges),
    )
