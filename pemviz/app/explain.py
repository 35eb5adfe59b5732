"""Explain a failure: what happened at each step of a rollout and which misses decided the crash.

For one rollout (:class:`pemviz.app.runs.Trajectory`): per step the PEM's p(detect) and the proposal's
q(detect) of the state it was in, the detection taken and the cumulative importance log-weight; and a
counterfactual: the rollout replayed with each miss flipped to a detection on the deterministic batched
twin of the simulator (:func:`pemviz.scenarios.batched.replay`, the same arithmetic as highway-env). A
miss is *decisive* when flipping it alone avoids the crash (the gap stays at or above 2 m). This is the
"most likely failure and its causes" report of adaptive stress testing (Lee et al. 2020, "Adaptive
Stress Testing: Finding Likely Failure Events with Reinforcement Learning", JAIR 69).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pemviz.scenarios.batched import replay
from pemviz.scenarios.braking import BrakingParams


@dataclass(frozen=True)
class Explanation:
    """A rollout, step by step, and its counterfactual.

    Attributes:
        time_s: float64 [T] time of each step (seconds).
        p_detect: float64 [T] p_PEM(detect | state) at each step.
        q_detect: float64 [T] q(detect | state) of the detector that sampled it.
        cum_log_weight: float64 [T] sum over steps <= t of log p(a) - log q(a) (nats).
        misses: int [M] steps where the detector missed.
        decisive: int [D] the misses whose flip to a detection avoids the crash (empty for a safe rollout).
        flipped_min_gap_m: float64 [M] the smallest gap of the replay with that miss flipped (metres).
        crashed: the rollout's gap dropped below ``crash_gap_m``.
        replay_matches: the replay without flips reproduces the recorded gap (the counterfactual is valid).
    """

    time_s: np.ndarray
    p_detect: np.ndarray
    q_detect: np.ndarray
    cum_log_weight: np.ndarray
    misses: np.ndarray
    decisive: np.ndarray
    flipped_min_gap_m: np.ndarray
    crashed: bool
    replay_matches: bool

    def summary(self) -> str:
        """One line for the panel: the decisive misses, or why there are none."""
        if not self.crashed:
            return "no crash: nothing to explain (the gap stayed at or above 2 m)"
        if not self.replay_matches:
            return "the replay does not reproduce this rollout: no counterfactual"
        if self.decisive.size == 0:
            return (
                f"no single miss decides the crash: flipping any one of the {self.misses.size} misses alone still "
                "crashes (several misses together cause it)"
            )
        steps = ", ".join(f"{t} ({self.time_s[t]:.2f} s)" for t in self.decisive[:8])
        more = f" and {self.decisive.size - 8} more" if self.decisive.size > 8 else ""
        return (
            f"decisive misses at steps {steps}{more}: a detection at any one of them avoids the crash "
            f"({self.decisive.size} of {self.misses.size} misses)"
        )


def prob_detect(log_p_action: np.ndarray, detected: np.ndarray) -> np.ndarray:
    """p(detect) from the log-probability of the action taken, float64 [T]: exp(log p) if detected, else
    1 - exp(log p) (``-expm1``, exact for small probabilities)."""
    lp = np.asarray(log_p_action, dtype=np.float64)
    return np.where(np.asarray(detected, bool), np.exp(lp), -np.expm1(lp))


def explain(
    gap_m: np.ndarray,
    detected: np.ndarray,
    log_p: np.ndarray,
    log_q: np.ndarray,
    params: BrakingParams | None = None,
) -> Explanation:
    """Explain one braking rollout.

    Args:
        gap_m: float64 [T] recorded gap (metres).
        detected: bool [T] the detections taken.
        log_p, log_q: float64 [T] log-probability of each action under the PEM and the sampler (nats).
        params: the scenario's constants (crash gap, dt).
    """
    p = params or BrakingParams()
    detected = np.asarray(detected, bool)
    gap = np.asarray(gap_m, dtype=np.float64)
    t = detected.size
    misses = np.flatnonzero(~detected)
    crashed = bool(np.min(gap) < p.crash_gap_m)
    rows = np.repeat(detected[None, :], misses.size + 1, axis=0)
    rows[np.arange(1, misses.size + 1), misses] = True
    gaps = replay(p, rows)[:, :, 0]
    matches = bool(np.allclose(gaps[0], gap, rtol=0.0, atol=1e-9))
    flipped_min = gaps[1:].min(axis=1) if misses.size else np.zeros(0)
    decisive = misses[flipped_min >= p.crash_gap_m] if (crashed and matches) else np.zeros(0, int)
    lp, lq = np.asarray(log_p, dtype=np.float64), np.asarray(log_q, dtype=np.float64)
    return Explanation(
        time_s=np.arange(t) * p.dt_s,
        p_detect=prob_detect(lp, detected),
        q_detect=prob_detect(lq, detected),
        cum_log_weight=np.cumsum(lp - lq),
        misses=misses,
        decisive=decisive,
        flipped_min_gap_m=flipped_min,
        crashed=crashed,
        replay_matches=matches,
    )
