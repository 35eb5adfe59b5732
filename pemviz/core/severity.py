"""Severity: how deep the failures go, as an exceedance curve P(failure and min_t s_t < x) over levels x of a signal.

A failure of ``G(d >= 2)`` mixes grazes of the 2 m margin with contact. The exceedance curve splits them: for a
signal s (the braking gap, metres) and levels x from the spec's margin down to contact (x = 0), the probability that
a rollout fails and its signal drops below x: the exceedance curve that severity and fragility analyses read.

Each point is estimated from the same importance-weighted rollouts as the failure probability: with E_x the event
and tau_x the step at which it is decided (the later of the failure step and the first step with s < x),
mu_hat_x = (1/N) sum_i 1[E_x,i] w_i(tau_x,i), where w_i(k) = prod_{t < k} p / q is the weight of the rollout's first k
actions. Optional stopping at tau_x keeps each term unbiased: the actions after tau_x do not change E_x, and their
likelihood ratio has mean 1 under q (Innes & Ramamoorthy 2022, eq. 6, with the failure step replaced by tau_x).

The core knows no scenario: a problem states its scale (:class:`SeverityScale`) and the engine fills a
:class:`SeverityCurve`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pemviz.core.estimate import Estimate, error_text, format_probability


@dataclass(frozen=True)
class SeverityScale:
    """Which signal measures a failure's severity and at which levels the curve is estimated.

    Attributes:
        signal: the STL signal name (e.g. ``d``, the braking gap).
        label: what the signal is, for people (``gap``, ``clearance``).
        unit: its unit (``m``).
        levels: the levels x below the failure itself, descending (metres for a distance); the event at x is
            "failure and min_t s_t < x".
        margin: the level at which the spec itself fails on this signal (the braking scenario's crash gap, 2 m), or
            None where the failure is not a level of this signal (the cut-in fails on its safe distance).
        contact: the level of contact (0: the cars touch).
        target_flag: the ``pemviz run`` flag that makes a level the failure itself (``margin``: a run that targets
            it), or None.
    """

    signal: str
    label: str
    unit: str
    levels: tuple[float, ...]
    margin: float | None = None
    contact: float = 0.0
    target_flag: str | None = None

    def __post_init__(self) -> None:
        if any(b >= a for a, b in zip(self.levels, self.levels[1:])):
            raise ValueError(f"severity levels must be strictly descending, got {self.levels}")

    def level_text(self, x: float) -> str:
        """``x = 1 m``, with ``(contact)`` where x is the contact level."""
        tail = " (contact)" if x <= self.contact else ""
        return f"{self.label} < {x:g} {self.unit}{tail}".replace("  ", " ")


def level_events(signal: np.ndarray, failed: np.ndarray, fail_step: np.ndarray,
                 levels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
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
        ValueError: shapes that do not match.
    """
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
        exact_log_p: the exact log probability (nats) where it is known, else None.
    """

    level: float | None
    estimate: Estimate
    exact_log_p: float | None = None

    @property
    def reached(self) -> bool:
        """True when the run's rollouts reach the level often enough to trust the point (a ``reliable`` verdict)."""
        return self.estimate.verdict == "reliable"


@dataclass(frozen=True)
class SeverityCurve:
    """The exceedance curve of a run: the failure itself, then each level of the scale (:class:`SeverityScale`).

    Attributes:
        scale: the signal and its levels.
        points: the failure first (``level`` None, or the scale's margin), then one per level, descending.
    """

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
        return self.scale.level_text(point.level)

    def title(self) -> str:
        """``severity: P(min gap < x), from the same rollouts`` (with "failure and" where the failure is not a level)."""
        s = self.scale
        event = f"min {s.label} < x" if s.margin is not None else f"failure and min {s.label} < x"
        return f"severity: P({event}), from the same rollouts"

    def rows(self) -> list[tuple[str, str]]:
        """(the point's level in words, what the run says of it) for each point: the estimate, its interval, ESS,
        verdict and the exact answer where known; a level the run does not reach reliably says so, and how to reach
        it (the scale's ``target_flag``, or more rollouts)."""
        s = self.scale
        out = []
        for point in self.points:
            e = point.estimate
            if point is not self.points[0] and not point.reached:
                how = (f"pemviz run --{s.target_flag} {point.level:g} targets it" if s.target_flag
                       else "more rollouts (a larger budget, or --rel-error)")
                ess = "" if e.n_failures == 0 else f", ESS {e.ess:.1f}, {e.verdict}"
                out.append((self.point_text(point), f"not reached by this run ({e.n_failures} of {e.n:,} rollouts{ess}): {how}"))
                continue
            text = f"{format_probability(e.log_mu_hat)} {e.interval_text()}  ESS {e.ess:.1f}  {e.verdict}"
            if point.exact_log_p is not None:
                inside = "inside" if e.covers(point.exact_log_p) else "OUTSIDE"
                text += (f"; exact {format_probability(point.exact_log_p)} "
                         f"({error_text(e.log_mu_hat, point.exact_log_p)}, {inside})")
            out.append((self.point_text(point), text))
        return out

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
