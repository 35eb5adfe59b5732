"""The cut-in's look-ahead: a state's events tried and continued with nominal perception, and the chain of
:mod:`pemviz.scenarios.cut_in.committor` solved from them (:class:`CutInLookAhead`).

A **look-ahead** applies each of a few events of the cut-in car to copies of a rollout's state and continues them
with nominal perception until the ACC follows the cut-in car, then extrapolates the IDM's closest approach
(:meth:`CutInLookAhead.extrap`); its robustness is the branch's level G
(:func:`~pemviz.scenarios.cut_in.committor.continuous_level`). With the default traffic it runs on :class:`OneCar`,
the twin with the cut-in car alone. :meth:`CutInLookAhead.solve_beam` builds the chain U_t(G, k) from a beam over
the cut-in car's events and an extra-trees regression of the events' shifts of G (scikit-learn
``ExtraTreesRegressor``). Every simulated step counts in :attr:`CutInLookAhead.steps`.

Units: metres, seconds, m/s."""

from __future__ import annotations

import copy
import dataclasses
import functools
from typing import Any

import numpy as np

from pemviz.core import exact
from pemviz.scenarios.cut_in.batched import MAX_SPEED_MPS, BatchedCutIn, CutInBatchState, cached_trajectory
from pemviz.scenarios.cut_in.committor import LMAX, Grid, LevelChain, continuous_level, g_bin, level
from pemviz.scenarios.cut_in.highway import TrafficTrajectory
from pemviz.scenarios.cut_in.scenario import (
    LANE_WIDTH_M,
    OBJECT_NAMES,
    OBSERVATION_NAMES,
    CutInParams,
    idm_acceleration,
)
from pemviz.scenarios.cut_in.scene import scene_signals
from pemviz.stack import tracker

VISIBLE = OBJECT_NAMES.index("visible")
LOG_PVVY, CONFIRMED, COAST, VX_ERROR, VY_ERROR = 7, 9, 10, 15, 17
"""Columns of :func:`features`: the log of the cut-in car's track's lateral velocity variance, whether it is
confirmed, and the predictions since its last update (1 after an updated step: the state is predicted); with errors,
the track's velocity errors along and across the road."""
MARGIN, RECENT, CLEAR, FOLLOWED = (
    OBSERVATION_NAMES.index(k) for k in ("safe_margin_m", "cut_in_recent", "clearance_m", "followed_index")
)

DP_DEPTH = 5
"""How many steps before the window the beam (and the study's event sequences) start."""
BEAM_SIZE = 400
"""The most representatives a step of :meth:`CutInLookAhead.solve_beam` keeps."""
BEAM_MODERATE = 1.6e-2
"""The tail mass of the moderate errors a beam representative's children take."""
REGIME_RATIOS = (1.2, 1.5, 2.0, 3.0, 5.0, 10.0)
"""The bounds of the ratio of the track's lateral velocity variance to the nominal path's that separate its regimes
(a restarted track starts from its velocity prior)."""


def p_detect_of(logit: np.ndarray) -> np.ndarray:
    """p(detect) from its logit, float64 (the same shape), the same on every CPU (:func:`pemviz.core.exact.
    softplus_and_sigmoid`): the cut-in car's p(detect) decides the tilt's classes and the beam's ranking."""
    return exact.softplus_and_sigmoid(np.asarray(logit, dtype=np.float64))[1]


def operand(obs: np.ndarray) -> np.ndarray:
    """The failure formula's operand at one step, float64 [N] (metres): min(safe margin + 1000 x cut-in grace,
    clearance), from observations [N, F] (:data:`pemviz.scenarios.cut_in.scenario.OBSERVATION_NAMES`)."""
    return np.minimum(obs[:, MARGIN] + 1000.0 * obs[:, RECENT], obs[:, CLEAR])


def features(state: CutInBatchState, traffic: Any, errors: bool = False) -> np.ndarray:
    """The cut-in car's track and the ego at a state, float64 [N, 14] (``errors``: [N, 18], with the track's position
    and velocity errors against the car's true state along and across the road; metres, m/s, log variances).

    Args:
        state: N rollouts' state.
        traffic: the step's true traffic (:class:`pemviz.scenarios.cut_in.highway.TrafficTrajectory` entry).
        errors: append the track's errors against the car's true state (metres, m/s along and across the road)."""
    tr = state.tracks
    log = exact.log  # the same on every CPU: the regimes and the effect model's splits read these
    cols = [
        tr.x[0] - state.ego_x_m,
        tr.vx[0],
        log(tr.pxx[0] + 1e-6),
        log(tr.pvvx[0] + 1e-6),
        tr.y[0],
        tr.vy[0],
        log(tr.pyy[0] + 1e-6),
        log(tr.pvvy[0] + 1e-6),
        tr.active[0],
        tr.confirmed[0],
        tr.coast[0],
        traffic.x_m[0] - state.ego_x_m,
        state.ego_speed_mps,
        state.followed == 0,
    ]
    if errors:
        cols += [
            tr.x[0] - traffic.x_m[0],
            tr.vx[0] - traffic.vx_mps[0],
            tr.y[0] - traffic.y_m[0],
            tr.vy[0] - traffic.vy_mps[0],
        ]
    return np.column_stack(cols)


class OneCar(BatchedCutIn):
    """The batched twin with the cut-in car alone (every other car and its track dropped): the look-ahead's simulator.
    With the default traffic no other car is ever in the ego's lane, so with nominal perception the ACC acts on the
    cut-in car's track alone; the outcome differs only where another car would have hidden the cut-in car."""

    def __init__(self, params: CutInParams, n: int) -> None:  # noqa: D107 (no super().__init__: it checks M >= 3)
        one = copy.copy(params)
        object.__setattr__(one, "n_objects", 1)
        self.params, self.n, self.n_objects = one, int(n), 1
        self._trajectory = one_car_trajectory(params)
        self._shift, self._traffic_at = None, None  # one start gap (BatchedCutIn's gap_shift_m: none)
        self.reset()


@functools.lru_cache(maxsize=8)
def one_car_trajectory(params: CutInParams) -> TrafficTrajectory:
    """The traffic of every step with the cut-in car (object 0) alone, computed once per parameter set."""

    def alone(tr: Any) -> Any:
        arrays = {
            f.name: getattr(tr, f.name)[:1]
            for f in dataclasses.fields(tr)
            if isinstance(getattr(tr, f.name), np.ndarray)
        }
        return dataclasses.replace(tr, occluder_pairs=(), **arrays)

    return TrafficTrajectory(tuple(alone(tr) for tr in cached_trajectory(params).traffic))


def one_car_state(st: CutInBatchState) -> CutInBatchState:
    """A state of the twin cut down to the cut-in car's track (a followed other car becomes none)."""
    tracks = tracker.Tracks(*(getattr(st.tracks, f.name)[:1] for f in dataclasses.fields(st.tracks)))
    return CutInBatchState(
        st.t, st.ego_x_m, st.ego_speed_mps, st.ego_accel_mps2, tracks, np.where(st.followed > 0, -1, st.followed)
    )


class CutInLookAhead:
    """Look-aheads of the cut-in scene (module docstring) and the chain solved from them.

    Args:
        params: the scene.
        target: the PEMs (:class:`pemviz.pem.perception.SalientDetector`): p(detect) and the errors' quantiles.
        grid: the events.
        window: (first, end) steps at which the cut-in car's events are tilted.
        end: the continuations' last step.
        one_car: continue on :class:`OneCar` (else the whole twin).
        graded: a look-ahead's features end with the follow step and the track's lateral margins there.
        continuous: the margin read from the track the ACC decided on (the predicted position less vy dt).
        errors: :func:`features` with the track's errors.
        error_buckets: (feature column, ascending bounds) that split the regimes further.
        dp_mass: the tail mass of the beam's (and the study's event sequences') range errors: beyond the tracker's
            gate.
        effect_model: fit the regression of the events' shifts of G in :meth:`solve_beam`."""

    def __init__(
        self,
        params: CutInParams,
        target: Any,
        grid: Grid,
        window: tuple[int, int],
        end: int,
        *,
        one_car: bool = True,
        graded: bool = True,
        continuous: bool = True,
        errors: bool = False,
        error_buckets: tuple[tuple[int, tuple[float, ...]], ...] = (),
        dp_mass: float = 1e-3,
        effect_model: bool = True,
    ) -> None:
        self.params, self.target, self.grid = params, target, grid
        self.traj = cached_trajectory(params).traffic
        self.window, self.end = (int(window[0]), int(window[1])), int(end)
        self.one_car, self.graded, self.continuous = one_car, graded, continuous
        self.error_buckets = list(error_buckets)
        self.errors = errors or bool(self.error_buckets)
        self.dp_mass, self.effect_model_on, self.effect_model = dp_mass, effect_model, None
        self.pvvy_nom: dict[int, float] = {}
        self.branch_steps = self.one_steps = self.extrap_steps = 0

    @property
    def steps(self) -> int:
        """Rollout-steps simulated so far by look-aheads, on the whole twin and on :class:`OneCar` (the kinematic tail
        of :meth:`extrap` apart)."""
        return self.branch_steps + self.one_steps

    def regime(self, feats: np.ndarray, t: int) -> np.ndarray:
        """The track's regime (int64 [...]) at step t from :func:`features` rows [..., F]: confirmed or not, coasting
        or not, the bucket of its lateral velocity variance over the nominal path's (:data:`REGIME_RATIOS`) and, with
        ``error_buckets``, of those columns."""
        tn = min(t, max(self.pvvy_nom))
        ratio = exact.exp(feats[..., LOG_PVVY] - self.pvvy_nom[tn])
        bucket = np.searchsorted(np.array(REGIME_RATIOS), ratio)
        base = ((feats[..., CONFIRMED] < 0.5) * 2 + (feats[..., COAST] > 1)) * (len(REGIME_RATIOS) + 1) + bucket
        for col, bounds in self.error_buckets:
            base = base * (len(bounds) + 1) + np.searchsorted(np.array(bounds), feats[..., col])
        return base

    def n_regimes(self) -> int:
        """How many regimes :meth:`regime` tells apart."""
        return int(4 * (len(REGIME_RATIOS) + 1) * np.prod([len(b) + 1 for _, b in self.error_buckets]))

    def count(self, bsim: BatchedCutIn, steps: int) -> None:
        """Count ``steps`` rollout-steps of a look-ahead on ``bsim`` (the whole twin or the cut-in car alone)."""
        if isinstance(bsim, OneCar):
            self.one_steps += steps
        else:
            self.branch_steps += steps

    def margin(self, tr: tracker.Tracks) -> np.ndarray:
        """The cut-in car's track's lateral margin outside the lane's 2 m band, float64 [N] (metres; 5 without a
        track); with ``continuous``, of the track as the last step's update left it (the predicted position less
        vy dt): the estimate the ACC decided on."""
        y = tr.y[0] - tr.vy[0] * self.params.dt_s if self.continuous else tr.y[0]
        return np.where(tr.active[0], np.abs(y - self.params.ego_y_m) - LANE_WIDTH_M / 2, 5.0)

    def continue_nominal(self, bsim: BatchedCutIn, lo: np.ndarray, before: np.ndarray | None = None) -> np.ndarray:
        """Continue every rollout of ``bsim`` with nominal perception until the ACC follows the cut-in car, then by
        :meth:`extrap`, lowering ``lo`` [N] (metres) to the operand's minimum; returns float64 [N, 3] (follow step,
        the track's lateral margin there and a step before; ``before`` [N] else 5 m)."""
        n = lo.size
        live = np.arange(n)
        graded = np.tile([float(self.end), 5.0, 5.0], (n, 1))
        if before is not None:
            graded[:, 1] = before
        while live.size and bsim.t < self.end:
            obs = bsim.observation()
            lo[live] = np.minimum(lo[live], operand(obs))
            tr = bsim.state.tracks
            graded[live, 2] = np.abs(tr.vy[0]) * self.params.dt_s if self.continuous else graded[live, 1]
            graded[live, 1] = self.margin(tr)
            done = obs[:, FOLLOWED] == 0
            graded[live[done], 0] = bsim.t
            if done.any():
                self.extrap(bsim, live, done, lo)
                live = live[~done]
                if not live.size:
                    break
                state = bsim.snapshot().select(np.flatnonzero(~done))
                bsim = type(bsim)(self.params, live.size)
                bsim.restore(state)
            bsim.step(bsim.objects()[:, :, VISIBLE] > 0.5, None)
            self.count(bsim, live.size)
        if live.size:
            lo[live] = np.minimum(lo[live], operand(bsim.observation()))
        return graded

    def extrap(self, bsim: BatchedCutIn, live: np.ndarray, done: np.ndarray, lo: np.ndarray) -> None:
        """The ego of the rollouts ``live[done]`` behind the cut-in car to step ``end`` with the IDM on its true
        distance and speed, lowering ``lo`` (metres) to the operand's minimum."""
        p = self.params
        st = bsim.state.select(np.flatnonzero(done))
        rows = live[done]
        # the operand depends on the ego's (x, v) at the follow step alone: one extrapolation per distinct pair
        pairs, first, inverse = np.unique(
            np.column_stack([st.ego_x_m, st.ego_speed_mps]), axis=0, return_index=True, return_inverse=True
        )
        tracks, followed = st.tracks.select(first), st.followed[first]
        x, v, low = pairs[:, 0].copy(), pairs[:, 1].copy(), np.full(pairs.shape[0], np.inf)
        for t in range(st.t, self.end):
            tr = self.traj[t]
            a = idm_acceleration(p.idm, p.ego_target_speed_mps, v, tr.x_m[0] - x, v - tr.vx_mps[0])
            a = np.maximum(a, -v / p.dt_s)
            a = np.where(v > MAX_SPEED_MPS, np.minimum(a, MAX_SPEED_MPS - v), a)
            x, v = x + v * p.dt_s, np.maximum(v + a * p.dt_s, 0.0)
            low = np.minimum(low, operand(scene_signals(p, self.traj[t + 1], x, v, a, tracks, followed)))
            self.extrap_steps += rows.size
        lo[rows] = np.minimum(lo[rows], low[inverse.ravel()])

    def look_ahead(
        self,
        sim: BatchedCutIn,
        idx: np.ndarray,
        u: np.ndarray,
        rows: np.ndarray,
        prefix_min: np.ndarray,
        reps: np.ndarray | None = None,
        keep_states: bool = False,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Each branch's robustness [k, B] (metres) and next-state features [k, B, F] for the rollouts ``idx`` [k] of
        ``sim`` at their step, the other cars taking the step's own uniforms ``u`` [N, M, 3].

        Args:
            sim: the N rollouts, at their step.
            idx: int [k] the rollouts branched.
            u: float64 [N, M, 3] the step's uniforms (detection, range error, lateral error) of every car.
            rows: the step's object rows [N, M, G].
            prefix_min: each rollout's operand minimum so far [N] (metres).
            reps: the branches' uniforms of the cut-in car [B, 3] (None: the grid's NBRANCH).
            keep_states: leave the branches' states after their step in :attr:`branch_states` (row i B + b: rollout
                ``idx[i]``, branch b)."""
        target, m, g = self.target, rows.shape[1], self.grid
        reps = g.reps if reps is None else reps
        k, kk = idx.size, reps.shape[0]
        r_rows = rows[idx].reshape(k * m, -1)
        p_detect = p_detect_of(target.detect_logit(r_rows)).reshape(k, m)
        det = (u[idx, :, 0] <= p_detect).reshape(-1)
        noise = np.zeros((k * m, 2))
        if det.any():
            noise[det] = target.noise_from_uniforms(r_rows[det], u[idx].reshape(k * m, 3)[det, 1:])
        det_b = np.repeat(det.reshape(k, m), kk, axis=0)
        noise_b = np.repeat(noise.reshape(k, m, 2), kk, axis=0)
        rb = np.tile(reps, (k, 1))
        rows0 = np.repeat(rows[idx, 0, :], kk, axis=0)
        det_b[:, 0] = rb[:, 0] <= np.repeat(p_detect[:, 0], kk)  # a branch's detection uniform is 0 or 1
        noise_b[:, 0] = 0.0
        hit = det_b[:, 0]
        noise_b[hit, 0] = target.noise_from_uniforms(rows0[hit], rb[hit, 1:])
        start = sim.snapshot().select(np.repeat(idx, kk))
        bsim: BatchedCutIn
        if self.one_car:
            bsim = OneCar(self.params, k * kk)
            bsim.restore(one_car_state(start))
            bsim.step(det_b[:, :1], noise_b[:, :1])
        else:
            bsim = BatchedCutIn(self.params, k * kk)
            bsim.restore(start)
            bsim.step(det_b, noise_b)
        self.count(bsim, k * kk)
        if keep_states:
            self.branch_states = bsim.snapshot()
        feats = features(bsim.state, self.traj[bsim.t], self.errors)
        lo = np.repeat(prefix_min[idx], kk)
        before = self.margin(start.tracks) if self.continuous else None  # the margin of the state they start from
        graded = self.continue_nominal(bsim, lo, before)
        if self.graded:
            feats = np.column_stack([feats, graded[:, 0] - sim.t, graded[:, 1:]])
        return lo.reshape(k, kk), feats.reshape(k, kk, -1)

    def nominal_path(self) -> tuple[dict[int, float], dict[int, tuple[CutInBatchState, bool]]]:
        """Walk the nominal path (every visible car detected, no error) to the window's end: sets :attr:`pvvy_nom`
        (the regimes' reference) and returns the cut-in car's p(detect) and (state, visible) of each step."""
        p, target = self.params, self.target
        sim = BatchedCutIn(p, 1)
        p0s, nominal = {}, {}
        for t in range(self.window[1] + 1):
            self.pvvy_nom[t] = float(features(sim.state, self.traj[t])[0, LOG_PVVY])
            p0s[t] = float(p_detect_of(target.detect_logit(np.ascontiguousarray(sim.objects())[:1, 0]))[0])
            nominal[t] = (sim.snapshot(), bool(sim.objects()[0, 0, VISIBLE] > 0.5))
            if t < p.n_steps:
                sim.step(sim.objects()[:, :, VISIBLE] > 0.5, None)
        return p0s, nominal

    def solve_beam(self, width: float, beam: int = BEAM_SIZE, h: float = 0.01, gmax: float = LMAX) -> LevelChain:
        """:class:`~pemviz.scenarios.cut_in.committor.LevelChain` on cells of (regime, bin of G ``width`` wide),
        their representatives found by a beam over the cut-in car's events from :data:`DP_DEPTH` steps before the
        window: each looked ahead with every grid event, the likeliest branch of each cell kept (at most ``beam``).
        With ``effect_model`` the shift regression is fitted on the look-aheads. Runs on :class:`OneCar`; every step
        counts (:attr:`steps`).

        Raises:
            ValueError: not ``one_car`` (the representatives are states of the cut-in car alone)."""
        if not self.one_car:
            raise ValueError("the beam's representatives are states of the cut-in car alone: it needs one_car")
        p, target, g = self.params, self.target, self.grid
        w0, w1 = self.window
        nb = int(np.ceil((gmax + h) / width))
        p0s, nominal = self.nominal_path()
        ev, log_pe = self.beam_events()
        states, logp = one_car_state(nominal[w0 - DP_DEPTH][0]), np.zeros(1)
        effects: dict[int, dict] = {}
        nexts: dict[int, dict] = {}
        g_nom, counts = {}, {}
        effect_rows = []
        nreg = self.n_regimes()
        for t in range(w0 - DP_DEPTH, w1):
            bsim = OneCar(p, logp.size)
            bsim.restore(states)
            if not nominal[t][1]:  # the car is not visible: every representative steps on, no event
                bsim.step(np.zeros((logp.size, 1), dtype=bool), None)
                self.count(bsim, logp.size)
                states = bsim.snapshot()
                continue
            rows = np.ascontiguousarray(bsim.objects())
            n = logp.size
            r, bfeat = self.look_ahead(
                bsim, np.arange(n), np.zeros((n, 1, 3)), rows, np.full(n, np.inf), keep_states=True
            )
            gl = continuous_level(level(r), bfeat[..., -2], bfeat[..., -1])  # [n, NBRANCH]
            reg = self.regime(features(bsim.state, self.traj[t], self.errors), t)
            if t >= w0:
                cells = reg * nb + g_bin(gl[:, 1], width, nb)
                effects[t] = {int(c): gl[i] - gl[i, 1] for i, c in enumerate(cells)}  # the nominal's first (i = 0)
                nexts[t] = {int(c): self.regime(bfeat[i], t + 1) for i, c in enumerate(cells)}
                g_nom[t], counts[t] = float(gl[0, 1]), n
                effect_rows.append((self.effect_inputs(bsim.state, t, gl[:, 1]), gl - gl[:, 1:2]))
            p0 = p_detect_of(target.detect_logit(rows[:, 0]))
            log_p0, log_miss = exact.log(p0)[:, None], exact.log(1.0 - p0)[:, None]
            lp = logp[:, None] + np.where(ev == 0, log_miss, log_p0 + log_pe[None, :])
            creg = self.regime(bfeat[:, ev], t + 1)
            cell = creg * nb + g_bin(gl[:, ev], width, nb)
            alive = (gl[:, ev] > 0).ravel()
            flat = np.flatnonzero(alive)[np.argsort(-lp.ravel()[alive], kind="stable")]
            _, first = np.unique(cell.ravel()[flat], return_index=True)
            keep = flat[np.sort(first)][:beam]  # the likeliest child of each cell, likeliest first
            if keep.size == 0:  # every child failed (a scene that fails easily): go on from the nominal path
                states, logp = one_car_state(nominal[t + 1][0]), np.zeros(1)
                continue
            parent, j = np.divmod(keep, ev.size)
            states, logp = self.branch_states.select(parent * g.nbranch + ev[j]), lp.ravel()[keep]
        if self.effect_model_on:
            from sklearn.ensemble import ExtraTreesRegressor

            x, y = (np.concatenate(a) for a in zip(*effect_rows, strict=False))
            self.effect_model = ExtraTreesRegressor(n_estimators=100, min_samples_leaf=1, random_state=0).fit(x, y)
        return LevelChain(g, self.window, p0s, effects, nexts, nreg, h, gmax, g_nom, counts, width)

    def effect_inputs(self, state: CutInBatchState, t: int, g0: np.ndarray) -> np.ndarray:
        """The effect model's inputs, float64 [N, 20]: the track and the ego with the track's errors (:func:`features`
        with errors), G ``g0`` [N], the step."""
        return np.column_stack([features(state, self.traj[t], True), g0, np.full(g0.size, float(t))])

    def beam_events(self) -> tuple[np.ndarray, np.ndarray]:
        """The branches a beam representative's children take (none, a miss, a range error low and high at the grid
        edge nearest ``dp_mass``, and each error low and high at :data:`BEAM_MODERATE`), int64 [E], and the log of
        each one's probability given a detection (nats; 0 for the central draw; the miss's is the state's own) [E]."""
        g = self.grid
        j, jm = g.edge(self.dp_mass), g.edge(BEAM_MODERATE)
        ev = np.array([1, 0, 2 + j, 2 + g.ng + j, 2 + jm, 2 + g.ng + jm, 2 + 2 * g.ng + jm, 2 + 3 * g.ng + jm])
        mass = np.array([1.0, 1.0, g.masses[j], g.masses[j]] + [g.masses[jm]] * 4)
        return ev, exact.log(mass)
