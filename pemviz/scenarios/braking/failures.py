"""Why did a braking rollout fail: its severity, the controller's signals, the misses that decide it, in words.

Everything is a function of one rollout's detections on the deterministic batched twin
(:func:`pemviz.scenarios.braking.batched.replay`), so a counterfactual detection is an exact replay: the "most
likely failure and its causes" of adaptive stress testing (Lee et al., "Adaptive Stress Testing", JAIR 69, 2020)
with delta debugging's minimal cause (Zeller & Hildebrandt, "Simplifying and Isolating Failure-Inducing Input", IEEE
TSE 28(2), 2002).

Failure: the gap below ``BrakingParams.crash_gap_m`` (2 m) at some step (Innes & Ramamoorthy 2022). Contact: the gap
at or below ``BrakingParams.contact_gap_m`` (0.7 m), where the scenario stops the ego as CARLA's collision does; a
breach without contact is a near miss. The gap at step ``t`` is the one the detector was asked about. No I/O. Units:
metres, seconds, m/s, m/s^2."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from pemviz.scenarios.braking.batched import BatchedBraking
from pemviz.scenarios.braking.simulator import BrakingParams, ego_acceleration, initial_controller_state

EXACT_MAX_SIZE = 3
"""The minimal miss set is searched exhaustively up to this many misses (then greedily, :func:`minimal_miss_set`)."""

EXACT_MAX_ROWS = 20_000
"""An exhaustive search of one size replays at most this many sets (else it stops at the size before)."""

_CHUNK = 4096
"""Rollouts replayed together (bounds the working memory of a search)."""


# -- severity ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Severity:
    """How bad a rollout's outcome was.

    Attributes:
        min_gap_m: the smallest gap of the rollout (metres).
        min_gap_step: the first step at which it occurs.
        breach_step: the first step with gap < ``crash_gap_m`` (None: no failure).
        breach_closing_mps: closing speed (ego minus lead) over the step into the breach (m/s; nan without one).
        contact_step: the first step with gap <= ``contact_gap_m`` (None: no contact).
        contact_speed_mps: closing speed over the step into contact: the impact speed (m/s; nan without contact).
        crash_gap_m, contact_gap_m: the thresholds used (metres).
        dt_s: the step (seconds)."""

    min_gap_m: float
    min_gap_step: int
    breach_step: int | None
    breach_closing_mps: float
    contact_step: int | None
    contact_speed_mps: float
    crash_gap_m: float
    contact_gap_m: float
    dt_s: float

    @property
    def failed(self) -> bool:
        return self.breach_step is not None

    @property
    def contact(self) -> bool:
        return self.contact_step is not None

    @property
    def short(self) -> str:
        """The words used everywhere for the outcome: ``contact at 3.2 m/s``, ``breach 1.91 m, no contact`` or
        ``safe, min gap 3.41 m``."""
        if self.contact:
            return f"contact at {self.contact_speed_mps:.1f} m/s"
        if self.failed:
            return f"breach {self.min_gap_m:.2f} m, no contact"
        return f"safe, min gap {self.min_gap_m:.2f} m"

    @property
    def phrase(self) -> str:
        """:attr:`short` with when and how fast: ``breach 1.91 m, no contact (the 2 m margin crossed at 2.45 s,
        closing at 1.20 m/s)``."""
        if self.breach_step is None:  # not self.failed
            return f"{self.short} (at {self.min_gap_step * self.dt_s:.2f} s): the {self.crash_gap_m:g} m margin held"
        v = self.breach_closing_mps
        speed = f"{v:.2f} m/s" if math.isfinite(v) else "an unknown speed (breached at the start)"
        crossed = (
            f"the {self.crash_gap_m:g} m margin crossed at {self.breach_step * self.dt_s:.2f} s, closing at {speed}"
        )
        if self.contact_step is not None:  # self.contact
            return f"{self.short} at {self.contact_step * self.dt_s:.2f} s ({crossed})"
        return f"{self.short} ({crossed})"

    @property
    def rank(self) -> float:
        """Sort key, larger = worse: impact speed above 1000 for contacts, else the negated smallest gap."""
        if self.contact:
            return 1000.0 + (self.contact_speed_mps if math.isfinite(self.contact_speed_mps) else 0.0)
        return -self.min_gap_m


def severity(gap_m: np.ndarray, params: BrakingParams | None = None) -> Severity:
    """The severity of a rollout from its gaps alone; the closing speed over the step into a threshold is ``(gap[t-1] -
    gap[t]) / dt``, exactly ego minus lead speed at step ``t - 1`` under highway-env's explicit Euler.

    Args:
        gap_m: float64 [T] the gap at each step (metres).
        params: the scenario's constants (``crash_gap_m``, ``contact_gap_m``, ``dt_s``).
    Raises:
        ValueError: ``gap_m`` not a non-empty 1-D array."""
    p = params or BrakingParams()
    gap = np.asarray(gap_m, dtype=np.float64)
    if gap.ndim != 1 or gap.size == 0:
        raise ValueError(f"severity: gap_m must be float [T >= 1], got shape {gap.shape}")

    def first(mask: np.ndarray) -> tuple[int | None, float]:
        if not mask.any():
            return None, math.nan
        t = int(np.argmax(mask))
        return t, (float(gap[t - 1] - gap[t]) / p.dt_s if t > 0 else math.nan)

    breach, closing = first(gap < p.crash_gap_m)
    contact, impact = first(gap <= p.contact_gap_m)
    i = int(np.argmin(gap))
    return Severity(float(gap[i]), i, breach, closing, contact, impact, p.crash_gap_m, p.contact_gap_m, p.dt_s)


# -- the controller ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class ControllerTrace:
    """The ego controller along a rollout (the CARLA BasicAgent of
    :func:`pemviz.scenarios.braking.simulator.ego_acceleration`).

    Attributes:
        time_s: float64 [T] (seconds).
        gap_m, ego_speed_mps, lead_speed_mps: float64 [T] the scenario's observations (metres, m/s).
        brake_command: bool [T] the emergency brake commanded at step t (the lead detected within
            ``braking_distance_m``); with the actuation lag it acts at step t + 1.
        brake_applied: bool [T] the emergency brake acting at step t (the observation's ``brake_pending``).
        accel_mps2: float64 [T] the ego's acceleration over step t (m/s^2; negative: braking)."""

    time_s: np.ndarray
    gap_m: np.ndarray
    ego_speed_mps: np.ndarray
    lead_speed_mps: np.ndarray
    brake_command: np.ndarray
    brake_applied: np.ndarray
    accel_mps2: np.ndarray


def controller_trace(detected: np.ndarray, params: BrakingParams | None = None) -> ControllerTrace:
    """Replay a detection sequence on the batched twin and record the controller's signals at every step.

    Args:
        detected: bool [T] the detector's output at each step, T <= ``params.n_steps``.
        params: the scenario's constants (None: :class:`~pemviz.scenarios.braking.simulator.BrakingParams`).
    Raises:
        ValueError: ``detected`` not 1-D or longer than the scenario."""
    p = params or BrakingParams()
    d = np.asarray(detected, dtype=bool)
    if d.ndim != 1 or d.size > p.n_steps:
        raise ValueError(f"controller_trace: detected must be bool [T <= {p.n_steps}], got shape {d.shape}")
    n = d.size
    sim = BatchedBraking(p, 1)
    ctrl = initial_controller_state(1)  # the same pure function of the same inputs as the simulator's memory
    obs = np.empty((n, 4))
    command, accel = np.zeros(n, dtype=bool), np.zeros(n)
    for t in range(n):
        o = sim.observation()
        obs[t] = o[0]
        a, ctrl = ego_acceleration(p, d[t : t + 1], o[:, 0], o[:, 1], ctrl)
        accel[t], command[t] = a[0], ctrl.pending_brake[0]
        sim.step(d[t : t + 1])
    return ControllerTrace(np.arange(n) * p.dt_s, obs[:, 0], obs[:, 1], obs[:, 2], command, obs[:, 3] > 0.5, accel)


# -- counterfactuals --------------------------------------------------------------------------------


def min_gaps(detected: np.ndarray, params: BrakingParams | None = None) -> np.ndarray:
    """The smallest gap of each of N replayed rollouts, float64 [N] (metres).

    Args:
        detected: bool [N, T] detection sequences, T <= ``params.n_steps``.
        params: the scenario's constants (None: :class:`~pemviz.scenarios.braking.simulator.BrakingParams`)."""
    p = params or BrakingParams()
    d = np.asarray(detected, dtype=bool)
    out = np.empty(d.shape[0])
    for a in range(0, d.shape[0], _CHUNK):
        rows = d[a : a + _CHUNK]
        sim = BatchedBraking(p, rows.shape[0])
        low = np.full(rows.shape[0], np.inf)
        for t in range(rows.shape[1]):
            np.minimum(low, sim.gap_m, out=low)
            sim.step(rows[:, t])
        out[a : a + _CHUNK] = low
    return out


@dataclass(frozen=True)
class Counterfactual:
    """Which misses decide a failure, found by exact replays on the deterministic twin.

    Attributes:
        failed: the replayed rollout fails (a gap below ``crash_gap_m``).
        misses: int [M] the steps where the detector missed.
        flipped_min_gap_m: float64 [M] the smallest gap with that one miss flipped to a detection (metres).
        decisive: int [D] the misses whose flip alone avoids the failure.
        last_saving_step: the latest decisive miss (None: no single detection saves the rollout).
        minimal_set: int [k] misses whose flip together avoids the failure, none of which can be left out; empty
            when the rollout does not fail or nothing saves it.
        minimal_set_min_gap_m: the smallest gap with ``minimal_set`` flipped (nan without a set).
        smallest: no set of fewer misses avoids the failure (exhaustive search of the smaller sizes).
        recovery_step: the last step s from which detecting at every step still avoids the failure (None: none).
        recovery_min_gap_m: the smallest gap of that replay (nan without one)."""

    failed: bool
    misses: np.ndarray
    flipped_min_gap_m: np.ndarray
    decisive: np.ndarray
    last_saving_step: int | None
    minimal_set: np.ndarray
    minimal_set_min_gap_m: float
    smallest: bool
    recovery_step: int | None
    recovery_min_gap_m: float


def _flip(detected: np.ndarray, sets: list[tuple[int, ...]]) -> np.ndarray:
    rows = np.repeat(detected[None, :], len(sets), axis=0)
    for i, s in enumerate(sets):
        rows[i, list(s)] = True
    return rows


def minimal_miss_set(
    detected: np.ndarray, params: BrakingParams | None = None, candidates: np.ndarray | None = None
) -> tuple[np.ndarray, float, bool]:
    """A set of misses whose flip to detections avoids the failure, none of which can be left out.

    Every set of 1, 2, ... up to :data:`EXACT_MAX_SIZE` misses is tried while a size has at most
    :data:`EXACT_MAX_ROWS` sets (the first size that avoids the failure gives the smallest set, the largest smallest
    gap first); else greedily the latest k misses, then any miss that can be left out is (delta debugging's
    1-minimality). Misses at the last step are no candidates.

    Args:
        detected: bool [T] a failing rollout's detections.
        params: the scenario's constants (None: :class:`~pemviz.scenarios.braking.simulator.BrakingParams`).
        candidates: int [M] the misses to consider (default: every miss before the last step).
    Returns:
        (int [k] the set's steps in order, the smallest gap with them flipped in metres, whether it is the
            smallest); (int [0], nan, False) when even flipping every candidate fails, or the rollout does not fail."""
    p = params or BrakingParams()
    d = np.asarray(detected, dtype=bool)
    miss = np.flatnonzero(~d[:-1]) if candidates is None else np.asarray(candidates, dtype=np.int64)
    none = (np.zeros(0, np.int64), math.nan, False)
    if miss.size == 0 or min_gaps(d[None], p)[0] >= p.crash_gap_m:
        return none
    exhausted = 0  # every set of this many misses or fewer fails
    for k in range(1, min(EXACT_MAX_SIZE, miss.size) + 1):
        if math.comb(miss.size, k) > EXACT_MAX_ROWS:
            break
        sets = list(itertools.combinations(miss.tolist(), k))
        gaps = min_gaps(_flip(d, sets), p)
        if gaps.max() >= p.crash_gap_m:
            i = int(np.argmax(gaps))
            return np.array(sets[i], dtype=np.int64), float(gaps[i]), True
        exhausted = k
    suffixes = [tuple(miss[miss.size - k :].tolist()) for k in range(1, miss.size + 1)]
    gaps = min_gaps(_flip(d, suffixes), p)
    ok = np.flatnonzero(gaps >= p.crash_gap_m)
    if ok.size == 0:
        return none
    chosen, gap = list(suffixes[int(ok[0])]), float(gaps[int(ok[0])])
    while len(chosen) > 1:
        fewer = [tuple(chosen[:j] + chosen[j + 1 :]) for j in range(len(chosen))]
        g = min_gaps(_flip(d, fewer), p)
        works = np.flatnonzero(g >= p.crash_gap_m)
        if works.size == 0:
            break
        j = int(works[0])
        chosen, gap = list(fewer[j]), float(g[j])
    return np.array(chosen, dtype=np.int64), gap, len(chosen) == exhausted + 1


def counterfactual(detected: np.ndarray, params: BrakingParams | None = None) -> Counterfactual:
    """Single flips, the minimal miss set and the recovery step of one rollout (see :class:`Counterfactual`).

    Args:
        detected: bool [T] the rollout's detections, T <= ``params.n_steps``.
        params: the scenario's constants (None: :class:`~pemviz.scenarios.braking.simulator.BrakingParams`).
    Raises:
        ValueError: ``detected`` not 1-D or longer than the scenario."""
    p = params or BrakingParams()
    d = np.asarray(detected, dtype=bool)
    if d.ndim != 1 or d.size == 0 or d.size > p.n_steps:
        raise ValueError(f"counterfactual: detected must be bool [1 <= T <= {p.n_steps}], got shape {d.shape}")
    n = d.size
    misses = np.flatnonzero(~d)
    # row 0: as recorded; rows 1..M: one miss flipped; rows M+1..M+T: detections from step s on
    rows = np.repeat(d[None, :], 1 + misses.size + n, axis=0)
    rows[np.arange(1, misses.size + 1), misses] = True
    later = np.arange(n)[None, :] >= np.arange(n)[:, None]
    rows[1 + misses.size :] |= later
    gaps = min_gaps(rows, p)
    failed = bool(gaps[0] < p.crash_gap_m)
    flipped = gaps[1 : 1 + misses.size]
    recovery = gaps[1 + misses.size :]
    if not failed:
        empty = np.zeros(0, np.int64)
        return Counterfactual(False, misses, flipped, empty, None, empty, math.nan, False, None, math.nan)
    decisive = misses[flipped >= p.crash_gap_m]
    saves = np.flatnonzero(recovery >= p.crash_gap_m)
    rec = int(saves[-1]) if saves.size else None
    minimal, minimal_gap, smallest = minimal_miss_set(d, p)
    return Counterfactual(
        failed=True,
        misses=misses,
        flipped_min_gap_m=flipped,
        decisive=decisive,
        last_saving_step=int(decisive[-1]) if decisive.size else None,
        minimal_set=minimal,
        minimal_set_min_gap_m=minimal_gap,
        smallest=smallest,
        recovery_step=rec,
        recovery_min_gap_m=float(recovery[rec]) if rec is not None else math.nan,
    )


# -- in words ---------------------------------------------------------------------------------------


def last_saving_steps(detected: np.ndarray, params: BrakingParams | None = None) -> np.ndarray:
    """The last step at which one detection alone still saves each rollout, as
    :attr:`Counterfactual.last_saving_step` (the latest decisive miss), for many rollouts in one batch of replays.

    Only the misses before a rollout's first breach of the margin and inside the braking distance are flipped: a
    detection at or after the breach cannot undo it, and one outside the braking distance commands no brake.

    Args:
        detected: bool [F, T] the rollouts' detections, T <= ``params.n_steps``.
        params: the scenario's constants (None: :class:`~pemviz.scenarios.braking.simulator.BrakingParams`).
    Returns:
        int [F]: the step, -1 where no single detection saves the rollout or where it does not fail.
    Raises:
        ValueError: ``detected`` not 2-D or longer than the scenario."""
    p = params or BrakingParams()
    d = np.asarray(detected, dtype=bool)
    if d.ndim != 2 or d.shape[1] > p.n_steps:
        raise ValueError(f"last_saving_steps: detected must be bool [F, T <= {p.n_steps}], got shape {d.shape}")
    out = np.full(d.shape[0], -1, dtype=np.int64)
    if d.size == 0:
        return out
    breach = np.full(d.shape[0], d.shape[1], dtype=np.int64)
    sim, low = BatchedBraking(p, d.shape[0]), np.full(d.shape[0], np.inf)
    inside = np.zeros(d.shape, dtype=bool)  # a detection acts only within the braking distance
    for t in range(d.shape[1]):  # the first step whose gap is below the margin (the recorded rollout)
        below = (sim.gap_m < p.crash_gap_m) & (breach == d.shape[1])
        breach[below] = t
        np.minimum(low, sim.gap_m, out=low)
        inside[:, t] = sim.gap_m < p.braking_distance_m
        sim.step(d[:, t])
    rollout, step = np.nonzero(~d & inside & (np.arange(d.shape[1])[None, :] < breach[:, None]))
    if rollout.size == 0:
        return out
    rows = d[rollout].copy()
    rows[np.arange(rollout.size), step] = True
    saved = min_gaps(rows, p) >= p.crash_gap_m
    np.maximum.at(out, rollout[saved], step[saved])
    out[low >= p.crash_gap_m] = -1
    return out


def _times(steps: np.ndarray, dt: float, most: int = 4) -> str:
    """``2.30-2.65, 2.75 and 3.10-4.80 s``: steps as times, runs of consecutive steps as ranges (at most ``most``)."""
    runs = np.split(steps, np.flatnonzero(np.diff(steps) != 1) + 1) if steps.size else []
    parts = [f"{r[0] * dt:.2f}" if r.size == 1 else f"{r[0] * dt:.2f}-{r[-1] * dt:.2f}" for r in runs[:most]]
    if len(runs) > most:
        parts.append(f"{len(runs) - most} more runs")
    return (", ".join(parts[:-1]) + " and " + parts[-1] if len(parts) > 1 else "".join(parts)) + " s"


def describe(
    detected: np.ndarray,
    sev: Severity,
    ctrl: ControllerTrace,
    cf: Counterfactual,
    params: BrakingParams | None = None,
) -> str:
    """What happened, in a few plain sentences: the outcome, the misses within braking distance before the breach and
    what they did to the brake, and the smallest change that would have avoided the failure, e.g. ``Breach 1.91 m,
    no contact (...). From 1.80 s, when the lead came within 10 m, to the breach the lead was missed at 9 of 12
    steps; ... One detection at 2.10 s, the last that suffices alone, would have avoided it (min gap 2.80 m, 0.80 m
    clear of the 2 m margin).``

    Args:
        detected: bool [T] the rollout's detections.
        sev: :func:`severity` of the rollout.
        ctrl: :func:`controller_trace` of the same rollout.
        cf: :func:`counterfactual` of the same rollout.
        params: the scenario's constants (None: :class:`~pemviz.scenarios.braking.simulator.BrakingParams`)."""
    p = params or BrakingParams()
    dt = p.dt_s
    d = np.asarray(detected, dtype=bool)
    if sev.breach_step is None:  # not sev.failed
        return (
            f"No failure: {sev.phrase}; the emergency brake acted at {int(ctrl.brake_applied.sum())} of "
            f"{d.size} steps."
        )
    end = int(sev.breach_step)
    near = np.flatnonzero(ctrl.gap_m[:end] < p.braking_distance_m)
    lines = [sev.phrase[0].upper() + sev.phrase[1:] + "."]
    if near.size:
        start = int(near[0])
        missed = int((~d[start:end]).sum())
        braked = int(ctrl.brake_applied[start + 1 : end + 1].sum())
        lines.append(
            f"From {start * dt:.2f} s, when the lead came within {p.braking_distance_m:g} m, to the breach at "
            f"{end * dt:.2f} s the lead was missed at {missed} of {end - start} steps"
            + ("" if p.latched_brake else "; each miss left the emergency brake off at the next step")
            + f" (it acted at {braked} step{'s' * (braked != 1)})."
        )
    else:
        lines.append(f"The gap fell below {p.crash_gap_m:g} m before the lead came within braking distance.")

    def clear(gap: float) -> str:
        """``min gap 2.80 m, 0.80 m clear of the 2 m margin``."""
        room = gap - p.crash_gap_m
        room_text = f"{room:.2f} m" if room >= 0.01 else "less than 1 cm"
        return f"min gap {gap:.2f} m, {room_text} clear of the {p.crash_gap_m:g} m margin"

    if cf.last_saving_step is not None:
        t = cf.last_saving_step
        lines.append(
            f"One detection at {t * dt:.2f} s, the last that suffices alone, would have avoided it "
            f"({clear(float(cf.flipped_min_gap_m[np.searchsorted(cf.misses, t)]))})."
        )
    elif cf.minimal_set.size:
        fewest = ", and no fewer do" if cf.smallest else ""
        lines.append(
            f"No single detection avoids it; detections at the {cf.minimal_set.size} misses at "
            f"{_times(cf.minimal_set, dt)} together would have ({clear(cf.minimal_set_min_gap_m)}){fewest}."
        )
    else:
        lines.append("Even a detection at every step would not have avoided it.")
    if cf.recovery_step is not None:
        lines.append(
            f"A detector that worked from {cf.recovery_step * dt:.2f} s on would still have avoided it "
            f"({clear(cf.recovery_min_gap_m)})."
        )
    return " ".join(lines)


# -- one rollout, all of the above ------------------------------------------------------------------


@dataclass(frozen=True)
class FailureStory:
    """Everything above for one recorded rollout (what :func:`story` returns).

    Attributes:
        severity, controller, counterfactual: :func:`severity`, :func:`controller_trace` and :func:`counterfactual`
            of it.
        replay_matches: the twin's replay reproduces the recorded gaps (to 1e-9 m); else the controller and
            counterfactual describe another rollout and are not shown.
        sentence: :func:`describe`, or the outcome and a note that the replay does not reproduce the rollout."""

    severity: Severity
    controller: ControllerTrace
    counterfactual: Counterfactual
    replay_matches: bool
    sentence: str


def story(gap_m: np.ndarray, detected: np.ndarray, params: BrakingParams | None = None) -> FailureStory:
    """Severity, controller, counterfactual and sentence of one recorded rollout, checked against its replay.

    Args:
        gap_m: float64 [T] the recorded gap (metres).
        detected: bool [T] the recorded detections, T <= ``params.n_steps``.
        params: the scenario's constants (None: :class:`~pemviz.scenarios.braking.simulator.BrakingParams`).
    Raises:
        ValueError: the arrays are not 1-D of one length, or longer than the scenario."""
    p = params or BrakingParams()
    gap, d = np.asarray(gap_m, dtype=np.float64), np.asarray(detected, dtype=bool)
    if gap.shape != d.shape:
        raise ValueError(f"story: gap_m and detected need one shape [T], got {gap.shape} and {d.shape}")
    ctrl = controller_trace(d, p)
    matches = bool(np.allclose(ctrl.gap_m, gap, rtol=0.0, atol=1e-9))
    sev, cf = severity(gap, p), counterfactual(d, p)
    sentence = (
        describe(d, sev, ctrl, cf, p)
        if matches
        else (
            sev.phrase[0].upper() + sev.phrase[1:] + ". The replay does not reproduce this rollout: no counterfactual."
        )
    )
    return FailureStory(sev, ctrl, cf, matches, sentence)


def replay_with_detections(
    detected: np.ndarray, flips: np.ndarray, params: BrakingParams | None = None
) -> ControllerTrace:
    """The replay of ``detected`` [T] with the steps ``flips`` (int [k]) turned into detections: a counterfactual
    rollout, step by step (:func:`controller_trace`)."""
    d = np.array(detected, dtype=bool)
    d[np.asarray(flips, dtype=np.int64)] = True
    return controller_trace(d, params)
