"""Explain a failure: what happened at each step of a rollout, what the controller did and which misses decided it.

For one rollout (:class:`pemviz.app.runs.Trajectory`): per step the PEM's p(detect) and the proposal's
q(detect) of the state it was in, the detection taken and the cumulative importance log-weight; the
controller's signals, the severity of the outcome and the counterfactuals of
:mod:`pemviz.scenarios.braking_failures`, all replayed on the deterministic batched twin of the simulator
(:func:`pemviz.scenarios.batched.replay`, the same arithmetic as highway-env). A miss is *decisive* when flipping
it alone avoids the failure (the gap stays at or above 2 m). This is the "most likely failure and its causes"
report of adaptive stress testing (Lee et al. 2020, "Adaptive Stress Testing: Finding Likely Failure Events with
Reinforcement Learning", JAIR 69).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pemviz.core.proposal_view import prob_detect
from pemviz.scenarios.braking import BrakingParams
from pemviz.scenarios.braking_failures import (
    ControllerTrace,
    Counterfactual,
    Severity,
    controller_trace,
    counterfactual,
    describe,
    severity,
)

__all__ = ["Explanation", "explain", "prob_detect"]


@dataclass(frozen=True)
class Explanation:
    """A rollout, step by step, and its counterfactual.

    Attributes:
        time_s: float64 [T] time of each step (seconds).
        p_detect: float64 [T] p_PEM(detect | state) at each step.
        q_detect: float64 [T] q(detect | state) of the detector that sampled it.
        cum_log_weight: float64 [T] sum over steps <= t of log p(a) - log q(a) (nats).
        misses: int [M] steps where the detector missed.
        decisive: int [D] the misses whose flip to a detection avoids the failure (empty for a safe rollout).
        flipped_min_gap_m: float64 [M] the smallest gap of the replay with that miss flipped (metres).
        crashed: the rollout's gap dropped below ``crash_gap_m``.
        replay_matches: the replay without flips reproduces the recorded gap (the counterfactual is valid).
        severity: how bad the outcome was (:class:`pemviz.scenarios.braking_failures.Severity`).
        controller: the controller's signals along the rollout (brake command, brake applied, acceleration).
        counterfactual: the minimal miss set, the last saving step and the recovery step.
        sentence: what happened, in plain words (:func:`pemviz.scenarios.braking_failures.describe`).
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
    severity: Severity
    controller: ControllerTrace
    counterfactual: Counterfactual
    sentence: str

    def summary(self) -> str:
        """One line for the panel: the decisive misses or the minimal miss set, or why there are none."""
        if not self.crashed:
            return "no failure: nothing to explain (the gap stayed at or above 2 m)"
        if not self.replay_matches:
            return "the replay does not reproduce this rollout: no counterfactual"
        cf = self.counterfactual
        if self.decisive.size == 0:
            if cf.minimal_set.size == 0:
                return f"even a detection at each of the {self.misses.size} misses does not avoid the failure"
            size = "smallest" if cf.smallest else "minimal"
            return (
                f"no single miss decides the failure; a {size} set of {cf.minimal_set.size} misses does (steps "
                f"{', '.join(str(t) for t in cf.minimal_set[:12])}{' ...' if cf.minimal_set.size > 12 else ''}): "
                "detections at all of them avoid it, leaving any one out does not"
            )
        times = ", ".join(f"{self.time_s[t]:.2f}" for t in self.decisive[:10])
        more = f" and {self.decisive.size - 10} more" if self.decisive.size > 10 else ""
        return (
            f"{self.decisive.size} of the {self.misses.size} misses are decisive, at {times} s{more} (steps "
            f"{self.decisive[0]} to {self.decisive[-1]}): a detection at any one of them avoids the failure"
        )


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
    ctrl = controller_trace(detected, p)
    matches = bool(np.allclose(ctrl.gap_m, gap, rtol=0.0, atol=1e-9))
    crashed = bool(np.min(gap) < p.crash_gap_m)
    cf = counterfactual(detected, p)
    sev = severity(gap, p)
    decisive = cf.decisive if (crashed and matches) else np.zeros(0, int)
    sentence = describe(detected, sev, ctrl, cf, p) if matches else (
        sev.phrase[0].upper() + sev.phrase[1:] + ". The replay does not reproduce this rollout: no counterfactual."
    )
    lp, lq = np.asarray(log_p, dtype=np.float64), np.asarray(log_q, dtype=np.float64)
    return Explanation(
        time_s=np.arange(detected.size) * p.dt_s,
        p_detect=prob_detect(lp, detected),
        q_detect=prob_detect(lq, detected),
        cum_log_weight=np.cumsum(lp - lq),
        misses=cf.misses,
        decisive=decisive,
        flipped_min_gap_m=cf.flipped_min_gap_m,
        crashed=crashed,
        replay_matches=matches,
        severity=sev,
        controller=ctrl,
        counterfactual=cf,
        sentence=sentence,
    )
