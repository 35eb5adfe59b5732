"""What happened in one cut-in rollout, in words, and how bad it was: pure functions of the rollout's scene signals
(:data:`pemviz.scenarios.cut_in.scenario.OBSERVATION_NAMES`) and object rows
(:data:`pemviz.scenarios.cut_in.scenario.OBJECT_NAMES`).

The story follows the cut-in car (object 0): its lane change, its entry into the ego's lane, its first detection and
misses, its confirmed track and where it lay, when the ACC followed it and braked, and the outcome
(:data:`pemviz.scenarios.cut_in.scenario.FAILURE_FORMULA`, Maierhofer et al. 2020) with its severity: the smallest
clearance (metres) and, at contact, the closing speed (m/s). The rows' ``followed`` and ``ego_accel_mps2`` at step t
are the ACC's decision at step t - 1: :class:`AccTrace` shifts them back.

Units: metres, seconds, m/s, m/s^2."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pemviz.scenarios.cut_in.scenario import LANE_WIDTH_M, NO_VEHICLE_M

CUT_IN_OBJECT = 0
"""The cut-in car's object index (the first of :attr:`pemviz.scenarios.cut_in.scenario.CutInParams.vehicles`)."""


def car_labels(n_objects: int) -> tuple[str, ...]:
    """What the console, the panel and the recording call the cut-in's M cars: ``car 0`` (the cut-in car, object
    :data:`CUT_IN_OBJECT`) to ``car M-1``."""
    return tuple(f"car {m}" for m in range(n_objects))


BRAKING_MPS2 = -0.5
"""An ACC acceleration at or below this (m/s^2) counts as braking in the story (the IDM's free-road term is 0 at the
set speed; a car followed far ahead costs a few tenths)."""

OBSERVATION_COLUMNS = (
    "safe_margin_m",
    "cut_in_recent",
    "clearance_m",
    "ego_accel_mps2",
    "front_index",
    "followed_index",
)
"""The scene signals the story reads."""
OBJECT_COLUMNS = (
    "gap_m",
    "rel_speed_mps",
    "lateral_speed_mps",
    "in_ego_lane",
    "tracked",
    "track_err_y_m",
    "followed",
    "loc_x",
)
"""The object-row columns the story reads."""


def has_story_columns(observation_names: tuple[str, ...], object_names: tuple[str, ...] | None) -> bool:
    """Whether a rollout with these scene signals and object-row columns can be told (:func:`cut_in_story`)."""
    return set(OBSERVATION_COLUMNS) <= set(observation_names) and set(OBJECT_COLUMNS) <= set(object_names or ())


@dataclass(frozen=True)
class AccTrace:
    """The ACC's decision at each step but the last (the rows' ``followed`` and ``ego_accel_mps2`` of the step after).

    Attributes:
        time_s: float64 [T - 1] the time of each decision (seconds).
        accel_mps2: float64 [T - 1] the acceleration it commanded, applied over the next step (m/s^2).
        followed: int [T - 1] the object whose track it followed (IDM on its estimated distance), -1 none."""

    time_s: np.ndarray
    accel_mps2: np.ndarray
    followed: np.ndarray


@dataclass(frozen=True)
class CutInSeverity:
    """How bad a cut-in rollout was.

    Attributes:
        min_clearance_m: the smallest clearance to a vehicle beside the ego's box (metres, bumper to bumper; negative:
            the boxes overlap); :data:`pemviz.scenarios.cut_in.scenario.NO_VEHICLE_M` when no vehicle was ever beside.
        min_clearance_step: the step of that clearance.
        failure_step: the first step the failure formula is violated (None: the rollout held it).
        collision: the failure is a collision (the clearance below 0 at ``failure_step``), else R_G1's safe distance.
        margin_m: R_G1's margin at ``failure_step`` (metres; negative for a safe-distance failure); nan without
            failure.
        contact_step: the first step with a negative clearance (None: no contact).
        closing_speed_mps: at contact, the ego's speed minus that of the vehicle in front over the step that made
            contact (m/s); nan without contact, or without a vehicle in front then (a contact beside the ego).
        dt_s: seconds per step."""

    min_clearance_m: float
    min_clearance_step: int
    failure_step: int | None
    collision: bool
    margin_m: float
    contact_step: int | None
    closing_speed_mps: float
    dt_s: float

    @property
    def failed(self) -> bool:
        return self.failure_step is not None

    @property
    def contact(self) -> bool:
        return self.contact_step is not None

    @property
    def clearance_text(self) -> str:
        """``minimum clearance 0.42 m at 3.10 s`` (``-0.66 m ... (the boxes overlap)`` at contact)."""
        if self.min_clearance_m >= NO_VEHICLE_M:
            return "minimum clearance: no vehicle ever beside the ego's box"
        overlap = " (the boxes overlap)" if self.min_clearance_m < 0 else ""
        return (
            f"minimum clearance {self.min_clearance_m:.2f} m at {self.min_clearance_step * self.dt_s:.2f} s"
            f"{overlap}"
        )

    @property
    def short(self) -> str:
        """One line: ``contact at 2.8 m/s closing speed · minimum clearance -0.66 m ...``."""
        if self.contact_step is not None:  # self.contact
            v = self.closing_speed_mps
            speed = f"contact at {v:.1f} m/s closing speed" if math.isfinite(v) else "contact beside the ego"
            head = f"{speed} at {self.contact_step * self.dt_s:.2f} s"
        elif self.failure_step is not None:  # self.failed
            head = (
                f"R_G1's safe distance short by {-self.margin_m:.2f} m at {self.failure_step * self.dt_s:.2f} s, "
                "no contact"
            )
        else:
            head = "no failure, no contact"
        return f"{head} · {self.clearance_text}"

    @property
    def rank(self) -> float:
        """Sort key, larger = worse: the closing speed above 1000 for contacts (1000 beside the ego), else the
        negated smallest clearance (metres)."""
        if self.contact:
            return 1000.0 + (self.closing_speed_mps if math.isfinite(self.closing_speed_mps) else 0.0)
        return -self.min_clearance_m


@dataclass(frozen=True)
class CutInStory:
    """What happened to the cut-in car and the ego, step by step (module docstring); steps are None where the event
    never happened.

    Attributes:
        lane_change_step: the first step car 0 moves across the road.
        lane_entry_step: the first step its box overlaps the ego's lane.
        first_detected_step: the first step the camera detected it.
        misses_after_entry, steps_after_entry: its misses and the steps from its lane entry up to the ACC's first
            decision to follow it (or the failure, or the end).
        track_step: the first step the tracker held a confirmed track of it.
        outside_steps: steps after its lane entry, before the ACC followed it, at which its track lay outside the
            ego's lane.
        worst_track_error_m: the largest lateral error of its track in those steps (metres; nan: none).
        follow_step: the first step the ACC decided to follow it.
        brake_step: the first decision at or below :data:`BRAKING_MPS2` after its lane entry.
        hardest_accel_mps2, hardest_step: the ACC's lowest commanded acceleration (m/s^2) and its step.
        acc: the ACC's decisions (:class:`AccTrace`).
        in_lane: bool [T] car 0's box overlaps the ego's lane at each step.
        severity: :class:`CutInSeverity`.
        sentences: the story in words."""

    lane_change_step: int | None
    lane_entry_step: int | None
    first_detected_step: int | None
    misses_after_entry: int
    steps_after_entry: int
    track_step: int | None
    outside_steps: int
    worst_track_error_m: float
    follow_step: int | None
    brake_step: int | None
    hardest_accel_mps2: float
    hardest_step: int
    acc: AccTrace
    in_lane: np.ndarray
    severity: CutInSeverity
    sentences: tuple[str, ...]

    @property
    def text(self) -> str:
        return " ".join(self.sentences)


def _first(mask: np.ndarray, start: int = 0) -> int | None:
    """The first index >= ``start`` where ``mask`` holds, None if none."""
    hits = np.flatnonzero(np.asarray(mask, bool)[start:])
    return int(hits[0]) + start if hits.size else None


def cut_in_severity(
    observations: np.ndarray,
    observation_names: tuple[str, ...],
    rows: np.ndarray,
    object_names: tuple[str, ...],
    dt_s: float,
) -> CutInSeverity:
    """The :class:`CutInSeverity` of one rollout: its scene signals ``observations`` [T, F] and object rows ``rows``
    [T, M, G] (metres, m/s). The closing speed at contact is minus the row's ``rel_speed_mps`` of the vehicle in front
    at contact, at the step before (whose speeds moved the cars into contact: highway-env moves, then accelerates)."""
    col = {n: np.asarray(observations[:, observation_names.index(n)], dtype=np.float64) for n in OBSERVATION_COLUMNS}
    clearance = col["clearance_m"]
    violated = (col["safe_margin_m"] + 1000.0 * col["cut_in_recent"] < 0.0) | (clearance < 0.0)
    fail = _first(violated)
    contact = _first(clearance < 0.0)
    k = int(np.argmin(clearance))
    closing = math.nan
    if contact is not None:
        front = int(col["front_index"][contact])
        if front >= 0:
            rel = rows[max(contact - 1, 0), front, object_names.index("rel_speed_mps")]
            closing = float(-rel)
    return CutInSeverity(
        min_clearance_m=float(clearance[k]),
        min_clearance_step=k,
        failure_step=fail,
        collision=bool(fail is not None and clearance[fail] < 0.0),
        margin_m=float(col["safe_margin_m"][fail]) if fail is not None else math.nan,
        contact_step=contact,
        closing_speed_mps=closing,
        dt_s=float(dt_s),
    )


def acc_trace(observations: np.ndarray, observation_names: tuple[str, ...], dt_s: float) -> AccTrace:
    """The ACC's decisions (:class:`AccTrace`) of one rollout's scene signals ``observations`` [T, F]."""
    accel = np.asarray(observations[1:, observation_names.index("ego_accel_mps2")], dtype=np.float64)
    followed = np.asarray(observations[1:, observation_names.index("followed_index")]).astype(np.int64)
    return AccTrace(np.arange(accel.size) * float(dt_s), accel, followed)


def cut_in_story(
    observations: np.ndarray,
    observation_names: tuple[str, ...],
    rows: np.ndarray,
    object_names: tuple[str, ...],
    detected: np.ndarray,
    dt_s: float,
    obj: int = CUT_IN_OBJECT,
    name: str = "car 0",
) -> CutInStory:
    """Tell one cut-in rollout (module docstring).

    Args:
        observations: float64 [T, F] its scene signals, named by ``observation_names``.
        observation_names: the F signals' names.
        rows: float64 [T, M, G] its object rows, named by ``object_names``.
        object_names: the G columns' names.
        detected: bool [T, M] the camera's detections.
        dt_s: seconds per step.
        obj: the cut-in car's index among the M objects.
        name: its name in the sentences.
    Raises:
        ValueError: a column the story reads is missing (:func:`has_story_columns`)."""
    if not has_story_columns(tuple(observation_names), tuple(object_names)):
        raise ValueError(
            f"cut_in_story: needs the scene signals {OBSERVATION_COLUMNS} and the object columns " f"{OBJECT_COLUMNS}"
        )
    names = tuple(object_names)
    car = {n: np.asarray(rows[:, obj, names.index(n)], dtype=np.float64) for n in OBJECT_COLUMNS}
    det = np.asarray(detected, bool)[:, obj]
    t_steps = det.size
    sev = cut_in_severity(observations, tuple(observation_names), rows, names, dt_s)
    acc = acc_trace(observations, tuple(observation_names), dt_s)
    at = lambda k: f"{k * dt_s:.2f} s"  # noqa: E731

    change = _first(np.abs(car["lateral_speed_mps"]) > 1e-6)
    entry = _first(car["in_ego_lane"] > 0.5)
    first_det = _first(det)
    track = _first(car["tracked"] > 0.5)
    follow = _first(acc.followed == obj)
    end = t_steps if sev.failure_step is None else sev.failure_step + 1
    stop = follow if follow is not None and (entry is None or follow >= entry) else end
    span = np.arange(entry, max(entry, min(stop, end))) if entry is not None else np.zeros(0, int)
    misses = int((~det[span]).sum())
    est_lateral = car["loc_x"] + car["track_err_y_m"]
    outside = span[(car["tracked"][span] > 0.5) & (np.abs(est_lateral[span]) >= LANE_WIDTH_M / 2)]
    worst = float(np.max(np.abs(car["track_err_y_m"][outside]))) if outside.size else math.nan
    brake = _first(acc.accel_mps2 <= BRAKING_MPS2, entry or 0)
    hardest = int(np.argmin(acc.accel_mps2)) if acc.accel_mps2.size else 0
    lowest = float(acc.accel_mps2[hardest]) if acc.accel_mps2.size else math.nan

    s = []
    if change is None:
        s.append(f"{name.capitalize()} never changed lanes.")
    else:
        slower = -car["rel_speed_mps"][change]
        pace = f"{slower:.1f} m/s slower than the ego" if slower >= 0 else f"{-slower:.1f} m/s faster than the ego"
        s.append(
            f"{name.capitalize()} began to change lanes at {at(change)}, {car['gap_m'][change]:.1f} m ahead and "
            f"{pace}."
        )
    if entry is None:
        s.append("It never entered the ego's lane.")
    else:
        s.append(f"Its box entered the ego's lane at {at(entry)} (step {entry}), {car['gap_m'][entry]:.1f} m ahead.")
    if first_det is None:
        s.append("The camera never detected it.")
    else:
        seen = f"The camera first detected it at {at(first_det)}"
        if span.size:
            until = "the ACC followed it" if stop == follow else ("the failure" if sev.failed else "the end")
            missed = "at none of them" if misses == 0 else f"at {misses} of them"
            seen += f"; of the {span.size} steps from its lane entry until {until}, it was missed {missed}"
        s.append(seen + ".")
    if track is None:
        s.append("The tracker never confirmed a track of it.")
    else:
        where = ""
        if outside.size:
            where = (
                f", but placed it outside the ego's lane at {outside.size} step{'s' * (outside.size != 1)} after "
                f"it entered (lateral error up to {worst:.2f} m), where the ACC follows no track"
            )
        s.append(f"The tracker confirmed a track of it at {at(track)}{where}.")
    if follow is None:
        s.append("The ACC never followed it.")
    else:
        late = (
            f", {(follow - entry) * dt_s:.2f} s after it entered the lane"
            if entry is not None and follow >= entry
            else ""
        )
        s.append(f"The ACC first followed it at {at(follow)}{late}.")
    if brake is None:
        s.append("The ego never braked" + (" after it entered." if entry is not None else "."))
    else:
        s.append(f"The ego braked from {at(brake)}, hardest {lowest:.1f} m/s^2 at {at(hardest)}.")
    if sev.contact:
        speed = (
            f" at a closing speed of {sev.closing_speed_mps:.1f} m/s" if math.isfinite(sev.closing_speed_mps) else ""
        )
        s.append(f"Contact at {at(sev.contact_step)} (step {sev.contact_step}){speed}; {sev.clearance_text}.")
    elif sev.failed:
        s.append(
            f"R_G1's safe distance to the vehicle in front was violated at {at(sev.failure_step)} (step "
            f"{sev.failure_step}) by {-sev.margin_m:.2f} m, outside the rule's waiver after a cut-in, without "
            f"contact; {sev.clearance_text}."
        )
    else:
        s.append(f"No failure: {sev.clearance_text}.")
    return CutInStory(
        change,
        entry,
        first_det,
        misses,
        int(span.size),
        track,
        int(outside.size),
        worst,
        follow,
        brake,
        lowest,
        hardest,
        acc,
        car["in_ego_lane"] > 0.5,
        sev,
        tuple(s),
    )
