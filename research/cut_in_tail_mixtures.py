"""Defensive tail mixtures over the cut-in car's perception uniforms on the cut-in scenario's moderate setting
(reference 8.66e-5 from 10^7 plain Monte Carlo rollouts,
:data:`pemviz.scenarios.cut_in.scenario.MONTE_CARLO_REFERENCE`): a study of how far a proposal with bounded weights and
no state gets at a tenth of plain Monte Carlo's cost.

A rollout of the batched twin is a deterministic function of its uniforms (per step and object: the detection's, then
the range and lateral errors', in the order :func:`pemviz.core.lockstep.run_batched` reads them), whose density under
the PEMs is 1. At each step t of ``--window`` where the cut-in car (object 0) is visible, its uniforms are drawn from a
defensive mixture (Hesterberg 1995, Technometrics 37(2)):

- detection: with probability eps[t, 0] a forced miss (u uniform on (p(detect), 1)), else u uniform on (0, 1);
- each error of a detected car: with probability eps[t, side] a tail draw whose tail mass m = min(u, 1 - u) is
  log-uniform on [``--mmin``, ``--mmax``] on that side, else u uniform on (0, 1) (a missed car's errors are not used
  and are drawn uniformly).

The importance weight is 1 / q(U), exactly, and every factor is at most 1 / (1 - eps): no weight can explode. Modes:

- ``fixed``: eps the same at every step (``--eps``: a miss; each error's two tails share it), one batch;
- ``ce``: a first batch as ``fixed``, then eps[t, component] refitted per step, component (a miss, each side of each
  error) by one EM step of the cross-entropy method on the first batch's failures weighted by their importance weights
  (clipped to [``--eps-min``, ``--eps-max``]), then the second batch. Cost = both batches.

- ``amis``: adaptive multiple importance sampling (Cornuet, Marin, Mira & Robert 2012, Scand. J. Stat. 39(4)):
  batches of ``--n`` (default 2,000, 3,000, 4,000, 4,000), after each eps refitted as in ``ce`` on every rollout so far,
  each weighed by the deterministic mixture of all the batches' proposals (:meth:`TailMixtures.log_q`: the balance
  heuristic, Veach & Guibas 1995); the estimate uses all of them, so no batch is spent only on the refit.
- ``ams``: a ``fixed`` batch (``--n``, default 3,000) trains a learned committor V(s) = P(failure | the cut-in car's
  row and the step) (:func:`fit_committor`), and adaptive multilevel splitting (:mod:`pemviz.estimators.ams`, N =
  ``--ams-n``, k = ``--ams-k``) ranks prefixes by -log V instead of the robustness (whose levels tie). Cost = the
  batch + the splitting's rollout-equivalents.

``--diag K`` prints, for the last seed, the K failures that carry the most weight with the cut-in car's events in
steps 5-39 (a miss; an error with tail mass below 1e-2: ``r+3e-04`` is a range error in the upper tail at mass 3e-4).

Measured (2-core developer machine with other work running; the printed lines of the commands below):

- ``fixed`` (window 10-26, eps 0.02 / 0.02, tails 1e-8..1e-2; 13,000 rollouts, 8 seeds): x1.84 0.47 0.52 0.80 0.33
  0.39 0.54 0.53 of the reference, median relative error 0.51, 5 of 8 within x2, 3 of 8 intervals hold it, 410-500
  failures a run, ESS 3.5-25, verdicts ``unreliable`` (7) and ``doubtful`` (1).
- ``ce`` (4,000 + 9,000, 4 seeds): x0.79 0.53 0.28 0.92, median 0.34, 1,600-2,000 failures in the second batch; seed
  2 says ``reliable`` (ESS 72, k-hat 0.64) with its interval [1.9e-5, 3.0e-5] below the reference: a verdict from the
  drawn weights cannot see mass the proposal never draws.
- ``amis`` (2,000 + 3,000 + 4,000 + 4,000, all weighed, 8 seeds): x0.43 0.36 0.42 0.27 0.40 0.42 0.65 0.32, median
  0.59, 1 of 8 within x2, 3 of 8 intervals hold it; seeds 3 and 7 say ``reliable`` (ESS 94 and 73) while 3.7 and 3.1
  times low: recycling every batch sharpens the estimate around the modes the refit settled on.
- ``fixed`` with the tails on [1e-6, 1e-2] instead (eps 0.02 / 0.02, or 0.03 / 0.06; 8 seeds): median 0.43 and 0.41.
- ``ams`` (3,000 + AMS N = 1,000, k = 100: 10,400-12,300 rollout-equivalents, 6 seeds): x0.02 1.04 0.45 0.19 0.13
  0.63, median 0.68, every verdict ``doubtful`` (the failures descend from a few initial rollouts).
- ``--diag 12`` on ``fixed`` seed 2: the 12 heaviest failures carry 61 % of the weight, e.g. a miss then a range error
  at tail mass 1e-4..1e-5 the next step (``17:miss 18:r-9e-05``), two moderate range errors in a row: drawn at about
  the PEMs' own rate. A proposal boosts an event at tail mass m by eps / (2 m L) (L = ln(mmax / mmin)), so boosting
  every step's moderate errors ten-fold needs more probability than there is, and which step's error decides depends
  on the tracker's state: the measured case for a state-dependent proposal.

Usage::

    python research/cut_in_tail_mixtures.py --seeds 8
    python research/cut_in_tail_mixtures.py --mode ce --seeds 4
    python research/cut_in_tail_mixtures.py --mode amis --seeds 8
    python research/cut_in_tail_mixtures.py --seeds 1 --first-seed 2 --diag 12
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.special import expit, logsumexp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pemviz.core.estimate import estimate  # noqa: E402
from pemviz.core.lockstep import run_batched  # noqa: E402
from pemviz.scenarios.cut_in.batched import BatchedCutIn  # noqa: E402
from pemviz.scenarios.cut_in.problem import cut_in_params, cut_in_problem  # noqa: E402
from pemviz.scenarios.cut_in.scenario import MONTE_CARLO_REFERENCE, OBJECT_NAMES  # noqa: E402

REFERENCE = MONTE_CARLO_REFERENCE["moderate"][0] / MONTE_CARLO_REFERENCE["moderate"][1]
VISIBLE = OBJECT_NAMES.index("visible")
COMPONENTS = ("miss", "range low", "range high", "lateral low", "lateral high")
DIAG_STEPS = (5, 40)
FEATURES = (
    "range_m",
    "gap_m",
    "rel_speed_mps",
    "lateral_speed_mps",
    "loc_x",
    "occluded_fraction",
    "visible",
    "tracked",
    "track_err_x_m",
    "track_err_y_m",
    "followed",
    "ego_speed_mps",
    "ego_accel_mps2",
)
"""The cut-in car's row columns the learned committor reads (with the step)."""
FEATURE_STEPS = (5, 40)
"""Steps at which the learned committor scores a rollout (the failures' decisive events lie in 11-23)."""


def committor_inputs(rows0: np.ndarray, t: int) -> np.ndarray:
    """The committor's inputs at step t, float64 [n, F + 1]: the cut-in car's row columns :data:`FEATURES`, the step."""
    cols = [OBJECT_NAMES.index(f) for f in FEATURES]
    return np.column_stack([rows0[:, cols], np.full(rows0.shape[0], float(t))])


def fit_committor(failed: np.ndarray, step_log_w: np.ndarray, features: np.ndarray):
    """A classifier of P(failure | state at step t) under the PEMs (scikit-learn's HistGradientBoostingClassifier)
    from a tail-mixture batch: every (rollout, step in :data:`FEATURE_STEPS`) is a sample labelled with the rollout's
    failure and weighted by the likelihood ratio p / q of its steps from t on, so that the weighted failure rate given
    the state is P_p(failure | state)."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    future = np.cumsum(step_log_w[:, ::-1], axis=1)[:, ::-1][:, FEATURE_STEPS[0] : FEATURE_STEPS[1]]
    x = features.reshape(-1, features.shape[-1])
    y = np.repeat(failed, features.shape[1])
    model = HistGradientBoostingClassifier(
        max_iter=200, learning_rate=0.1, max_leaf_nodes=15, min_samples_leaf=20, l2_regularization=1.0, random_state=0
    )
    return model.fit(x, y, sample_weight=np.exp(future.reshape(-1)))


def committor_score(problem, model):
    """An AMS prefix score for :func:`pemviz.estimators.ams.running_score`'s place: the running minimum over the
    steps of -log V(state) (V the classifier's P(failure)) at :data:`FEATURE_STEPS`, and of the failure formula's
    operand robustness where it is negative (a failure), float64 [N, T]; failure: the last column < 0."""
    from pemviz import stl

    lo, hi = FEATURE_STEPS

    def score(_problem, batch):
        rows = batch.object_rows[:, lo:hi, 0, :]
        n, width = rows.shape[:2]
        x = np.concatenate([committor_inputs(rows[:, j], lo + j)[:, None] for j in range(width)], axis=1)
        v = model.predict_proba(x.reshape(n * width, -1))[:, 1].reshape(n, width)
        out = np.full((n, batch.n_steps), np.inf)
        out[:, lo:hi] = -np.log(np.clip(v, 1e-300, 1.0 - 1e-12))
        rho = np.array(stl.robustness_signal(problem.formula.operand, problem.signal_arrays(batch), "classic"))
        return np.minimum.accumulate(np.where(rho < 0.0, rho, out), axis=1)

    return score


class TailMixtures:
    """The cut-in's moderate setting with the cut-in car's uniforms drawn from per-step defensive tail mixtures."""

    def __init__(self, window: tuple[int, int], m_min: float, m_max: float) -> None:
        from pemviz.pem import load_pem

        self.params = cut_in_params("moderate")
        self.problem = cut_in_problem(load_pem(), self.params)
        self.window, self.m_min, self.m_max = window, m_min, m_max
        self.log_range = np.log(m_max / m_min)

    def tail_density(self, u: np.ndarray, side: int) -> np.ndarray:
        """The one-sided log-uniform tail density at u, float64 [k] (side 0: the lower tail, 1: the upper)."""
        m = u if side == 0 else 1.0 - u
        return np.where((m >= self.m_min) & (m <= self.m_max), 1.0 / (m * self.log_range), 0.0)

    def log_q(self, eps: np.ndarray, kept: np.ndarray, p_kept: np.ndarray, seen: np.ndarray) -> np.ndarray:
        """log q(U) of rollouts' uniforms under the mixtures ``eps`` [W, 5] (nats, [n]; ``kept``, ``p_kept``,
        ``seen`` as :meth:`simulate` returns them): the sum over the window's visible steps of the detection's and,
        for a detected car, both errors' mixture densities (the PEMs' own density is 1, so log w = -log q)."""
        out = np.zeros(kept.shape[0])
        with np.errstate(divide="ignore", invalid="ignore"):  # p = 1 where the car is not visible (masked)
            for j in range(eps.shape[0]):
                u, p, e = kept[:, self.window[0] + j], p_kept[:, j], eps[j, 0]
                miss = u[:, 0] > p
                term = np.log((1.0 - e) + np.where(miss, e / (1.0 - p), 0.0))
                for c in range(2):
                    lo, hi = eps[j, 1 + 2 * c], eps[j, 2 + 2 * c]
                    g = (
                        (1.0 - lo - hi)
                        + lo * self.tail_density(u[:, 1 + c], 0)
                        + hi * self.tail_density(u[:, 1 + c], 1)
                    )
                    term = term + np.where(miss, 0.0, np.log(g))
                out += np.where(seen[:, j], term, 0.0)
        return out

    def simulate(self, n: int, eps: np.ndarray, rng: np.random.Generator):
        """(failed bool [n], log w [n] (nats), object 0's uniforms [n, T, 3], its p(detect) [n, W], visible [n, W],
        its detections bool [n, T], the per-step log weights [n, T] (nats), its committor features [n, R, F] at the
        steps :data:`FEATURE_STEPS`).

        eps: float64 [W, 5], the mixture weights per window step of :data:`COMPONENTS`.
        """
        params, target, m = self.params, self.problem.target, self.params.n_objects
        w0 = self.window[0]
        sim = BatchedCutIn(params, n)
        log_w = np.zeros(n)
        kept = np.zeros((n, params.n_steps, 3))
        p_kept, seen = np.ones((n, eps.shape[0])), np.zeros((n, eps.shape[0]), dtype=bool)
        step_log_w = np.zeros((n, params.n_steps))
        features = np.zeros((n, FEATURE_STEPS[1] - FEATURE_STEPS[0], len(FEATURES) + 1))

        def uniforms():
            for t in range(params.n_steps):
                u = rng.random(n * m * 3).reshape(n, m, 3)
                rows0 = np.ascontiguousarray(sim.objects()[:, 0, :])
                if FEATURE_STEPS[0] <= t < FEATURE_STEPS[1]:
                    features[:, t - FEATURE_STEPS[0]] = committor_inputs(rows0, t)
                if w0 <= t < self.window[1]:
                    j = t - w0
                    idx = np.flatnonzero(rows0[:, VISIBLE] > 0.5)
                    p = expit(target.detect_logit(rows0[idx]))
                    x, k = rng.random((idx.size, 3)), idx.size
                    e_miss = eps[j, 0]
                    forced = rng.random(k) < e_miss
                    ud = np.where(forced, p + x[:, 0] * (1.0 - p), x[:, 0])
                    lw = -np.log((1.0 - e_miss) + np.where(ud > p, e_miss / (1.0 - p), 0.0))
                    hit = ud <= p
                    ue = x[:, 1:].copy()
                    for c in range(2):
                        lo, hi = eps[j, 1 + 2 * c], eps[j, 2 + 2 * c]
                        r = rng.random(k)
                        mass = self.m_max * np.exp(-rng.random(k) * self.log_range)
                        drawn = np.where(r < lo, mass, np.where(r < lo + hi, 1.0 - mass, x[:, 1 + c]))
                        g = (1.0 - lo - hi) + lo * self.tail_density(drawn, 0) + hi * self.tail_density(drawn, 1)
                        lw -= np.where(hit, np.log(g), 0.0)
                        ue[:, c] = np.where(hit, drawn, x[:, 1 + c])
                    u[idx, 0] = np.column_stack([ud, ue])
                    log_w[idx] += lw
                    step_log_w[idx, t] = lw
                    p_kept[idx, j], seen[idx, j] = p, True
                kept[:, t] = u[:, 0]
                yield u.reshape(-1)

        with np.errstate(divide="ignore"):
            batch = run_batched(sim, n, params.n_steps, target, target, uniforms(), keep_rows=False)
        failed = self.problem.failed(batch, self.problem.robustness(batch, "classic"))
        return failed, log_w, kept, p_kept, seen, batch.detected[:, :, 0], step_log_w, features

    def refit(self, eps: np.ndarray, failed, log_w, kept, p_kept, seen, eps_min: float, eps_max: float) -> np.ndarray:
        """One EM step of the cross-entropy update of every mixture weight on the failures, weighted by their
        importance weights (each weight: the weighted mean responsibility of its component), clipped."""
        f = np.flatnonzero(failed)
        if not f.size:
            return eps
        w = np.exp(log_w[f] - log_w[f].max())
        w /= w.sum()
        new = np.empty_like(eps)
        for j in range(eps.shape[0]):
            u = kept[f, self.window[0] + j]
            p, vis = p_kept[f, j], seen[f, j]
            miss = vis & (u[:, 0] > p)
            e = eps[j, 0]
            new[j, 0] = np.sum(w * np.where(miss, (e / (1 - p)) / ((1 - e) + e / (1 - p)), 0.0))
            detected = vis & ~miss
            for c in range(2):
                lo, hi, uc = eps[j, 1 + 2 * c], eps[j, 2 + 2 * c], u[:, 1 + c]
                g = (1.0 - lo - hi) + lo * self.tail_density(uc, 0) + hi * self.tail_density(uc, 1)
                new[j, 1 + 2 * c] = np.sum(w * np.where(detected, lo * self.tail_density(uc, 0) / g, 0.0))
                new[j, 2 + 2 * c] = np.sum(w * np.where(detected, hi * self.tail_density(uc, 1) / g, 0.0))
        return np.clip(new, eps_min, eps_max)


def events_text(kept: np.ndarray, detected: np.ndarray) -> str:
    """The cut-in car's events in :data:`DIAG_STEPS` of one rollout: misses and errors with tail mass below 1e-2."""
    out = []
    for t in range(*DIAG_STEPS):
        if not detected[t]:
            out.append(f"{t}:miss")
            continue
        for c, name in ((1, "r"), (2, "l")):
            mass = min(kept[t, c], 1.0 - kept[t, c])
            if mass < 1e-2:
                out.append(f"{t}:{name}{'+' if kept[t, c] > 0.5 else '-'}{mass:.0e}")
    return " ".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--mode", choices=("fixed", "ce", "amis", "ams"), default="fixed")
    ap.add_argument("--ams-n", type=int, default=1000)
    ap.add_argument("--ams-k", type=int, default=100)
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument(
        "--n",
        type=int,
        nargs="+",
        default=None,
        help="rollouts per batch (fixed: 13000; ce: 4000 9000; amis: 2000 3000 4000 4000)",
    )
    ap.add_argument("--window", type=int, nargs=2, default=(10, 26), help="steps whose uniforms are mixed")
    ap.add_argument("--eps", type=float, nargs=2, default=(0.02, 0.02), help="miss share, each error's tail share")
    ap.add_argument("--mmin", type=float, default=1e-8)
    ap.add_argument("--mmax", type=float, default=1e-2)
    ap.add_argument("--eps-min", type=float, default=0.002)
    ap.add_argument("--eps-max", type=float, default=0.25)
    ap.add_argument("--diag", type=int, default=0, help="print the K heaviest failures of the last seed")
    args = ap.parse_args()
    sizes = args.n or {"fixed": [13000], "ce": [4000, 9000], "amis": [2000, 3000, 4000, 4000], "ams": [3000]}[args.mode]
    study = TailMixtures(tuple(args.window), args.mmin, args.mmax)
    width = args.window[1] - args.window[0]
    print(
        f"cut-in, moderate setting (reference {REFERENCE:.3g}); mode {args.mode}, window {args.window}, eps "
        f"{args.eps}, tails {args.mmin:g}..{args.mmax:g}, {sum(sizes):,} tail-mixture rollouts a seed"
        + (f", then AMS N = {args.ams_n}, k = {args.ams_k}" if args.mode == "ams" else "")
    )
    ratios = []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        rng = np.random.default_rng(seed)
        t0 = time.perf_counter()
        eps = np.empty((width, 5))
        eps[:, 0], eps[:, 1:] = args.eps[0], args.eps[1] / 2
        pool: list[tuple] = []  # amis: every batch's (failed, kept, p_kept, seen) and its eps
        for i, n in enumerate(sizes):
            out = study.simulate(n, eps, rng)
            failed, log_w = out[0], out[1]
            if args.mode == "amis":
                pool.append((out[0], out[2], out[3], out[4], out[5], eps.copy()))
                failed, kept, p_kept, seen, detected = (np.concatenate([b[k] for b in pool]) for k in range(5))
                shares = np.log(np.array(sizes[: i + 1], dtype=np.float64) / failed.size)
                log_w = -logsumexp(
                    shares[:, None] + np.stack([study.log_q(b[5], kept, p_kept, seen) for b in pool]), axis=0
                )
                out = (failed, log_w, kept, p_kept, seen, detected)
            if i < len(sizes) - 1:
                eps = study.refit(eps, *out[:5], args.eps_min, args.eps_max)
        cost = sum(sizes)
        if args.mode == "ams":
            import pemviz.estimators.ams as ams

            model = fit_committor(failed, out[6], out[7])
            plain = ams.running_score
            ams.running_score = committor_score(study.problem, model)
            try:
                splitting = ams.run_ams(study.problem, args.ams_n, args.ams_k, seed=1000 + seed)
            finally:
                ams.running_score = plain
            est, cost = splitting.estimate(), cost + splitting.n_simulations
        else:
            est = estimate(log_w, failed, np.zeros(failed.size))
        ratios.append(est.mu_hat / REFERENCE)
        holds = est.covers(float(np.log(REFERENCE)))
        print(
            f"  seed {seed}: {est.mu_hat:.3e} {est.interval_text()} x{ratios[-1]:.2f} of the reference "
            f"({'holds' if holds else 'misses'} it), {est.n_failures} failures, ESS {est.ess:.1f}, k-hat "
            f"{est.khat:.2f}, {est.verdict}; {cost:,} rollout-equivalents, {time.perf_counter() - t0:.1f} s",
            flush=True,
        )
    r = np.array(ratios)
    print(
        f"median relative error {np.median(np.abs(r - 1)):.2f} (target <= 0.2); within x2 in "
        f"{int(np.sum((r >= 0.5) & (r <= 2)))} of {r.size}"
    )
    if args.diag:
        f = np.flatnonzero(failed)
        w = np.exp(log_w[f] - log_w[f].max())
        order = np.argsort(-w)[: args.diag]
        print(f"the {order.size} heaviest failures of seed {seed} carry {w[order].sum() / w.sum():.0%} of the weight:")
        for i in order:
            print(f"  {w[i] / w.sum():6.1%}  log w {log_w[f[i]]:6.2f}  {events_text(out[2][f[i]], out[5][f[i]])}")


if __name__ == "__main__":
    main()
