"""The braking scenario's hooks of the panel (:class:`pemviz.app.drawing.PanelDrawing`), mixed into
:class:`pemviz.scenarios.braking.drawing.BrakingDrawing`: its scene, the explanation of a rollout
(:class:`BrakingExplanation`, by exact replays on the batched twin: a miss is *decisive* when flipping it alone
avoids the failure; Lee et al. 2020, "Adaptive Stress Testing", JAIR 69), its strip charts and captions. Plain data,
no viser (:mod:`pemviz.scenarios.panel_data`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from pemviz.core.proposal_view import prob_detect
from pemviz.scenarios.braking.failures import ControllerTrace, Counterfactual, Severity, story
from pemviz.scenarios.braking.recording import car_positions
from pemviz.scenarios.panel_data import CurveAxis, LaneScene, Series, ViewAxis, Zone

if TYPE_CHECKING:
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.scenarios.braking.simulator import BrakingParams

GAP_BINS_M = np.linspace(0.0, 13.0, 27)
"""Gap bins of the proposal view (:mod:`pemviz.core.proposal_view`): 0.5 m wide, 0 to 13 m."""


@dataclass(frozen=True)
class BrakingExplanation:
    """A braking rollout, step by step, and its counterfactual.

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
        severity: how bad the outcome was (:class:`pemviz.scenarios.braking.failures.Severity`).
        controller: the controller's signals along the rollout (brake command, brake applied, acceleration).
        counterfactual: the minimal miss set, the last saving step and the recovery step.
        sentence: what happened, in plain words (:func:`pemviz.scenarios.braking.failures.describe`)."""

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

    @property
    def contact(self) -> np.ndarray:
        """bool [T]: the cars in contact (gap at most ``contact_gap_m``), where the simulator stops the ego within one
        step: a collision, not the controller's braking."""
        return np.asarray(self.controller.gap_m, dtype=np.float64) <= self.severity.contact_gap_m

    @property
    def minimal_set_outcome(self) -> str:
        """What detections at the minimal miss set give: ``the gap stays at or above 2.13 m``."""
        return f"the gap stays at or above {self.counterfactual.minimal_set_min_gap_m:.2f} m"

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
) -> BrakingExplanation:
    """Explain one braking rollout: its :func:`~pemviz.scenarios.braking.failures.story` (severity, controller,
    counterfactual, sentence) with the probabilities and the importance weight of each step.

    Args:
        gap_m: float64 [T] recorded gap (metres).
        detected: bool [T] the detections taken.
        log_p: float64 [T] log-probability of each action under the PEM (nats).
        log_q: float64 [T] log-probability of each action under the sampler (nats).
        params: the scenario's constants (crash gap, dt; default
            :class:`~pemviz.scenarios.braking.simulator.BrakingParams`).
    Raises:
        ValueError: ``gap_m`` and ``detected`` not of one shape [T], or longer than the scenario."""
    from pemviz.scenarios.braking.simulator import BrakingParams

    p = params or BrakingParams()
    detected = np.asarray(detected, bool)
    gap = np.asarray(gap_m, dtype=np.float64)
    told = story(gap, detected, p)
    cf = told.counterfactual
    crashed = bool(np.min(gap) < p.crash_gap_m)
    decisive = cf.decisive if (crashed and told.replay_matches) else np.zeros(0, int)
    lp, lq = np.asarray(log_p, dtype=np.float64), np.asarray(log_q, dtype=np.float64)
    return BrakingExplanation(
        time_s=np.arange(detected.size) * p.dt_s,
        p_detect=prob_detect(lp, detected),
        q_detect=prob_detect(lq, detected),
        cum_log_weight=np.cumsum(lp - lq),
        misses=cf.misses,
        decisive=decisive,
        flipped_min_gap_m=cf.flipped_min_gap_m,
        crashed=crashed,
        replay_matches=told.replay_matches,
        severity=told.severity,
        controller=told.controller,
        counterfactual=cf,
        sentence=told.sentence,
    )


def _column(batch: RolloutBatch, i: int, name: str, fallback: int | None = None) -> np.ndarray:
    """float64 [T] the column ``name`` of rollout ``i`` (else column ``fallback``, else NaN)."""
    names = tuple(batch.observation_names)
    obs = batch.observations[i]
    if name in names:
        return np.array(obs[:, names.index(name)], dtype=np.float64)
    return np.array(obs[:, fallback], dtype=np.float64) if fallback is not None else np.full(obs.shape[0], np.nan)


class BrakingPanel:
    """What the panel draws of a braking rollout (the ``params`` attribute is the drawing object's): a
    :class:`~pemviz.scenarios.panel_data.LaneScene`, the lead being the object ahead."""

    params: BrakingParams

    @property
    def n_steps(self) -> int:
        """T, the steps of a rollout."""
        return int(self.params.n_steps)

    def panel_scene(self) -> LaneScene:
        """The scene's constants: the cars' boxes, the camera, the braking distance and the crash margin."""
        p = self.params
        zones = (
            Zone(
                "brake_zone_10m",
                p.braking_distance_m,
                "window",
                f"brakes if the lead is\ndetected within {p.braking_distance_m:g} m",
            ),
            Zone("crash_zone_2m", p.crash_gap_m, "margin", f"the {p.crash_gap_m:g} m crash margin"),
        )
        return LaneScene(
            p.ego_length_m,
            p.lead_length_m,
            p.vehicle_width_m,
            p.camera_offset_m,
            p.gap0_m,
            "lead",
            zones,
            "gap",
            f"{p.crash_gap_m:g} m line crossed",
            int(p.n_steps),
            "gap and speeds",
        )

    def proposal_axis(self) -> ViewAxis:
        """The proposal view's bins: the gap to the lead, 0.5 m wide (:data:`GAP_BINS_M`)."""
        return ViewAxis("gap d (m), 0.5 m bins", "the lead", "gap_m", "below", GAP_BINS_M, "gap (m)")

    def curve_axis(self) -> CurveAxis:
        """The reference-state curves' x axis: the gap to the lead."""
        return CurveAxis("gap (m)", "gap d (m)", "p(detect | d)")

    def group_heading(self) -> tuple[str, str]:
        """The rollouts table's group column: its heading, and the start of each group's label that it says."""
        return "last saving detection", "last saving detection at "

    def lane_positions(self, batch: RolloutBatch, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rollout ``i`` of ``batch`` on the road, float64 [T] each (metres): the ego's centre (0 at the start), the
        lead's centre (:func:`pemviz.scenarios.braking.recording.car_positions`, as the recording places them) and the
        gap (the ruler's length)."""
        gap = _column(batch, i, "gap_m", 0)
        ego_x, lead_x = car_positions(gap, _column(batch, i, "ego_speed_mps"), self.params)
        return ego_x, lead_x, gap

    def lane_explanation(self, batch: RolloutBatch, i: int) -> BrakingExplanation:
        """Rollout ``i`` of ``batch`` explained (:func:`explain`)."""
        return explain(
            _column(batch, i, "gap_m", 0), batch.detected[i, :, 0], batch.log_p[i], batch.log_q[i], self.params
        )

    def strip_series(self, batch: RolloutBatch, i: int) -> tuple[Series, ...]:
        """The strip chart's lines of rollout ``i``: the gap, the ego's and the lead's speeds."""
        return (
            Series("gap (m)", _column(batch, i, "gap_m", 0), "main"),
            Series("ego speed (m/s)", _column(batch, i, "ego_speed_mps"), "ego"),
            Series("lead speed (m/s)", _column(batch, i, "lead_speed_mps"), "object"),
        )

    def step_caption(self, batch: RolloutBatch, i: int, ex: BrakingExplanation, t: int) -> tuple[str, str]:
        """The scene's caption at step ``t`` of rollout ``i``, before and after the detector's state: the gap and the
        speeds; the brake and the acceleration."""
        c = ex.controller
        brake = "applied" if c.brake_applied[t] else ("commanded" if c.brake_command[t] else "off")
        before = (
            f"gap {_column(batch, i, 'gap_m', 0)[t]:.2f} m · ego {_column(batch, i, 'ego_speed_mps')[t]:.2f} "
            f"m/s · lead {_column(batch, i, 'lead_speed_mps')[t]:.2f} m/s"
        )
        return before, f"brake {brake} · acceleration {c.accel_mps2[t]:+.2f} m/s^2"
