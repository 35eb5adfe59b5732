"""Conditional Monte Carlo for the braking scenario's deepest severity levels: each rollout is followed by the sampler
until its gap first drops below a start gap (5 m), and from there every detection sequence is enumerated, so the
rollout contributes its importance weight up to that step times the exact probability of a failure after it.

A gap below 0 m needs the ego at the contact gap at full speed, a window of about 2 cm set by the last detections
(:func:`pemviz.scenarios.braking.problem.never_detected_min_gap_m`), which a state proposal does not see.
Enumerating the last steps replaces that phase by its exact average: unbiased (conditional Monte Carlo at a stopping
time: Asmussen & Glynn, Stochastic Simulation, Springer 2007, V.4). A branch is dropped only when it cannot fail any
more (a speed bound), once the ego is stopped in contact behind a stopped lead, or when it is ``prune_nats`` below
the failure probability found so far (a relative bias below 1e-12 at the default 40 nats)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.special import log_expit

from pemviz.scenarios.braking.simulator import (
    OBSERVATION_NAMES,
    BrakingParams,
    braking_step,
    ego_commands,
    ego_limited,
    ego_step,
    lead_speeds,
)

LOOK_AHEAD_GAP_M = 6.0
"""The gap (metres) below which the detections are enumerated: nearer, the weights stay heavy; further, a run takes
minutes (``pemviz run --margin 0``, ``docs/validation.md``)."""

LOOK_AHEAD_ROLLOUT_S = 1.8e-3
"""Seconds per rollout of the look-ahead from :data:`LOOK_AHEAD_GAP_M` targeting 0 m, about, for the run's time
estimates (``pemviz run --margin 0 --seed 0``)."""

PRUNE_NATS = 40.0
"""A branch whose probability is this far (nats) below the failure probability found from its rollout is dropped."""

MAX_BRANCHES = 4_000_000
"""The most branches held at once (about 0.3 GB); more raise an error rather than exhaust the memory."""


def start_steps(gap_m: np.ndarray, start_gap_m: float) -> np.ndarray:
    """The first step at which each rollout's gap is below ``start_gap_m``, int [N] (T where it never is).

    Args:
        gap_m: float64 [N, T] gaps (metres).
        start_gap_m: the start gap (metres) below which the enumeration takes over."""
    below = np.asarray(gap_m) < start_gap_m
    return np.where(below.any(axis=1), below.argmax(axis=1), below.shape[1])


def _replay_states(p: BrakingParams, detected: np.ndarray, upto: np.ndarray) -> tuple[np.ndarray, ...]:
    """(gap, speed, PID integral, pending brake) [N] of each rollout at step ``upto[i]`` (its detections replayed
    through :func:`braking_step` from the start state)."""
    n = detected.shape[0]
    vlead = lead_speeds(p)
    g, v = np.full(n, p.gap0_m), np.full(n, p.ego_speed0_mps)
    integ, pend = np.zeros(n), np.zeros(n, dtype=bool)
    out = [g.copy(), v.copy(), integ.copy(), pend.copy()]
    last = int(upto[upto < detected.shape[1]].max(initial=-1))
    for t in range(last):
        g, v, integ, pend = braking_step(p, float(vlead[t]), g, v, integ, pend, detected[:, t])
        at = upto == t + 1
        for o, x in zip(out, (g, v, integ, pend), strict=False):
            o[at] = x[at]
    return tuple(out)


def log_exceedance_after(
    params: BrakingParams,
    logit_at_gap: Callable[[np.ndarray], np.ndarray],
    detected: np.ndarray,
    start: np.ndarray,
    level_m: float,
    prune_nats: float = PRUNE_NATS,
    observed_gap_m: np.ndarray | None = None,
) -> np.ndarray:
    """log P(min gap < ``level_m`` over the steps from ``start[i]`` on | rollout i's state at ``start[i]``), float64
    [N] (nats; -inf where no detection sequence fails, or ``start[i]`` = T), by enumerating every detection from
    that step on.

    Args:
        params: the scene's constants.
        logit_at_gap: logit of the PEM's p(detect) at gaps [K] (metres), e.g. ``pem.logit_at_gap``.
        detected: bool [N, T] the rollouts' detections (the steps before ``start`` set its state).
        start: int [N] the step each rollout is continued from (:func:`start_steps`).
        level_m: the failure's gap (metres).
        prune_nats: see :data:`PRUNE_NATS`.
        observed_gap_m: float64 [N] the gap each rollout reported at its start (metres), checked against the
            replayed one; or None.
    Raises:
        ValueError: ``detected`` not [N, T] with T = ``params.n_steps``, ``start`` not [N] in [0, T], a replayed gap
            more than 1e-6 m from ``observed_gap_m``, or more than :data:`MAX_BRANCHES` branches at once."""
    p = params
    detected = np.asarray(detected, dtype=bool)
    start = np.asarray(start, dtype=np.int64)
    n_steps = p.n_steps
    if (
        detected.ndim != 2
        or detected.shape[1] != n_steps
        or start.shape != (detected.shape[0],)
        or (start.size and (start.min() < 0 or start.max() > n_steps))
    ):
        raise ValueError(
            f"log_exceedance_after: detected must be bool [N, {n_steps}] and start int [N] in "
            f"[0, {n_steps}], got {detected.shape} and {start.shape}"
        )
    out = np.full(detected.shape[0], -np.inf)
    group = 100
    for lo in range(0, detected.shape[0], group):
        sl = slice(lo, lo + group)
        gap = None if observed_gap_m is None else np.asarray(observed_gap_m, dtype=np.float64)[sl]
        out[sl] = _enumerate(p, logit_at_gap, detected[sl], start[sl], level_m, prune_nats, gap)
    return out


def _enumerate(
    p: BrakingParams,
    logit_at_gap: Callable[[np.ndarray], np.ndarray],
    detected: np.ndarray,
    start: np.ndarray,
    level: float,
    prune_nats: float,
    observed_gap_m: np.ndarray | None,
) -> np.ndarray:
    n, n_steps, dt = detected.shape[0], p.n_steps, p.dt_s
    vlead = lead_speeds(p)
    lead_travel = np.concatenate([np.cumsum(vlead[::-1])[::-1] * dt, [0.0]])  # [T + 2]: metres from step t on
    g0, v0, i0, p0 = _replay_states(p, detected, start)
    if observed_gap_m is not None:
        off = np.flatnonzero((start < n_steps) & ~(np.abs(g0 - observed_gap_m) <= 1e-6))
        if off.size:
            i = int(off[0])
            raise ValueError(
                f"the braking look-ahead replays a gap of {g0[i]:.6g} m at step {start[i]} of a rollout "
                f"that reported {observed_gap_m[i]:.6g} m: its rollouts are not of this scene's "
                "parameters"
            )
    total = np.full(n, -np.inf)
    # A group holds the branches that share (owner, gap, speed, PID integral): with a one-step actuation lag, the two
    # branches of a detection differ only in the pending brake until the next step. Each branch has its group,
    # pending brake and log-probability, in the order a branch-by-branch enumeration holds them.
    shared = p.actuation_lag_steps == 1
    own, grp = np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    g = v = integ = log_path = np.empty(0)
    pend = np.empty(0, dtype=bool)
    for t in range(int(start.min(initial=n_steps)), n_steps):
        join = np.flatnonzero(start == t)
        if join.size:
            grp = np.concatenate([grp, np.arange(own.size, own.size + join.size)])
            own = np.concatenate([own, join])
            g, v, integ = (
                np.concatenate([g, g0[join]]),
                np.concatenate([v, v0[join]]),
                np.concatenate([integ, i0[join]]),
            )
            pend = np.concatenate([pend, p0[join]])
            log_path = np.concatenate([log_path, np.zeros(join.size)])
        failed, fails_next, keep = _group_ends(p, t, g, v, level, float(vlead[t]), lead_travel)
        for ends in (failed, fails_next):
            if ends.any():
                at = np.flatnonzero(ends[grp])
                np.logaddexp.at(total, own[grp[at]], log_path[at])
        kept = keep[grp] & (log_path >= (total[own] - prune_nats)[grp])
        grp, pend, log_path = grp[kept], pend[kept], log_path[kept]
        if grp.size == 0:
            own, g, v, integ = grp, log_path, log_path, log_path
            if start.max(initial=-1) <= t:
                break
            continue
        live = np.zeros(own.size, dtype=bool)
        live[grp] = True
        if not live.all():
            grp = (np.cumsum(live) - 1)[grp]
            own, g, v, integ = own[live], g[live], v[live], integ[live]
        (own, g, v, integ), grp, pend, log_path = _branch(
            p, logit_at_gap, float(vlead[t]), shared, (own, g, v, integ), grp, pend, log_path
        )
        if grp.size > MAX_BRANCHES:
            raise ValueError(
                f"the braking look-ahead holds {grp.size:,} branches at step {t} (at most "
                f"{MAX_BRANCHES:,}): these braking parameters leave too many detection sequences open after "
                f"the {LOOK_AHEAD_GAP_M:g} m start (a weak brake or a margin above the contact gap "
                f"{p.contact_gap_m:g} m); run them with --method mc, or a stronger brake"
            )
    return total


def _group_ends(
    p: BrakingParams,
    t: int,
    g: np.ndarray,
    v: np.ndarray,
    level: float,
    lead_speed_mps: float,
    lead_travel: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(failed at step ``t``, fails at the next step, still open) bool [G] of states (gap ``g``, speed ``v``) at
    step ``t``: in contact next step, the gap moves once more, then only as the lead does, unless that takes it out
    of contact (the ego would start again); a state too slow to reach the speed a failure below the contact gap
    needs before it enters contact is closed (the throttle then accelerates at most ``throttle_accel0_mps2``)."""
    dt, n_steps = p.dt_s, p.n_steps
    failed = g < level  # observed at step t
    nxt = g + (lead_speed_mps - v) * dt
    contact = ~failed & (g <= p.contact_gap_m) & (np.maximum(g, nxt) + lead_travel[t + 1] <= p.contact_gap_m)
    fails_next = contact & (nxt < level) & (t + 1 < n_steps)
    keep = ~(failed | contact)
    if level < p.contact_gap_m and p.throttle_accel_slope_per_s >= 0:
        a_max, v_need = p.throttle_accel0_mps2, (p.contact_gap_m - level) / (2 * dt)
        travel = np.maximum(g - p.contact_gap_m, 0.0) + lead_travel[t]
        reach = np.sqrt(v**2 + 2 * a_max * travel + (n_steps - t) * (a_max * dt) ** 2) + a_max * dt
        keep &= (g <= p.contact_gap_m) | (reach > v_need)
    return failed, fails_next, keep


def _branch(
    p: BrakingParams,
    logit_at_gap: Callable[[np.ndarray], np.ndarray],
    lead_speed_mps: float,
    shared: bool,
    groups: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    grp: np.ndarray,
    pend: np.ndarray,
    log_path: np.ndarray,
) -> tuple[tuple[np.ndarray, ...], np.ndarray, np.ndarray, np.ndarray]:
    """Every branch one step on (:func:`braking_step`), split by the detection at this step inside the braking
    distance: the groups' (owner, gap, speed, integral) [G] and each branch's group, pending brake and log-probability
    [B], the same after the step. A group's controller commands are computed once for its branches; with a one-step
    lag (``shared``) a branch's two children share the next state but for the pending brake: one group."""
    own, g, v, integ = groups
    split_g = g < p.braking_distance_m  # a detection changes the state only inside the braking distance
    log_det, log_miss = np.zeros(g.size), np.zeros(g.size)  # outside it one child, of probability 1
    logit = logit_at_gap(g[split_g])
    log_det[split_g], log_miss[split_g] = log_expit(logit), log_expit(-logit)
    integ2, full_brake, accel_pid = ego_commands(p, v, integ)
    g2 = g + (lead_speed_mps - v) * p.dt_s
    v_brake = ego_step(p, v, ego_limited(p, g, v, -full_brake))
    v_pid = ego_step(p, v, ego_limited(p, g, v, accel_pid))
    split = split_g[grp]
    s = slice(None) if split.all() else np.flatnonzero(split)  # the branches whose detection is enumerated
    held = pend & p.latched_brake  # the latched brake, once started, stays on
    pend2 = np.concatenate([split | held, held[s]])  # the detected child first
    log_path2 = np.concatenate([log_path + log_det[grp], log_path[s] + log_miss[grp[s]]])
    children = np.arange(grp.size)[s]
    if shared:  # the brake applied is the pending one, the same for both children
        rows, grp2 = grp, np.concatenate([np.arange(grp.size), children])
        v2 = np.where(pend, v_brake[grp], v_pid[grp])
    else:  # no lag: each child applies its own detection's brake
        rows = np.concatenate([grp, grp[s]])
        grp2 = np.arange(rows.size)
        v2 = np.where(pend2, v_brake[rows], v_pid[rows])
    return (own[rows], g2[rows], v2, integ2[rows]), grp2, pend2, log_path2


def braking_look_ahead(
    params: BrakingParams, logit_at_gap: Callable[[np.ndarray], np.ndarray], start_gap_m: float = LOOK_AHEAD_GAP_M
) -> Callable:
    """The braking problem's :data:`pemviz.core.problems.LookAheadFn`: each rollout from the first step its gap is below
    ``start_gap_m`` (metres), with the exact probability of a gap below ``params.crash_gap_m`` after it
    (:func:`log_exceedance_after`)."""
    column = OBSERVATION_NAMES.index("gap_m")

    def look_ahead(batch) -> tuple[np.ndarray, np.ndarray]:
        gap = batch.observations[..., column]
        start = start_steps(gap, start_gap_m)
        detected = np.asarray(batch.detected).reshape(batch.n, batch.n_steps)
        seen = gap[np.arange(batch.n), np.minimum(start, batch.n_steps - 1)]
        return start, log_exceedance_after(
            params, logit_at_gap, detected, start, params.crash_gap_m, observed_gap_m=seen
        )

    return look_ahead
