"""The braking scenario's hooks of the recording (:class:`pemviz.sinks.drawing.RecordingDrawing`), mixed into
:class:`pemviz.scenarios.braking.drawing.BrakingDrawing`: the description, each rollout's severity
(:func:`pemviz.scenarios.braking.failures.severity`), a rollout as a lane of two cars, and the most likely failure's
story (:func:`pemviz.scenarios.braking.failures.story`). Plain data, no rerun."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from pemviz.scenarios.braking.simulator import BrakingParams

if TYPE_CHECKING:
    from pemviz.core.rollouts import RolloutBatch
    from pemviz.scenarios.braking.failures import Severity


def car_positions(
    gap_m: np.ndarray, ego_speed_mps: np.ndarray, params: BrakingParams | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Centre x of the ego and of the lead at every step, float64 [T] each (metres; ego starts at 0): the ego by
    explicit Euler on its recorded speed (NaN counts as 0), the lead at ``ego + camera_offset_m + gap_m +
    lead_length_m / 2``.

    Args:
        gap_m: float64 [T] gaps (metres).
        ego_speed_mps: float64 [T] ego speeds (m/s).
        params: the scenario's constants (default :class:`~pemviz.scenarios.braking.simulator.BrakingParams`)."""
    p = params or BrakingParams()
    v = np.nan_to_num(np.asarray(ego_speed_mps, dtype=np.float64), nan=0.0)
    ego_x = p.dt_s * np.concatenate([[0.0], np.cumsum(v[:-1])])
    lead_x = ego_x + p.camera_offset_m + gap_m + p.lead_length_m / 2
    return ego_x, lead_x


def _counterfactual_story(
    cf: Any,
    gap: np.ndarray,
    detected: np.ndarray,
    misses: np.ndarray,
    p: BrakingParams,
    lines: list[str],
    series: list[tuple],
    markers: list[tuple],
) -> None:
    """The minimal miss set and the last saving step of a failure whose replay reproduces it
    (:class:`pemviz.scenarios.braking.failures.Counterfactual`): their summary lines, their replays' gaps (metres)
    and their markers, appended to ``lines``, ``series`` and ``markers``."""
    from pemviz.scenarios.braking.failures import replay_with_detections

    dt, last = p.dt_s, cf.last_saving_step
    ms = cf.minimal_set
    if ms.size:
        smallest = "the smallest such set" if cf.smallest else "none of them can be left out"
        lines += [
            f"**Minimal miss set** ({ms.size} of {misses.size} misses, {smallest}): "
            f"step{'s' * (ms.size > 1)} {_steps_text(ms, dt)}; detected, the min gap is "
            f"{cf.minimal_set_min_gap_m:.2f} m.",
            "",
        ]
        replay = replay_with_detections(detected, ms, p)
        series.append(
            (
                "gap_m/with_minimal_set",
                f"minimal miss set detected: min gap " f"{replay.gap_m.min():.2f} m",
                "detected",
                replay.gap_m,
            )
        )
        markers.append(("gap_m/minimal_set", "minimal miss set", "failure", "diamond", ms, gap[ms], 6.0))
        markers.append(("detect/minimal_set", "minimal miss set", "failure", "diamond", ms, None, 6.0))
    else:
        lines += ["**Minimal miss set**: none; even a detection at every miss does not avoid the failure.", ""]
    if last is not None:
        lines += [
            f"**Last saving step**: {last} ({last * dt:.2f} s): one detection there still avoids the "
            f"failure ({cf.decisive.size} of the {misses.size} misses would each do alone).",
            "",
        ]
        replay = replay_with_detections(detected, np.array([last]), p)
        series.append(
            (
                "gap_m/with_last_saving",
                f"detected at {last * dt:.2f} s: min gap " f"{replay.gap_m.min():.2f} m",
                "replay",
                replay.gap_m,
            )
        )
        markers.append(("detect/last_saving", "last saving step", "detected", "up", np.array([last]), None, 7.0))
    else:
        lines += ["**Last saving step**: none; no single detection avoids the failure.", ""]


def _steps_text(steps: np.ndarray, dt: float | None, most: int = 12) -> str:
    """``3 (0.15 s), 7 (0.35 s)``: the first ``most`` steps with their times, and how many more."""
    shown = ", ".join(f"{t}" + (f" ({t * dt:.2f} s)" if dt else "") for t in steps[:most])
    return shown + (f" and {steps.size - most} more" if steps.size > most else "")


class BrakingRecording:
    """What the recording draws of a braking rollout (the ``params`` attribute is the drawing object's).

    Attributes:
        draws_scene: True: each stage's least robust rollouts are lanes of a scene seen from above.
        object_words: ``the lead``."""

    params: BrakingParams
    outcome: Callable[[RolloutBatch, int], Severity]  # the drawing object's (BrakingDrawing.outcome)
    draws_scene = True
    object_words = "the lead"

    def intro(self, formula: str, metric: str, method: str) -> tuple[str, str]:
        """(title and paragraph on the scene, what the scene adds to how to read the recording), in Markdown: the
        braking distance and the crash gap (metres) of :attr:`params`."""
        p = self.params
        head = (
            f"# pemviz: crash probability of the braking scenario\n\n"
            f"A car follows a lead that brakes for a red light; the ego brakes only when its detector, "
            f"a perception error model (PEM) p(detect | d), sees the lead within {p.braking_distance_m:g} m. A crash "
            f"is the gap d dropping below {p.crash_gap_m:g} m, safety spec `{formula}`; rollouts are ranked "
            f"by **{metric}** robustness. Method: {method}"
        )
        tail = (
            f" and the *scene* (ego green = detected, orange = missed). Every failing rollout says "
            f"whether it made contact or only breached the {p.crash_gap_m:g} m margin."
        )
        return head, tail

    def outcome_values(self, batch: RolloutBatch, i: int) -> dict[str, Any] | None:
        """Rollout ``i``'s :class:`~pemviz.scenarios.braking.failures.Severity`: ``outcome`` (its words),
        ``min_gap_m`` (metres), ``breach_closing_mps``, ``contact``, ``contact_speed_mps`` (m/s; NaN: none); None
        without a ``gap_m`` column."""
        if "gap_m" not in batch.observation_names:
            return None
        sev = self.outcome(batch, i)
        fields = ("min_gap_m", "breach_closing_mps", "contact", "contact_speed_mps")
        return {"outcome": sev.short, **{name: getattr(sev, name) for name in fields}}

    def contacts(self, batch: RolloutBatch, rows: np.ndarray) -> np.ndarray | None:
        """Whether each of the rollouts ``rows`` (int [k]) made contact, bool [k]: the ``contact`` of
        :meth:`outcome_values` for all of them at once (the gap, in float64 metres, at or below ``contact_gap_m`` at
        some step: :func:`~pemviz.scenarios.braking.failures.severity`); None without a ``gap_m`` column."""
        if "gap_m" not in batch.observation_names:
            return None
        gap = np.asarray(batch.signal("gap_m")[np.asarray(rows)], dtype=np.float64)
        return np.any(gap <= self.params.contact_gap_m, axis=1)

    def scene_lane(self, batch: RolloutBatch, i: int) -> tuple | None:
        """Rollout ``i`` as a lane: the ego (green while it detects the lead, orange while it misses) and the lead
        (red once the gap is below the crash gap), boxes of the true car sizes centred where
        :func:`pemviz.scenarios.braking.drawing.car_positions` puts them (metres along the road), the sight line
        from the camera to the lead's rear; None without ``gap_m`` and ``ego_speed_mps`` columns."""
        if not {"gap_m", "ego_speed_mps"} <= set(batch.observation_names):
            return None
        p = self.params
        gap = batch.signal("gap_m")[i]
        ego_x, lead_x = car_positions(gap, batch.signal("ego_speed_mps")[i], p)
        camera_x = ego_x + p.camera_offset_m
        boxes = (
            ("ego", ego_x, (p.ego_length_m / 2, p.vehicle_width_m / 2), None),
            ("lead", lead_x, (p.lead_length_m / 2, p.vehicle_width_m / 2), gap < p.crash_gap_m),
        )
        return boxes, (camera_x, camera_x + gap), float(lead_x.max() + p.lead_length_m)

    def explanation(self, batch: RolloutBatch, i: int) -> dict[str, Any] | None:
        """The failing rollout ``i``'s story (:func:`pemviz.scenarios.braking.failures.story`): its severity, the
        step it crosses the crash gap and, where the replay reproduces it, the minimal miss set and the last saving
        step with their replays (gap, metres), the controller's acceleration (m/s^2) and brakes, the speeds (m/s);
        None without a ``gap_m`` column."""
        from pemviz.scenarios.braking.failures import story

        if "gap_m" not in batch.observation_names:
            return None
        p = self.params
        gap = batch.signal("gap_m")[i]
        detected = np.asarray(batch.detected[i, :, 0], dtype=bool)
        misses = np.flatnonzero(~detected)
        tale = story(gap, detected, p)
        sev, cf, ctrl = tale.severity, tale.counterfactual, tale.controller
        dt = p.dt_s
        breach = sev.breach_step
        props: dict[str, Any] = dict(
            outcome=sev.short,
            min_gap_m=sev.min_gap_m,
            breach_step=-1 if breach is None else breach,
            breach_time_s=math.nan if breach is None else breach * dt,
            breach_closing_mps=sev.breach_closing_mps,
            contact=sev.contact,
            contact_speed_mps=sev.contact_speed_mps,
            replay_matches=tale.replay_matches,
        )
        lines: list[str] = []
        series: list[tuple] = []
        markers: list[tuple] = []
        if breach is not None:
            markers.append(
                (
                    "gap_m/breach",
                    f"{p.crash_gap_m:g} m margin crossed",
                    "failure",
                    "down",
                    np.array([breach]),
                    gap[[breach]],
                    7.0,
                )
            )
        if tale.replay_matches:
            last = cf.last_saving_step
            props.update(
                minimal_miss_set=cf.minimal_set,
                minimal_set_is_smallest=cf.smallest,
                minimal_set_min_gap_m=cf.minimal_set_min_gap_m,
                last_saving_step=-1 if last is None else last,
                decisive_misses=cf.decisive,
                recovery_step=-1 if cf.recovery_step is None else cf.recovery_step,
            )
            _counterfactual_story(cf, gap, detected, misses, p, lines, series, markers)
            a = ctrl.accel_mps2
            top = max(4.0, float(np.max(a)) + 1.0)
            row = 0.07 * (top - min(-4.0, float(np.min(a)) - 1.0))
            series.append(("controller/acceleration", "acceleration (m/s^2)", "ego_speed", a))
            for key, name, mask, height, role in (
                ("brake_commanded", "brake commanded", ctrl.brake_command, top + 2 * row, "window"),
                ("brake_applied", "brake applied", ctrl.brake_applied, top + row, "failure"),
            ):
                steps = np.flatnonzero(mask)
                markers.append((f"controller/{key}", name, role, "circle", steps, np.full(steps.size, height), 3.0))
            series.append(("speed/ego", "ego speed (m/s)", "ego_speed", ctrl.ego_speed_mps))
            series.append(("speed/lead", "lead speed (m/s)", "object_speed", ctrl.lead_speed_mps))
        lines += [tale.sentence, ""]
        return {"words": sev.short, "props": props, "lines": lines, "series": tuple(series), "markers": tuple(markers)}
