"""Approximate zero-variance importance sampling on the cut-in's moderate setting with a look-ahead committor: a study
of the design (reference 8.66e-5 from 10^7 plain Monte Carlo rollouts,
:data:`pemviz.scenarios.cut_in.scenario.MONTE_CARLO_REFERENCE`). No sampler of pemviz changes.

For a Markov chain the zero-variance change of measure draws each step's events x from q(x | s) = p(x | s) Q(s, x) /
V(s), Q(s, x) the probability of failure after x and V(s) its mean under p (Kollman, Baggerly, Cox & Picard 1999, Ann.
Appl. Probab. 9(2); L'Ecuyer & Tuffin 2008, WSC). Here, at each step of ``--window`` where the cut-in car (object 0)
is visible, its uniforms (detection, range error, lateral error; density 1 under the PEMs) fall in one class of a
grid: a miss, or a detection with each error in one bin of tail mass (the edges :data:`GRIDS`, on either side, and the
central bin). The class is drawn with probability proportional to p(class) Q(class), mixed with ``--eps`` of the PEMs
(Hesterberg 1995), and the uniforms uniformly inside it: the weight p / q of the class is exact, so every estimate is
unbiased whatever Q is. Q comes from a **look-ahead**:

- each grid event (a miss; the central draw; each error at each grid edge, the other central) is applied to a copy of
  the rollout's state, the other cars taking the step's own draws, and continued with nominal perception (every
  visible car detected, no error) until the ACC follows the cut-in car; from there the ego's closest approach is
  the IDM's kinematics on the cut-in car's true trajectory (checked against the twin run to step 32: the same level
  in 99.9 % of 10^6 branches). Its robustness r gives the branch's **level** L: 0 when it fails, else 1 + floor(r /
  0.76 m) (0.76 m: what one step of late braking costs), so L - 1 counts the steps of lateness still allowed;
- a bin's Q is the mean of its two edges' Q (a joint class with both errors in tails: the larger); twin steps of the
  branches count in the cost (the kinematic tail is reported apart, ``+N kinematic``);
- the first stage takes Q = ``--a`` ^ L; after it, V(L, t) comes from the level kernel the look-ahead measured (the
  probability of each level after each step, averaged over the visited states) and the failure rate by level at the
  window's end, and a gradient-boosted regression of log V on the branch's next state (the cut-in car's track, the
  ego, the level, the step, the parent state's one-step value; ``--graded``: also the continuation's follow step and
  the track's lateral margin there) is fitted by ``--iterations`` of fitted value iteration on every visited state's
  one-step value log sum_c p(c) Q(s, c) (``--v-large``: 600 trees of 63 leaves instead of 200 of 31);
- ``--q-model``: the last stage runs no look-ahead: a regression of log Q on the state and the event's tail masses,
  fitted on every look-ahead branch so far, gives Q (1 rollout-equivalent a rollout).

``--one-car``: every look-ahead step runs on :class:`OneCar`, the twin with the cut-in car alone. With the default
traffic no other car enters the ego's lane, so under nominal perception the ACC acts on the cut-in car's track
alone: ``--check-one-car`` runs every look-ahead both ways (the same level in 99.9997 % of 344,400 branches), and a
test drives both twins through random misses and errors of the cut-in car (the same ego, operand and followed car).
A one-car step costs 0.16 us a rollout, against 0.81 us for the whole twin under nominal perception and 9.0 us for a
rollout step drawn from the PEMs (2-core machine, 20,000 rollouts a batch). Every run also prints its wall time in
plain Monte Carlo rollouts (measured at its start): plain Monte Carlo needs 1.3 x 10^5 of them for a median relative
error of 0.2.

``--train-once SEED`` fits V once on every stage of ``--n`` but the last (with that seed), then runs only the last
stage for each seed: the runs of a V that a cache keeps. ``--v-cache PATH`` writes that V (written whole, then
renamed) and reads it back in a later run whose scene, grid, window and training settings match (else it stops with
one line); the cost of fitting it is then not the run's.

``--dp``: no pilot, no fit: Q is U_t(G, k), the committor of a chain solved on the nominal path
(:meth:`LookAheadTilt.solve_dp`, :class:`LevelChain`): G the continuation's level made continuous (L - 1 plus how deep
inside the lane the track was when the ACC followed, in lateral steps of the track: :func:`continuous_level`), k the
track's regime (confirmed, coasting, its lateral velocity variance against the nominal path's), each step's events
shifting G and moving k as the look-ahead from each regime's likeliest state on the nominal path measures (its event
sequences' range errors at the grid edge nearest ``--dp-mass``, by default 1e-3: beyond the tracker's gate);
``--continuous``: Q = ``a`` ^ G instead of ``a`` ^ L in the first stage. ``--beam WIDTH``: the chain's cells are
(regime, bin of G), their representatives found by a beam over the cut-in car's events (:meth:`LookAheadTilt.
solve_beam`). ``--chain-effects``: no branches: one continuation a step gives the state's own G, and every event's
shift of G and next regime come from the chain (1.5 rollout-equivalents a rollout instead of 18-44);
``--effect-model`` (with ``--beam``): each event's shift of G at the rollout's own state comes from a multi-output
regression fitted on the beam's look-aheads (scikit-learn ``ExtraTreesRegressor``; no simulation). ``--beta``: q
proportional to p Q^beta. ``--grid lean``: 8 tail masses a side (34 branches instead of the fine grid's 82). The
chain's solve counts every step it simulates (its event sequences' too) and is printed apart: like a cached V, it is
solved once per scene.

``--mc-failures N`` draws N plain Monte Carlo rollouts, keeps the failures' uniforms, and replays them through the
last fitted proposal: their log weights log p / q, which a zero-variance proposal would make all equal to log p_fail
(-9.35), show where the proposal under-draws failures (those with log w far above it).

Measured (2-core developer machine; every run ``--window 10 24 --eps 0.3 --iterations 10``; cost in
rollout-equivalents, every twin step counted, the kinematic tail not; the reference 8.66e-5):

- ``--n 1000 1000 --graded`` (88,300 a run): x0.80, 0.60, 0.68, 0.74 of the reference, 1 of 4 intervals hold it,
  three say ``reliable``; without ``--graded``: x0.66, 0.80, 0.79, 0.83, 2 of 4 hold it;
- ``--n 3000 1000 --graded`` (176,000): x0.97, 0.84, 0.69, 1.33, 3 of 4 hold it;
- ``--n 1000 1000 --graded --v-large --iterations 20`` (88,200): x0.76, 0.90 (seeds 0, 1; 4 minutes a seed);
- ``--n 1000 4000 --graded --q-model`` (48,000): x0.66, 0.77, ESS 119-126 of 4,000;
  ``--n 400 5000 --graded --q-model --grid coarse --skip-doomed`` (15,250): x0.54, 0.71;
- ``--window 14 24 --n 1000 1000``: x0.66, 0.63, 3.50; the heaviest failure of the last (log w -1.4) had its state
  at step 14 made by a miss at step 11 and a -4 m range error at step 12 (the track restarted): the window must
  start by step 10;
- with ``--one-car --graded`` (wall time a run, in plain Monte Carlo rollouts): ``--n 1000 1000`` x0.72, 0.60 (54-57 s,
  88,000-93,000); ``--n 3000 1000`` x0.75, 0.78 (155-158 s); ``--n 1000 1000 --a 0.03 --eps 0.5``, seeds 0-5: x0.74,
  1.00, 0.84, 0.73, 0.68, 0.57, 4 of 6 intervals hold it, 2 of 4 ``reliable`` wrong (43-56 s, 70,000-119,000);
  ``--n 400 5000 --q-model --grid coarse --skip-doomed --a 0.03 --eps 0.5`` x0.65, 0.63 (32-33 s, 94,000-97,000).
  The fitted V's predictions take 25 of 57 s of a 1,000 + 1,000 run: on the clock, no configuration that fits V
  in the run is cheaper than plain Monte Carlo's 1.3 x 10^5 rollouts for a median relative error of 0.2;
  ``--errors``: x0.74, 0.92, 0.63, 0.62, 0.69, 0.63; ``--window 10 31 --end 40``: x0.77, 0.78, 2.02, 0.75;
- a V fitted once and cached (``--train-once 1000 --v-cache PATH --graded --one-car --a 0.03 --eps 0.5``):
  ``--n 5000 1000`` (271 s to fit), 1,000 rollouts a run in 9 s: x0.73, 0.56, 1.93, 0.75, 0.75, 0.92, 1.04, 0.94;
  ``--n 10000 1000`` (668 s to fit), 7-8 s a run (about 19,000 plain Monte Carlo rollouts): x0.78, 0.62, 0.71, 0.76,
  1.14, 0.67, 0.81, 0.78, 0.81, 0.83, median relative error 0.22, 4 of 8 ``reliable`` verdicts wrong; with
  ``--mc-failures 600000``, 14 of the 45 failures replayed have log w above -5 (18 with the 1,000-rollout V);
- ``--dp --dp-mass 1e-10`` (``--graded --one-car``; the chain solved in 3-4 s, 733 rollout-equivalents, once (542
  counted then, without its event sequences' steps); its own p_fail 1.2e-5, x0.14 of the reference): ``--n 1000``
  seeds 0-19 (5 s a run, 9,400-13,800 plain Monte Carlo rollouts): x5.97, 0.61,
  0.80, 1.13, 0.84, 1.08, 0.60, 0.67, 0.62, 0.85, 1.92, 0.72, 0.74, 0.95, 0.93, 0.69, 1.36, 1.63, 0.80, 0.59, median
  relative error 0.30, 19 of 20 within x2, 12 of 20 intervals hold it, 1 ``reliable`` (x0.85); ``--n 2000`` seeds
  0-5 (11-12 s): x0.71, 0.56, 1.00, 0.83, 0.76, 0.82; ``--n 300`` seeds 0-7: x0.48 (``reliable``: wrong), 1.46,
  0.66, 2.11, 1.29, 0.91, 0.92, 3.28; ``--n 1000 1000`` (V fitted on the chain's stage): x0.69, 0.71, both
  ``reliable``; ``--continuous --n 2000 --a 0.004``: x0.64, 0.71;
- seeds 0-19, ``--graded --one-car --dp`` (``--dp-mass 1e-3``), cost a run (+ the chain's, once): ``--n 1000``
  44,200 (+649): median relative error 0.24, 9 of 20 intervals hold the reference, 14 ``reliable`` (11 of them
  missing it, x0.65-0.76); ``--grid lean --n 650`` 11,900 (+376): 0.36, 13 of 20 hold, ``reliable`` x0.47 once;
  ``--grid lean --chain-effects --n 8000`` 12,050 (+376), 5 s a run: 0.29, 8 of 20 hold, 20 of 20 within x2;
  ``--grid lean --beam 0.25 --n 600`` 10,900 (+1,236): 0.29, 14 of 20 hold; with ``--eps 0.5``: 0.26, 15 of 20,
  17 within x2, 19 ``unreliable``; ``--grid lean --beam 0.25 --chain-effects --n 7500`` 11,280 (+1,236): 0.29, 10 of
  20 hold;
- the window to step 31 (``--window 10 32 --end 40 --grid lean``; 185 plain Monte Carlo failures replayed show that
  a window ending at step 23 leaves four of them at log w +6, their decisive events after it): ``--chain-effects
  --beta 0.5 --n 7900`` 12,494 (+510), 5 s a run: median relative error 0.24, 19 of 20 within x2, 16 of 20 hold, no
  ``reliable``; ``--beam 0.25 --n 550`` 11,450-11,500 (+1,464), 1-5 s: 0.23, 18 of 20 within x2, 16 of 20 hold, 19
  ``unreliable`` (research/cut-in-notes.md has every estimate and the routes tried);
- the effect model (``--window 10 32 --end 40 --grid lean --chain-effects --beam 0.25 --effect-model --beta 0.7
  --n 7280``; 11,530 a run + 1,464 for the chain, 12,994 in all; 6-7 s a run): seeds 0-19 median relative error
  0.18, 19 of 20 within x2, 16 of 20 intervals hold the reference; seeds 20-39: 0.18, 19 of 20, 17 of 20; no
  ``reliable`` verdict; over the 40, mean x0.95 (measured on an AVX-512 CPU before the noise PEM's scale and the
  tilt's logs came from :mod:`pemviz.core.exact`; this route is now ``pemviz run --scenario cut-in``, whose figures
  on every CPU are in research/cut-in-notes.md, "The default: the tilted proposal");
- ``--n 1000 1000 --mc-failures 600000``: 45 failures; under the proposal fitted on the first 1,000 rollouts, 18 of
  them have log w above -5 (a zero-variance proposal: -9.35 each): drawn at least 80 times too rarely. In them an
  error in the 1-20 % tails at steps 16-18 decides, from states that moderate errors at steps 10-16 brought close to
  the lane's edge and that the fitted V does not tell apart.

Usage::

    python research/cut_in_lookahead_tilt.py --seeds 4 --n 1000 1000 --graded
    python research/cut_in_lookahead_tilt.py --seeds 4 --n 3000 1000 --graded
    python research/cut_in_lookahead_tilt.py --seeds 2 --n 1000 1000 --graded --v-large --iterations 20
    python research/cut_in_lookahead_tilt.py --seeds 2 --n 1000 4000 --graded --q-model
    python research/cut_in_lookahead_tilt.py --seeds 2 --n 400 5000 --graded --q-model --grid coarse --skip-doomed
    python research/cut_in_lookahead_tilt.py --seeds 1 --n 1000 1000 --mc-failures 600000
    python research/cut_in_lookahead_tilt.py --seeds 1 --n 300 --graded --check-one-car
    python research/cut_in_lookahead_tilt.py --seeds 6 --n 1000 1000 --graded --one-car --a 0.03 --eps 0.5
    python research/cut_in_lookahead_tilt.py --train-once 1000 --v-cache v10k.pkl --seeds 10 --n 10000 1000 \
        --graded --one-car --a 0.03 --eps 0.5
    python research/cut_in_lookahead_tilt.py --seeds 20 --n 1000 --graded --one-car --dp --dp-mass 1e-10
    python research/cut_in_lookahead_tilt.py --seeds 20 --n 7900 --graded --one-car --dp --grid lean --chain-effects \
        --beta 0.5 --window 10 32 --end 40
    python research/cut_in_lookahead_tilt.py --seeds 20 --n 550 --graded --one-car --dp --grid lean --beam 0.25 \
        --window 10 32 --end 40
    python research/cut_in_lookahead_tilt.py --seeds 1 --n 7900 --graded --one-car --dp --grid lean --chain-effects \
        --beta 0.5 --window 10 32 --end 40 --mc-failures 2200000
    python research/cut_in_lookahead_tilt.py --seeds 20 --n 7280 --graded --one-car --dp --grid lean --chain-effects \
        --beam 0.25 --effect-model --beta 0.7 --window 10 32 --end 40
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.special import expit, logsumexp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pemviz.core.estimate import estimate  # noqa: E402
from pemviz.core.lockstep import run_batched  # noqa: E402
from pemviz.scenarios.cut_in.batched import BatchedCutIn  # noqa: E402
from pemviz.scenarios.cut_in.committor import GRIDS, LMAX, LevelChain, continuous_level, level  # noqa: E402
from pemviz.scenarios.cut_in.lookahead import (
    DP_DEPTH,
    LOG_PVVY,
    VISIBLE,
    VX_ERROR,
    VY_ERROR,  # noqa: E402
    features,
)
from pemviz.scenarios.cut_in.problem import cut_in_params, cut_in_problem  # noqa: E402
from pemviz.scenarios.cut_in.scenario import MONTE_CARLO_REFERENCE  # noqa: E402
from pemviz.scenarios.cut_in.tilt import CutInTilt  # noqa: E402


def level_dist(grid, r: np.ndarray) -> np.ndarray:
    """Each class of ``grid``'s distribution of levels [k, 1 + NB^2, LMAX + 1] from the branches' robustness ``r`` [k,
    NBRANCH] (metres): a bin, half each edge's; a joint class, the error whose mean level is lower."""
    oh = np.eye(LMAX + 1)[level(r)]
    dr, dl = (np.einsum("nb,kbl->knl", mp, oh) for mp in grid.maps)
    el = np.arange(LMAX + 1)
    use_r = (dr @ el)[:, :, None] <= (dl @ el)[:, None, :]
    k = r.shape[0]
    out = np.empty((k, 1 + grid.nb * grid.nb, LMAX + 1))
    out[:, 0] = oh[:, 0]
    out[:, 1:] = np.where(use_r[..., None], dr[:, :, None, :], dl[:, None, :, :]).reshape(k, -1, LMAX + 1)
    return out


REFERENCE = MONTE_CARLO_REFERENCE["moderate"][0] / MONTE_CARLO_REFERENCE["moderate"][1]


@dataclass
class Step:
    """One look-ahead step of a batch: the rollouts, the drawn classes, the branches' robustness and next states."""

    t: int
    idx: np.ndarray
    cls: np.ndarray
    r: np.ndarray
    pc: np.ndarray
    bfeat: np.ndarray
    sfeat: np.ndarray
    ps: np.ndarray
    parent: np.ndarray


CACHE_KEY = (
    "setting",
    "grid",
    "window",
    "end",
    "graded",
    "errors",
    "one_car",
    "q_model",
    "a",
    "eps",
    "train_once",
    "iterations",
    "v_large",
    "continuous",
    "dp",
    "chain_effects",
    "dp_mass",
    "dp_lateral",
    "vx_buckets",
    "vy_buckets",
    "beam",
    "effect_model",
    "beta",
)
"""The options a V fitted by ``--train-once`` depends on: a ``--v-cache`` fitted with others is refused."""


def check_options(args: argparse.Namespace, n_steps: int) -> None:
    """Stop with one line (SystemExit) on options the study cannot run with, before anything is loaded."""
    w0, w1 = args.window
    if min(args.n) < 1 or not 0.0 < args.eps <= 1.0 or not 0.0 < args.a <= 1.0 or not 0.0 < args.beta <= 1.0:
        raise SystemExit(
            f"--n {' '.join(map(str, args.n))} --eps {args.eps} --a {args.a} --beta {args.beta}: need "
            f"every stage's rollouts >= 1, 0 < eps <= 1 (the PEMs' share), 0 < a <= 1 (a probability) "
            f"and 0 < beta <= 1 (the tilt's power)"
        )
    if not 0 <= w0 < w1 <= args.end <= n_steps:
        raise SystemExit(
            f"--window {w0} {w1} --end {args.end}: need 0 <= window start < window end <= end <= "
            f"{n_steps} (the scene's steps)"
        )
    if (args.continuous or args.dp) and not args.graded:
        raise SystemExit("--continuous and --dp need --graded (they read the continuations' lateral margins)")
    buckets = {"--vx-buckets": args.vx_buckets, "--vy-buckets": args.vy_buckets}
    unsorted = any(sorted(b) != b for b in buckets.values())
    if not 0.0 < args.dp_mass < 0.5 or not 0.0 <= args.dp_lateral < 0.5 or unsorted:
        raise SystemExit(
            f"--dp-mass {args.dp_mass} --dp-lateral {args.dp_lateral} "
            + " ".join(f"{k} {' '.join(map(str, b))}" for k, b in buckets.items())
            + ": need 0 < dp-mass < 0.5 and 0 <= dp-lateral < 0.5 (tail masses; 0: no lateral events) and "
            "the buckets' bounds ascending"
        )
    if args.effect_model and not (args.beam and args.chain_effects):
        raise SystemExit(
            "--effect-model needs --beam and --chain-effects (it is fitted on the beam's look-aheads and "
            "gives the effects --chain-effects reads)"
        )
    if (args.chain_effects or args.beam) and not args.dp or args.beam < 0:
        raise SystemExit(
            f"--chain-effects and --beam {args.beam} need --dp (they read or build its chain), and the "
            f"beam's bin width must be > 0"
        )
    if args.dp and w0 < DP_DEPTH:
        raise SystemExit(
            f"--dp needs the window to start at step {DP_DEPTH} or later (its event sequences reach "
            f"{DP_DEPTH} steps back), got --window {w0} {w1}"
        )
    if args.beam and not args.one_car:
        raise SystemExit("--beam needs --one-car (its representatives are states of the cut-in car alone)")
    if args.check_one_car and not args.graded:
        raise SystemExit("--check-one-car needs --graded (it compares the continuations' follow steps)")


class LookAheadTilt(CutInTilt):
    """The study (module docstring): one setting, grid, window and mixture; :meth:`simulate` runs a stage. Its
    look-aheads, beam and tilted stage are pemviz's (:class:`pemviz.scenarios.cut_in.tilt.CutInTilt`); the routes
    that lost (look-ahead branches, fitted V, Q model, event sequences) are the study's own."""

    def __init__(self, args: argparse.Namespace) -> None:
        from pemviz.pem import load_pem

        params = cut_in_params(args.setting)
        check_options(args, params.n_steps)
        self.problem = cut_in_problem(load_pem(), params)
        buckets = tuple((c, tuple(b)) for c, b in ((VX_ERROR, args.vx_buckets), (VY_ERROR, args.vy_buckets)) if b)
        super().__init__(
            params,
            self.problem.target,
            args.grid,
            tuple(args.window),
            args.end,
            args.beam or None,
            args.beta,
            args.eps,
            one_car=args.one_car,
            graded=args.graded,
            continuous=args.continuous or args.dp,
            errors=args.errors,
            error_buckets=buckets,
            dp_mass=args.dp_mass,
            effect_model=args.effect_model,
        )
        self.a, self.skip_doomed = args.a, args.skip_doomed
        self.check_one_car, self.agree = args.check_one_car, []
        self.chain_effects, self.dp_lateral = args.chain_effects, args.dp_lateral
        self.n_state = 18 if args.errors else 14
        self.v_size = (
            dict(max_iter=600, max_leaf_nodes=63, min_samples_leaf=5, early_stopping=False)
            if args.v_large
            else dict(max_iter=200, max_leaf_nodes=31, min_samples_leaf=10)
        )
        self.reset()

    def reset(self) -> None:
        self.branch_steps = self.one_steps = self.extrap_steps = 0
        self.v_table = self.model = self.q_model = None
        self.traces: list = []

    def solve_dp(self, h: float = 0.01, gmax: float = LMAX) -> LevelChain:
        """The committor as a function of the continuous level and the track's regime, U_t(G, k), solved on the
        nominal path (no pilot): at each step of the window, the states that every sequence of :data:`DP_DEPTH`
        events (none, a miss, a range error low or high at the grid edge nearest ``--dp-mass``: beyond the tracker's
        gate, a rejected measurement, or after a coast a restart; with ``--dp-lateral``, also a lateral error low or
        high) before it leaves are sorted into regimes (:meth:`regime`); the look-ahead from the likeliest state of
        each regime (the fewest events, then the fewest errors) gives every grid event's effect on G and the regime
        after it (:class:`LevelChain`). The sequences are simulated as a tree (each state of a level takes every
        event), and every step counts. Fine grid, ``--dp-mass 1e-3``: 7-12 regime states a step, 64,880 steps (649
        rollout-equivalents), 3 s here; lean grid: 376, under 1 s."""
        p, target, g = self.params, self.problem.target, self.grid
        depth = DP_DEPTH
        nev = 6 if self.dp_lateral else 4
        seqs = np.array(np.meshgrid(*[range(nev)] * depth, indexing="ij")).reshape(depth, -1).T  # [nev^depth, depth]
        rank = (seqs > 0).sum(axis=1) * 10 + (seqs > 1).sum(axis=1)
        order = np.argsort(rank, kind="stable")
        jr = g.edge(self.dp_mass)
        event_branch = [1, 0, 2 + jr, 2 + g.ng + jr]  # none, a miss, a range error low and high
        if self.dp_lateral:
            jl = g.edge(self.dp_lateral)
            event_branch += [2 + 2 * g.ng + jl, 2 + 3 * g.ng + jl]
        event_branch = np.array(event_branch)
        sim = BatchedCutIn(p, 1)
        history, self.pvvy_nom = [], {}
        p0s, effects, nexts, g_nom, states = {}, {}, {}, {}, {}
        nreg = self.n_regimes()
        for t in range(self.window[1] + 1):
            self.pvvy_nom[t] = float(features(sim.state, self.traj[t])[0, LOG_PVVY])
            if self.window[0] <= t < self.window[1] and sim.objects()[0, 0, VISIBLE] > 0.5:
                cand = BatchedCutIn(p, 1)
                cand.restore(history[-depth])
                for j in range(depth):  # a tree: each state of the last level takes every event (prefix order)
                    size = nev ** (j + 1)
                    state = cand.snapshot().select(np.repeat(np.arange(size // nev), nev))
                    cand = BatchedCutIn(p, size)
                    cand.restore(state)
                    prow = np.ascontiguousarray(cand.objects())
                    det = prow[:, :, VISIBLE] > 0.5
                    rep = event_branch[np.tile(np.arange(nev), size // nev)]
                    det[:, 0] &= rep != 0
                    noise = np.zeros((size, p.n_objects, 2))
                    noise[det[:, 0], 0] = target.noise_from_uniforms(prow[det[:, 0], 0], g.reps[rep[det[:, 0]], 1:])
                    cand.step(det, noise)
                    self.count(cand, size)
                reg = self.regime(features(cand.state, self.traj[t], self.errors), t)
                chosen = {}
                for i in order:  # the likeliest state of each regime; order[0]: no event, the nominal path itself
                    chosen.setdefault(int(reg[i]), int(i))
                idx = np.array(list(chosen.values()))
                u = np.tile([0.0, 0.5, 0.5], (seqs.shape[0], p.n_objects, 1))
                r, bfeat = self.look_ahead(
                    cand, idx, u, np.ascontiguousarray(cand.objects()), np.full(seqs.shape[0], np.inf)
                )
                gl = continuous_level(level(r), bfeat[..., -2], bfeat[..., -1])
                effects[t] = dict(zip(chosen, gl - gl[:, 1:2], strict=False))
                nexts[t] = dict(zip(chosen, self.regime(bfeat, t + 1), strict=False))
                g_nom[t], states[t] = float(gl[0, 1]), idx.size
                p0s[t] = float(expit(target.detect_logit(np.ascontiguousarray(sim.objects())[:1, 0]))[0])
            history.append(sim.snapshot())
            if t < p.n_steps:
                sim.step(sim.objects()[:, :, VISIBLE] > 0.5, None)
        return LevelChain(g, self.window, p0s, effects, nexts, nreg, h, gmax, g_nom, states)

    def log_q_table(self, r: np.ndarray, t: int, feats: np.ndarray | None = None) -> np.ndarray:
        """log V(level, t + 1) of the branches [k, NBRANCH] from the level table (``a`` ^ L before the first fit;
        ``--continuous`` with ``feats``: ``a`` ^ G, :func:`continuous_level`)."""
        lv = level(r)
        if self.v_table is None:
            if self.continuous and feats is not None:
                gl = continuous_level(lv, feats[..., -2], feats[..., -1])
                if self.chain is not None:
                    return self.chain.log_u(t + 1, gl, self.regime(feats, t + 1))
                return gl * np.log(self.a)
            return lv * np.log(self.a)
        return np.log(self.v_table[lv, t + 1 - self.window[0]])

    def one_step(self, pc: np.ndarray, r: np.ndarray, t: int) -> np.ndarray:
        """log sum_c p(c) V_table(L_c, t + 1) [k]: a state's one-step value from the table."""
        return logsumexp(np.log(pc) + self.grid.class_values(self.log_q_table(r, t)), axis=1)

    def log_q_hat(self, r: np.ndarray, feats: np.ndarray, t: int, ps: np.ndarray) -> np.ndarray:
        """log Q(s, branch) [k, NBRANCH] of the branches' next states at step t + 1 (ps: the state's one-step value)."""
        table = self.log_q_table(r, t, feats)
        if self.model is None or t + 1 >= self.window[1]:
            return table
        lv = level(r)
        x = np.concatenate(
            [
                feats,
                lv[..., None],
                np.full(lv.shape + (1,), t + 1.0),
                np.broadcast_to(ps[:, None, None], lv.shape + (1,)),
            ],
            axis=-1,
        )
        pred = self.model.predict(x.reshape(-1, x.shape[-1])).reshape(lv.shape)
        return np.where(lv == 0, table, np.minimum(pred, 0.0))

    def q_inputs(self, sfeat: np.ndarray, t: int) -> np.ndarray:
        """The Q model's inputs at every branch event [k NBRANCH, n_state + 4]: the state, the step, the event."""
        k, kk = sfeat.shape[0], self.grid.nbranch
        return np.concatenate(
            [
                np.repeat(sfeat[:, None, : self.n_state], kk, axis=1),
                np.full((k, kk, 1), float(t)),
                np.broadcast_to(self.grid.desc, (k, kk, 3)),
            ],
            axis=2,
        ).reshape(k * kk, -1)

    def branch_log_q(
        self,
        sim: BatchedCutIn,
        t: int,
        idx: np.ndarray,
        u: np.ndarray,
        rows: np.ndarray,
        prefix_min: np.ndarray,
        sfeat: np.ndarray,
        p0: np.ndarray,
    ) -> np.ndarray:
        """log Q of the branches [k, NBRANCH] by the study's route: a Q model, the chain's effects (pemviz's), or a
        look-ahead of every branch scored by the chain, the level table or the fitted V (its step kept for the fit)."""
        self._step = None
        if self.q_model is not None:
            return np.minimum(self.q_model.predict(self.q_inputs(sfeat, t)).reshape(idx.size, -1), 0.0)
        if self.chain_effects:  # one continuation (the state's own G); the events' from the chain
            return super().branch_log_q(sim, t, idx, u, rows, prefix_min, sfeat, p0)
        r, bfeat = self.look_ahead(sim, idx, u, rows, prefix_min)
        if self.check_one_car:  # the same branches on the cut-in car alone
            self.one_car = True
            r1, b1 = self.look_ahead(sim, idx, u, rows, prefix_min)
            self.one_car = False
            self.agree.append(
                np.column_stack([level(r).ravel() == level(r1).ravel(), bfeat[..., -3].ravel() == b1[..., -3].ravel()])
            )
        if self.graded:
            sfeat = np.column_stack([sfeat, bfeat[:, 1, -3:]])
        ps = self.one_step(self.grid.p_class(p0), r, t)
        self._step = Step(t, idx, None, r, None, bfeat, sfeat, ps, self.parent[idx].copy())
        self.parent[idx] = ps
        return self.log_q_hat(r, bfeat, t, ps)

    def drawn(self, t: int, idx: np.ndarray, cls: np.ndarray, pc: np.ndarray) -> None:
        """Keep a look-ahead step for the fit; with ``--skip-doomed``, no look-ahead after a class whose edges both
        fail."""
        step = self._step
        if step is not None:
            step.cls, step.pc = cls, pc
            self._trace.append(step)
            if self.skip_doomed:
                self.doomed[idx] = level_dist(self.grid, step.r)[np.arange(idx.size), cls, 0] > 0.99

    def simulate(self, n: int, rng: np.random.Generator, given: np.ndarray | None = None):
        """One stage of n rollouts: (failed bool [n], log w [n], cost in rollout-equivalents, kinematic steps / T).
        ``given`` [T, n, M, 3]: replay these uniforms (their classes scored, nothing drawn)."""
        self.parent, self._trace = np.full(n, np.nan), []
        e0 = self.extrap_steps
        batch, log_w, steps = self.stage(n, rng, given)
        failed = self.problem.failed(batch, self.problem.robustness(batch, "classic"))
        if given is None:
            self.traces.append((n, self._trace, failed))
        return failed, log_w, n + steps / self.params.n_steps, (self.extrap_steps - e0) / self.params.n_steps

    def fit(self, iterations: int) -> None:
        """V(L, t) from the level kernel of every stage so far, then log V on the branches' next states by fitted value
        iteration (module docstring)."""
        from sklearn.ensemble import HistGradientBoostingRegressor

        w0, w1 = self.window
        width = w1 - w0
        kern, counts = np.zeros((width, LMAX + 1, LMAX + 1)), np.zeros((width, LMAX + 1))
        ends, fails = [], []
        for n, trace, failed in self.traces:
            after = np.full(n, -1)
            for s in trace:
                dist = level_dist(self.grid, s.r)
                ls = level(s.r[:, 1])
                np.add.at(kern[s.t - w0], ls, np.einsum("kc,kcl->kl", s.pc, dist))
                np.add.at(counts[s.t - w0], ls, 1)
                after[s.idx] = np.argmax(dist[np.arange(s.idx.size), s.cls], axis=1)
            ends.append(after)
            fails.append(failed)
        after, failed = np.concatenate(ends), np.concatenate(fails)
        kern /= np.maximum(counts, 1)[:, :, None]
        for j, big_l in zip(*np.nonzero(counts == 0), strict=False):
            kern[j, big_l] = 0.0
            kern[j, big_l, big_l] = 1.0
        v = np.zeros((LMAX + 1, width + 1))
        for big_l in range(LMAX + 1):
            sel = after == big_l
            v[big_l, width] = failed[sel].mean() if sel.sum() >= 5 else float(big_l == 0)
        v[0, width] = max(v[0, width], 0.5)
        v[1:, width] = np.maximum(v[1:, width], 1e-9)
        for j in range(width - 1, -1, -1):
            v[:, j] = kern[j] @ v[:, j + 1]
        self.v_table, self.model = np.maximum(v, 1e-12), None
        steps = [s for _, trace, _ in self.traces for s in trace]
        x = np.concatenate(
            [
                np.column_stack(
                    [
                        s.sfeat,
                        level(s.r[:, 1]),
                        np.full(s.idx.size, float(s.t)),
                        np.where(np.isnan(s.parent), np.log(self.v_table[level(s.r[:, 1]), s.t - w0]), s.parent),
                    ]
                )
                for s in steps
            ]
        )
        pss = [self.one_step(s.pc, s.r, s.t) for s in steps]  # the states' one-step values from the new table
        for _ in range(iterations):
            y = np.concatenate(
                [
                    logsumexp(np.log(s.pc) + self.grid.class_values(self.log_q_hat(s.r, s.bfeat, s.t, ps)), axis=1)
                    for s, ps in zip(steps, pss, strict=False)
                ]
            )
            self.model = HistGradientBoostingRegressor(learning_rate=0.1, random_state=0, **self.v_size).fit(x, y)

    def fit_q_model(self) -> None:
        """log Q(s, event) on the state, the step and the event (:func:`event_descriptor`), on every look-ahead branch
        so far, the targets the look-ahead's Q."""
        from sklearn.ensemble import HistGradientBoostingRegressor

        steps = [s for _, trace, _ in self.traces for s in trace]
        x = np.concatenate([self.q_inputs(s.sfeat, s.t) for s in steps])
        y = np.concatenate([self.log_q_hat(s.r, s.bfeat, s.t, s.ps).reshape(-1) for s in steps])
        self.q_model = HistGradientBoostingRegressor(
            max_iter=300, learning_rate=0.1, max_leaf_nodes=63, min_samples_leaf=20, random_state=0
        ).fit(x, y)


def mc_failures(study: LookAheadTilt, n: int, rng: np.random.Generator, chunk: int = 20000) -> np.ndarray:
    """The uniforms [T, F, M, 3] of the failures among n plain Monte Carlo rollouts."""
    params, target = study.params, study.problem.target
    kept = []
    for start in range(0, n, chunk):
        size = min(chunk, n - start)
        u = rng.random((params.n_steps, size, params.n_objects, 3))
        with np.errstate(divide="ignore"):
            batch = run_batched(
                BatchedCutIn(params, size),
                size,
                params.n_steps,
                target,
                target,
                (u[t].reshape(-1) for t in range(params.n_steps)),
                keep_rows=False,
            )
        kept.append(u[:, study.problem.failed(batch, study.problem.robustness(batch, "classic"))])
    return np.concatenate(kept, axis=1)


def mc_rollout_seconds(study: LookAheadTilt, n: int = 4000) -> float:
    """Seconds a plain Monte Carlo rollout of the twin takes here (``n`` drawn from the PEMs in one batch)."""
    problem = study.problem
    t0 = time.perf_counter()
    problem.failed(problem.simulate(n, problem.target, problem.target, np.random.default_rng(0)))
    return (time.perf_counter() - t0) / n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--n", type=int, nargs="+", default=[1000, 1000], help="rollouts per stage")
    ap.add_argument("--window", type=int, nargs=2, default=(10, 24), help="steps of the cut-in car that are tilted")
    ap.add_argument("--end", type=int, default=32, help="the continuations' last step")
    ap.add_argument("--grid", choices=tuple(GRIDS), default="fine")
    ap.add_argument("--a", type=float, default=4e-3, help="the first stage's Q = a^L")
    ap.add_argument("--eps", type=float, default=0.3, help="the PEMs' share of each step's proposal")
    ap.add_argument("--iterations", type=int, default=10, help="fitted value iterations")
    ap.add_argument("--graded", action="store_true", help="the continuation's follow step, lateral margins as inputs")
    ap.add_argument("--continuous", action="store_true", help="Q = a^G before a fit, G the level made continuous")
    ap.add_argument("--dp", action="store_true", help="Q = U_t(G), the level chain solved on the nominal path")
    ap.add_argument(
        "--chain-effects",
        action="store_true",
        help="with --dp: one continuation a step; every event's effect and next regime from the chain",
    )
    ap.add_argument(
        "--effect-model",
        action="store_true",
        help="with --beam --chain-effects: each event's effect from a model of the beam's look-aheads",
    )
    ap.add_argument(
        "--beam",
        type=float,
        default=0.0,
        metavar="WIDTH",
        help="with --dp: the chain's cells are (regime, bin of G of WIDTH), found by a beam of events",
    )
    ap.add_argument("--dp-mass", type=float, default=1e-3, help="tail mass of the chain's range errors")
    ap.add_argument("--beta", type=float, default=1.0, help="the tilt's power: q proportional to p Q^beta")
    ap.add_argument("--dp-lateral", type=float, default=0.0, help="tail mass of the chain's lateral errors (0: none)")
    ap.add_argument("--vx-buckets", type=float, nargs="*", default=[], help="regime bounds of the track's vx error")
    ap.add_argument("--vy-buckets", type=float, nargs="*", default=[], help="regime bounds of the track's vy error")
    ap.add_argument("--skip-doomed", action="store_true", help="no look-ahead after a class whose edges both fail")
    ap.add_argument("--q-model", action="store_true", help="the last stage without look-ahead (a learned Q)")
    ap.add_argument("--v-large", action="store_true", help="V: 600 trees of 63 leaves (else 200 of 31)")
    ap.add_argument("--one-car", action="store_true", help="look ahead on the cut-in car alone (the OneCar twin)")
    ap.add_argument(
        "--check-one-car",
        action="store_true",
        help="run every look-ahead both ways; print how often the levels and follow steps agree",
    )
    ap.add_argument("--errors", action="store_true", help="V and Q also read the track's errors against the truth")
    ap.add_argument(
        "--train-once",
        type=int,
        default=None,
        metavar="SEED",
        help="fit V on every stage but the last once, with this seed; then only the last stage per seed",
    )
    ap.add_argument(
        "--v-cache",
        default=None,
        metavar="PATH",
        help="with --train-once: read the fitted V from PATH if it exists, else fit it and write it there",
    )
    ap.add_argument("--mc-failures", type=int, default=0, help="replay the failures of N plain Monte Carlo rollouts")
    ap.add_argument("--setting", default="moderate")
    args = ap.parse_args()
    study = LookAheadTilt(args)
    if args.dp:
        t0 = time.perf_counter()
        study.chain = study.solve_beam(args.beam) if args.beam else study.solve_dp()
        u_nom = {t: float(np.exp(study.chain.log_u(t, np.array(g)))) for t, g in study.chain.g_nom.items()}
        steps, states = study.one_steps + study.branch_steps, study.chain.states.values()
        print(
            f"level chain solved on the nominal path in {time.perf_counter() - t0:.1f} s ({min(states)}-"
            f"{max(states)} regime states a step, {steps:,} continuation steps = {steps / study.params.n_steps:,.0f} "
            f"rollout-equivalents); its own p_fail "
            f"{u_nom[min(u_nom)]:.2e} (x{u_nom[min(u_nom)] / REFERENCE:.2f} of the reference); U at the nominal "
            f"state of steps " + ", ".join(f"{t}: {v:.1e}" for t, v in u_nom.items())
        )
    print(
        f"cut-in, {args.setting} setting (reference {REFERENCE:.3g}); stages {args.n}, window {args.window}, grid "
        f"{args.grid} ({study.grid.nbranch} branches), eps {args.eps}" + (", Q model" if args.q_model else "")
    )
    t_mc = mc_rollout_seconds(study)
    print(
        f"a plain Monte Carlo rollout takes {t_mc * 1e3:.2f} ms here (4,000 from the PEMs); plain Monte Carlo's "
        f"median relative error 0.2 (1.3e5 rollouts) takes {1.3e5 * t_mc:.0f} s"
    )
    ratios = []

    def stages(ns: list[int], rng: np.random.Generator, fit_last: bool) -> tuple:
        """Run stages ``ns``, fitting after each but (unless ``fit_last``) the last: (failed, log w, cost,
        kinematic, (the last stage's cost, seconds))."""
        cost = extra = 0.0
        for i, n in enumerate(ns):
            t_last = time.perf_counter()
            failed, log_w, c, e = study.simulate(n, rng)
            cost, extra, last = cost + c, extra + e, (c, time.perf_counter() - t_last)
            if i < len(ns) - 1 or fit_last:
                study.fit(args.iterations)
                if args.q_model and i == len(args.n) - 2:
                    study.fit_q_model()
        return failed, log_w, cost, extra, last

    if args.train_once is not None:  # V fitted once (a cached V), then only the last stage per seed
        t0 = time.perf_counter()
        study.reset()
        cache = Path(args.v_cache) if args.v_cache else None
        key = tuple(
            (name, repr(tuple(v) if isinstance(v, list) else v))
            for name, v in [(k, getattr(args, k)) for k in CACHE_KEY] + [("training stages", args.n[:-1])]
        )
        if cache is not None and cache.exists():
            try:
                with cache.open("rb") as f:
                    cached_key, study.v_table, study.model, study.q_model = pickle.load(f)
            except (OSError, EOFError, ValueError, TypeError, pickle.UnpicklingError) as err:
                raise SystemExit(
                    f"--v-cache {cache}: not a V this study wrote ({type(err).__name__}); give another "
                    f"path, or remove it to fit V again"
                ) from None
            if cached_key != key:
                mine = dict(key)
                other = dict(cached_key) if isinstance(cached_key[0], tuple) else {"format": "an older study"}
                diff = ", ".join(
                    f"{k} {other.get(k, '-')} (here {mine.get(k, '-')})"
                    for k in dict.fromkeys([*other, *mine])
                    if other.get(k) != mine.get(k)
                )
                raise SystemExit(f"--v-cache {cache}: fitted for other settings: {diff}")
            print(f"  V read from {cache} (trained before; its cost is not this run's)")
        else:
            *_, cost, extra, _ = stages(args.n[:-1], np.random.default_rng(args.train_once), True)
            study.traces.clear()
            wall = time.perf_counter() - t0
            print(
                f"  V trained once (seed {args.train_once}, stages {args.n[:-1]}): cost {cost:,.0f} (+{extra:,.0f} "
                f"kinematic), {wall:.0f} s = {wall / t_mc:,.0f} plain Monte Carlo rollouts"
            )
            if cache is not None:  # written whole, then renamed: never half a file
                part = cache.with_name(cache.name + ".part")
                with part.open("wb") as f:
                    pickle.dump((key, study.v_table, study.model, study.q_model), f)
                part.replace(cache)
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        t0 = time.perf_counter()
        rng = np.random.default_rng(seed)
        if args.train_once is None:
            study.reset()
            failed, log_w, cost, extra, last = stages(args.n, rng, False)
        else:
            failed, log_w, cost, extra, last = stages(args.n[-1:], rng, False)
            study.traces.pop()
        wall = time.perf_counter() - t0
        est = estimate(log_w, failed, np.zeros(failed.size))
        ratios.append(est.mu_hat / REFERENCE)
        print(
            f"  seed {seed}: {est.mu_hat:.3e} {est.interval_text()} x{ratios[-1]:.2f} "
            f"({'holds' if est.covers(float(np.log(REFERENCE))) else 'misses'} the reference), {est.n_failures} "
            f"failures, ESS {est.ess:.1f}, k-hat {est.khat:.2f}, {est.verdict}; cost {cost:,.0f} (+{extra:,.0f} "
            f"kinematic), {wall:.0f} s = {wall / t_mc:,.0f} plain Monte Carlo rollouts; the last stage alone (V "
            f"fitted before it): cost {last[0]:,.0f}, {last[1]:.0f} s = {last[1] / t_mc:,.0f}",
            flush=True,
        )
    r = np.array(ratios)
    print(
        f"median relative error {np.median(np.abs(r - 1)):.2f} (target <= 0.2); within x2 in "
        f"{int(np.sum((r >= 0.5) & (r <= 2)))} of {r.size}"
    )
    if study.agree:
        agree = np.concatenate(study.agree)
        print(
            f"the cut-in car alone against the whole twin, {agree.shape[0]:,} branches: the same level in "
            f"{agree[:, 0].mean():.4%}, the same follow step in {agree[:, 1].mean():.4%}"
        )
    if args.mc_failures:
        u = mc_failures(study, args.mc_failures, np.random.default_rng(12345))
        failed, log_w, _, _ = study.simulate(u.shape[1], rng, given=u)
        print(
            f"{u.shape[1]} failures in {args.mc_failures:,} plain Monte Carlo rollouts, replayed through the last "
            f"proposal: log w (zero variance: {np.log(REFERENCE):.2f} each) {np.round(np.sort(log_w)[::-1], 1)}; "
            f"{int(np.sum(log_w > -5.0))} above -5; the proposal's relative variance a rollout, E_p[w | fail] / p - "
            f"1 from them: {np.exp(log_w).mean() / REFERENCE - 1:,.0f} (plain Monte Carlo: 1 / p - 1 = "
            f"{1 / REFERENCE - 1:,.0f})"
        )


if __name__ == "__main__":
    main()
