"""p under other PEMs from the same rollouts: re-weighting by the likelihood ratio of the detections.

Under another detection PEM p_k only the detection terms of a rollout's weight differ:

    log w_k = log w + sum_{t, m} [log sigma(s_tm l^k_tm) - log sigma(s_tm l_tm)],

over the steps that enter the weight, l the nominal PEM's logit of object m at step t, l^k the other's, s = +1 for a
detection, -1 for a miss (Innes & Ramamoorthy 2022, eq. 6, with the target swapped; Owen, "Monte Carlo theory,
methods and examples", 2013, Ch. 9). An object out of sight adds nothing. Float64 log space throughout; no scenario."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pemviz.core.estimate import Estimate, error_text, format_probability


@dataclass(frozen=True)
class ShiftedDetector:
    """A detector whose every logit is shifted by ``shift`` (nats of log-odds): a camera that detects more often
    (shift > 0) or misses more often (shift < 0) than the PEM says. Logits of -inf (never detected) stay -inf."""

    base: Any
    shift: float

    def detect_logit(self, rows: np.ndarray) -> np.ndarray:
        return np.asarray(self.base.detect_logit(rows), dtype=np.float64) + self.shift


def with_pem(detector: Any, pem: Any) -> Any:
    """The same detector with another detection PEM: a :class:`pemviz.core.detectors.PEMDetector` (field ``pem``) or a
    :class:`pemviz.pem.perception.SalientDetector` (field ``detect``).

    Raises:
        TypeError: a detector with neither field."""
    names = {f.name for f in dataclasses.fields(detector)} if dataclasses.is_dataclass(detector) else set()
    if "pem" in names:
        return dataclasses.replace(detector, pem=pem)
    if "detect" in names:
        return dataclasses.replace(detector, detect=pem)
    raise TypeError(f"cannot swap the PEM of a {type(detector).__name__}")


def detection_log_ratios(
    target: Any, others: Sequence[Any], rows: np.ndarray, detected: np.ndarray, mask: np.ndarray
) -> np.ndarray:
    """sum over the masked steps and every object of log p_k(a | x) - log p(a | x), float64 [K, N] (nats).

    Args:
        target: the nominal detector (``detect_logit(rows [R, G]) -> [R]``).
        others: K detectors.
        rows: object rows, float64 [N, T, M, G].
        detected: bool [N, T, M].
        mask: bool [N, T], the steps that enter the weight."""
    from scipy.special import log_expit

    n, t, m, g = rows.shape
    out = np.zeros((len(others), n))
    if n == 0 or not others:
        return out
    keep = np.repeat(mask[:, :, None], m, axis=2).reshape(-1)
    flat = rows.reshape(-1, g)[keep]
    sign = np.where(detected.reshape(-1)[keep], 1.0, -1.0)
    owner = np.repeat(np.arange(n), t * m)[keep]
    l0 = np.asarray(target.detect_logit(flat), dtype=np.float64)
    base = log_expit(sign * l0)
    for k, other in enumerate(others):
        lk = np.asarray(other.detect_logit(flat), dtype=np.float64)
        with np.errstate(invalid="ignore"):
            term = np.where(np.isneginf(l0) & np.isneginf(lk), 0.0, log_expit(sign * lk) - base)
        out[k] = np.bincount(owner, weights=term, minlength=n)
    return out


@dataclass(frozen=True)
class AlternativeTarget:
    """Another target a problem's rollouts are re-weighted under.

    Attributes:
        kind: ``member`` (of a PEM ensemble) or ``shift`` (the nominal PEM with shifted logits).
        label: how it is named (``member 3``, ``+0.5``).
        detector: the target detector with that PEM (:func:`with_pem`, :class:`ShiftedDetector`).
        exact_log_p: its exact log p (nats) where known, else None."""

    kind: str
    label: str
    detector: Any
    exact_log_p: float | None = None


@dataclass(frozen=True)
class Alternative:
    """One other target the run's rollouts are re-weighted under, and what they say of it.

    Attributes:
        label: ``member 3``, ``shift +0.5``.
        estimate: p under it, with its interval, ESS and verdict (capped as the run's).
        exact_log_p: its exact log p (nats) where known, else None."""

    label: str
    estimate: Estimate
    exact_log_p: float | None = None


@dataclass(frozen=True)
class PemSpread:
    """The failure probability under the PEM's own uncertainty: the nominal estimate, each ensemble member's and each
    shifted PEM's, all from the same rollouts.

    Attributes:
        nominal: the run's estimate; members: one :class:`Alternative` per ensemble member (may be empty);
        shifts: one per logit shift; source: where the members come from (a file name)."""

    nominal: Estimate
    members: tuple[Alternative, ...]
    shifts: tuple[Alternative, ...] = ()
    source: str = ""

    def member_log_p(self) -> np.ndarray:
        """log p of each member's estimate, float64 [K] (nats; -inf with no failure)."""
        return np.array([a.estimate.log_mu_hat for a in self.members], dtype=np.float64)

    def spread(self) -> tuple[float, float, float]:
        """(median, 5th percentile, 95th percentile) of the members' log p (nats)."""
        lp = self.member_log_p()
        return float(np.median(lp)), float(np.percentile(lp, 5)), float(np.percentile(lp, 95))

    def exact_spread(self) -> tuple[float, float, float] | None:
        """The same of the members' exact log p, where every member's is known, else None."""
        ex = [a.exact_log_p for a in self.members]
        if not ex or any(x is None for x in ex):
            return None
        lp = np.array(ex, dtype=np.float64)
        return float(np.median(lp)), float(np.percentile(lp, 5)), float(np.percentile(lp, 95))

    def lines(self) -> list[str]:
        """The console lines: the members' spread, their ESS and verdicts, the members not to trust, the exact
        members where known, and each shift."""
        out = []
        if self.members:
            med, lo, hi = self.spread()
            ess = np.array([a.estimate.ess for a in self.members])
            reliable = [a for a in self.members if a.estimate.verdict == "reliable"]
            out.append(
                f"PEM uncertainty: p under {len(self.members)} bootstrap refits of the PEM ({self.source}), the "
                "same rollouts re-weighted"
            )
            out.append(
                f"  members: median {format_probability(med)}, 90 % of them in [{format_probability(lo)}, "
                f"{format_probability(hi)}] (x{math.exp(hi - lo):.3g} wide); the nominal PEM's "
                f"{format_probability(self.nominal.log_mu_hat)}"
            )
            out.append(
                f"  member ESS: median {np.nanmedian(ess):.1f}, min {np.nanmin(ess):.1f}; {len(reliable)} of "
                f"{len(self.members)} reliable"
            )
            weak = [a for a in self.members if a.estimate.verdict != "reliable"]
            if 0 < len(weak) <= 4:
                out.append(
                    "  not to trust (see their verdicts): "
                    + ", ".join(f"{a.label} (ESS {a.estimate.ess:.1f}, {a.estimate.verdict})" for a in weak)
                )
            elif weak:
                w = np.array([a.estimate.ess for a in weak])
                out.append(
                    f"  not to trust (see their verdicts): {len(weak)} of {len(self.members)} members (ESS "
                    f"{np.nanmin(w):.1f} to {np.nanmax(w):.1f}); the spread above is not a result"
                )
            exact = self.exact_spread()
            if exact is not None:
                emed, elo, ehi = exact
                # every member's exact log p is known (exact_spread)
                known = [(a.estimate, a.exact_log_p) for a in self.members if a.exact_log_p is not None]
                within = sum(abs(e.log_mu_hat - x) <= math.log(1.5) for e, x in known)
                covers = sum(e.covers(x) for e, x in known)
                out.append(
                    f"  exact members: median {format_probability(emed)}, 90 % in [{format_probability(elo)}, "
                    f"{format_probability(ehi)}]; re-weighted within x1.5 of exact: "
                    f"{within}/{len(self.members)}, its interval or lower bound holds it: "
                    f"{covers}/{len(self.members)}"
                )
        for a in self.shifts:
            e = a.estimate
            line = (
                f"PEM shifted by {a.label}: p = {format_probability(e.log_mu_hat)} {e.interval_text()}, ESS "
                f"{e.ess:.1f}: {e.verdict}"
            )
            if a.exact_log_p is not None:
                line += f"; exact {format_probability(a.exact_log_p)} ({error_text(e.log_mu_hat, a.exact_log_p)})"
            out.append(line)
        return out
