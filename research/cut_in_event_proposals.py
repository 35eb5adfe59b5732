"""What importance sampling over single perception events, and splitting on a graded lateness, can do on the cut-in
scenario's moderate setting (reference 8.66e-5 from 10^7 plain Monte Carlo rollouts,
:data:`pemviz.scenarios.cut_in.scenario.MONTE_CARLO_REFERENCE`): a study of why no sampler reaches a 10 % median
relative error at 5,000 simulations there.

Every rollout of the batched twin is a deterministic function of its uniforms U [N, T, M, 3]: per step and object, the
detection's uniform (detected iff u <= p(detect)), then the range and lateral errors' (inverse CDF of the noise PEM),
in the order :func:`pemviz.core.lockstep.run_batched` reads them. A proposal density q over U, with U's own density 1
under the PEMs, gives the unbiased importance weight 1 / q(U) whatever the scene. The proposals here inflate
*events*: a uniform in one of the tail bins :data:`BINS` (a miss and the detection's upper tail; both tails of each
error, from 1e-2 down to 0).

Families (fitted to failures, each weighted by its importance weight):

- ``product``: every (step, object, component) draws each tail bin with its own probability rho (the central part
  uniformly otherwise): the cross-entropy optimum of a product family is the failures' marginal event rates;
- ``events``: a mixture of the PEMs (share ``beta0``), single forced events (pi) and pairs of forced events (pi x pi)
  (Owen, Maximov & Chertkov 2019, "Importance sampling the union of rare events with an application to power
  systems analysis", Electron. J. Statist. 13: ALOE), whose weight 1 / (beta0 + beta1 S1 + beta2 S2) needs only
  the events present in U;
- ``both``: the two mixed (the balance heuristic of Veach & Guibas 1995).

A failure's events are fitted only where they are *decisive*: each tail event of an object in the window (range
< 40 m, visible) is reset alone (a detection, or a central error) and the rollout replayed; the events whose reset
saves it (:mod:`pemviz.core.counterfactuals`' idea, on the uniforms) are kept, every event where none alone is. Fits
are smoothed over neighbouring steps and bins. Replays count as simulations.

Modes (``--mode``):

- ``oracle``: collect failures with a broad events proposal over the cut-in car at steps 10-26 (``--collect``
  rollouts), fit each family to *all* of them (decisive events found by replay), then draw ``--n`` rollouts from each:
  the best these families do when their fit has several times the acceptance's whole budget in failures;
- ``adaptive``: each family fitted stage by stage from the PEMs (``--stage`` rollouts a stage; elites: the failures,
  else the rollouts at the lowest robustness with every tie) at ``--budget`` simulations, the stages pooled by the
  balance heuristic, for ``--seeds`` seeds;
- ``ams``: adaptive multilevel splitting (:func:`pemviz.estimators.ams.run_ams`) whose score is the classic
  robustness floored by exp(-L), L a graded lateness: the sum over steps 12-39 at which the ACC follows no car of
  how far the tracked centre of the cut-in car is from the lane's 2 m band (|x_track| - 1, at least 0; 1.5 with no
  track): ties broken by the tracker's continuous state.

Usage (2 cores; each about 1-3 min)::

    python research/cut_in_event_proposals.py --mode oracle
    python research/cut_in_event_proposals.py --mode adaptive --family events --seeds 10
    python research/cut_in_event_proposals.py --mode ams --ams-n 400 --seeds 6
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.ndimage import convolve1d

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pemviz.core.estimate import estimate  # noqa: E402
from pemviz.core.lockstep import run_batched  # noqa: E402
from pemviz.scenarios.cut_in.batched import BatchedCutIn  # noqa: E402
from pemviz.scenarios.cut_in.problem import cut_in_params, cut_in_problem  # noqa: E402
from pemviz.scenarios.cut_in.scenario import MONTE_CARLO_REFERENCE, OBJECT_NAMES  # noqa: E402

REFERENCE = MONTE_CARLO_REFERENCE["moderate"][0] / MONTE_CARLO_REFERENCE["moderate"][1]

DETECTION_BINS = ((0.98, 0.99), (0.99, 0.995), (0.995, 1.0))
ERROR_BINS = (
    (0.0, 1e-5),
    (1e-5, 1e-4),
    (1e-4, 1e-3),
    (1e-3, 1e-2),
    (0.99, 0.999),
    (0.999, 0.9999),
    (0.9999, 0.99999),
    (0.99999, 1.0),
)
BINS = (DETECTION_BINS, ERROR_BINS, ERROR_BINS)
"""Tail bins of each component's uniform (0 detection: its upper tail holds the misses; 1 range, 2 lateral)."""
NB = len(ERROR_BINS)
LO, HI = np.zeros((3, NB)), np.zeros((3, NB))
for _c, _bins in enumerate(BINS):
    for _b, (_lo, _hi) in enumerate(_bins):
        LO[_c, _b], HI[_c, _b] = _lo, _hi
WIDTH = HI - LO
"""[3, NB] each bin's probability under the PEMs (0: no such bin)."""
CENTRAL = ((0.0, 0.98), (0.01, 0.99), (0.01, 0.99))
"""Each component's uniform outside its tail bins."""
SIDES = (((0, 3),), ((0, 4), (4, 8)), ((0, 4), (4, 8)))
"""Bins smoothed together (one tail at a time)."""
STEP_KERNEL = np.array([0.1, 0.2, 0.4, 0.2, 0.1])
BIN_KERNEL = np.array([0.25, 0.5, 0.25])
VISIBLE = OBJECT_NAMES.index("visible")
WINDOW_M = 40.0


def bin_index(u: np.ndarray) -> np.ndarray:
    """int8 [..., 3]: the tail bin of each component's uniform in ``u`` [..., 3], -1 in the central part."""
    out = np.full(u.shape, -1, np.int8)
    for c in range(3):
        for b in range(NB):
            if WIDTH[c, b] > 0:
                out[..., c][(u[..., c] >= LO[c, b]) & (u[..., c] < HI[c, b])] = b
    return out


def smooth(table: np.ndarray) -> np.ndarray:
    """``table`` [T, M, 3, NB] smoothed over neighbouring steps and, one tail at a time, neighbouring bins."""
    out = convolve1d(table, STEP_KERNEL, axis=0, mode="constant")
    res = np.zeros_like(out)
    for c in range(3):
        for a, b in SIDES[c]:
            res[:, :, c, a:b] = convolve1d(out[:, :, c, a:b], BIN_KERNEL, axis=-1, mode="constant")
    return res


class Product:
    """Each coordinate with a fitted rate draws tail bin b with probability rho[t, m, c, b], else its central part."""

    def __init__(self, rho: np.ndarray) -> None:
        self.coords = np.argwhere(rho.sum(-1) > 0)
        self.r = rho[tuple(self.coords.T)]
        self.cum = np.cumsum(self.r, axis=1)

    def sample(self, n: int, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
        u = rng.random((n, *shape, 3))
        t, m, c = self.coords.T
        b = (rng.random((n, t.size))[:, :, None] >= self.cum[None]).sum(-1)
        tail = b < NB
        bb = np.where(tail, b, 0)
        x = rng.random((n, t.size))
        lo_c, hi_c = np.array(CENTRAL).T
        u[:, t, m, c] = np.where(tail, LO[c, bb] + x * WIDTH[c, bb], lo_c[c] + x * (hi_c - lo_c)[c])
        return u

    def log_density(self, u: np.ndarray) -> np.ndarray:
        t, m, c = self.coords.T
        bi = bin_index(u[:, t, m, :])[:, np.arange(t.size), c]
        tail = bi >= 0
        bb = np.where(tail, bi, 0).astype(np.int64)
        rb = np.take_along_axis(np.broadcast_to(self.r, (u.shape[0], *self.r.shape)), bb[..., None], -1)[..., 0]
        lo_c, hi_c = np.array(CENTRAL).T
        central = np.log(1.0 - self.r.sum(1)) - np.log((hi_c - lo_c)[c])
        return np.where(tail, np.log(rb) - np.log(WIDTH[c[None, :], bb]), central[None, :]).sum(1)


class Events:
    """beta0 p + beta1 sum_e pi_e p(. | e) + beta2 sum_{e, e'} pi_e pi_e' / Z p(. | e, e') over events e = (step,
    object, component, bin)."""

    def __init__(self, pi: np.ndarray, betas: tuple[float, float, float] = (0.1, 0.6, 0.3)) -> None:
        self.pi, self.betas = pi / pi.sum(), betas
        self.z = 1.0 - float(np.square(self.pi.sum(-1)).sum())
        """The probability that two independent draws of pi fall on different coordinates (a pair's normaliser)."""
        if betas[2] > 0.0 and self.z <= 0.0:
            raise ValueError("Events: pairs (beta2 > 0) need events on at least two coordinates")
        self.cum = np.cumsum(self.pi.reshape(-1))
        self.cum[-1] = 1.0

    def _event(self, rng: np.random.Generator) -> int:
        return int(np.searchsorted(self.cum, rng.random(), side="right"))

    def sample(self, n: int, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
        u = rng.random((n, *shape, 3))
        kind = rng.choice(3, size=n, p=self.betas)
        for i in np.flatnonzero(kind):
            events = [self._event(rng)]
            while kind[i] == 2 and len(events) < 2:
                e = self._event(rng)
                if e // NB != events[0] // NB:
                    events.append(e)
                else:  # the same coordinate: draw the pair again
                    events = [self._event(rng)]
            for e in events:
                t, m, c, b = np.unravel_index(e, self.pi.shape)
                u[i, t, m, c] = LO[c, b] + rng.random() * WIDTH[c, b]
        return u

    def log_density(self, u: np.ndarray) -> np.ndarray:
        bi = bin_index(u)
        present = bi >= 0
        idx = np.where(present, bi, 0).astype(np.int64)
        pi_b = np.take_along_axis(np.broadcast_to(self.pi, (u.shape[0], *self.pi.shape)), idx[..., None], -1)[..., 0]
        r = np.where(present, pi_b / np.where(present, WIDTH[np.arange(3), idx], 1.0), 0.0).reshape(u.shape[0], -1)
        s1, s2 = r.sum(1), np.square(r).sum(1)
        b0, b1, b2 = self.betas
        pairs = b2 * (s1 * s1 - s2) / self.z if b2 > 0.0 else 0.0
        return np.log(b0 + b1 * s1 + pairs)


class Study:
    """The cut-in problem at its moderate setting, simulated from given uniforms."""

    def __init__(self) -> None:
        import torch
        from pemviz.pem import load_pem

        torch.set_num_threads(1)
        self.params = cut_in_params("moderate")
        self.problem = cut_in_problem(load_pem(), self.params)
        self.shape = (self.params.n_steps, self.params.n_objects)
        self.simulations = 0

    def run(self, u: np.ndarray) -> tuple[np.ndarray, object]:
        """(classic robustness [N], the batch) of the rollouts of uniforms ``u`` [N, T, M, 3]."""
        n, t_max = u.shape[0], self.shape[0]
        target = self.problem.target
        with np.errstate(divide="ignore"):
            batch = run_batched(
                BatchedCutIn(self.params, n), n, t_max, target, target, (u[:, t].reshape(-1) for t in range(t_max))
            )
        self.simulations += n
        return self.problem.robustness(batch, "classic"), batch

    def decisive(self, u: np.ndarray, objects: np.ndarray, level: float) -> np.ndarray:
        """``u`` [E, T, M, 3] of elites at robustness <= ``level`` (< 0 at level 0) with every tail event that is not
        decisive reset to the central value (0 for a detection, 0.5 for an error); an elite none of whose events is
        decisive alone keeps every event in the window."""
        bi = bin_index(u)
        near = (objects[..., 0] < WINDOW_M) & (objects[..., VISIBLE] > 0.5)
        candidates = (bi >= 0) & near[..., None]
        i, t, m, c = np.nonzero(candidates)
        keep = np.zeros(u.shape, bool)
        if i.size:
            replay = u[i].copy()
            replay[np.arange(i.size), t, m, c] = np.where(c == 0, 0.0, 0.5)
            rob, _ = self.run(replay)
            saved = rob > level if level > 0.0 else rob >= 0.0
            keep[i[saved], t[saved], m[saved], c[saved]] = True
        none = ~keep.reshape(u.shape[0], -1).any(1)
        keep[none] = candidates[none]
        central = np.broadcast_to(np.array([0.0, 0.5, 0.5]), u.shape)
        return np.where(keep | (bi < 0), u, central)


def fit_product(u: np.ndarray, weight: np.ndarray, eps: float = 0.1, cap: float = 0.9) -> Product:
    """The product family fitted to elites' decisive uniforms ``u`` with normalised weights: their weighted event
    rates, smoothed, mixed with the PEMs' (``eps``), each coordinate's tail rate capped at ``cap``."""
    bi = bin_index(u)
    rho = np.zeros((*u.shape[1:], NB))
    i, t, m, c = np.nonzero(bi >= 0)
    np.add.at(rho, (t, m, c, bi[i, t, m, c]), weight[i])
    rho = smooth(rho)
    rho = (1 - eps) * rho + eps * np.where(rho.sum(-1, keepdims=True) > 0, WIDTH, 0.0)
    total = rho.sum(-1, keepdims=True)
    return Product(np.where(total > cap, rho * cap / np.maximum(total, 1e-300), rho))


def fit_events(
    u: np.ndarray,
    weight: np.ndarray,
    start: np.ndarray,
    eps: float = 0.1,
    iterations: int = 5,
    betas: tuple[float, float, float] = (0.1, 0.6, 0.3),
) -> Events:
    """The events family fitted to elites' decisive uniforms ``u`` by expectation-maximisation of the single-event
    mixture weights from ``start``, smoothed and mixed with a prior proportional to the bins' PEM probability."""
    prior = np.broadcast_to(WIDTH, start.shape).copy()
    prior /= prior.sum()
    bi = bin_index(u)
    present = bi >= 0
    idx = np.where(present, bi, 0).astype(np.int64)
    n = u.shape[0]
    grid = np.indices(bi.shape)
    pi = start / start.sum()
    for _ in range(iterations):
        pi_b = np.take_along_axis(np.broadcast_to(pi, (n, *pi.shape)), idx[..., None], -1)[..., 0]
        r = np.where(present, pi_b / np.where(present, WIDTH[np.arange(3), idx], 1.0), 0.0)
        resp = r / np.maximum(r.reshape(n, -1).sum(1), 1e-300)[:, None, None, None] * weight[:, None, None, None]
        new = np.zeros_like(pi)
        np.add.at(new, (grid[1][present], grid[2][present], grid[3][present], bi[present]), resp[present])
        pi = (1 - eps) * new / new.sum() + eps * prior
    pi = smooth(pi)
    return Events((1 - eps) * pi / pi.sum() + eps * prior, betas)


def fit(family: str, u: np.ndarray, weight: np.ndarray, start: np.ndarray | None):
    """A proposal of ``family`` fitted to elites' decisive uniforms."""
    prior = np.broadcast_to(WIDTH, u.shape[1:] + (NB,)).copy()
    if family == "product":
        return fit_product(u, weight)
    events = fit_events(u, weight, prior if start is None else start)
    if family == "events":
        return events
    return Mixed(fit_product(u, weight), events)


class Mixed:
    """(1 - share) product + share events, weighed by the balance heuristic."""

    def __init__(self, product: Product, events: Events, share: float = 0.5) -> None:
        self.product, self.events, self.share, self.pi = product, events, share, events.pi

    def sample(self, n: int, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
        from_events = rng.random(n) < self.share
        u = self.product.sample(n, shape, rng)
        u[from_events] = self.events.sample(int(from_events.sum()), shape, rng)
        return u

    def log_density(self, u: np.ndarray) -> np.ndarray:
        return np.logaddexp(
            math.log1p(-self.share) + self.product.log_density(u), math.log(self.share) + self.events.log_density(u)
        )


def report(label: str, log_w: np.ndarray, failed: np.ndarray, extra: str = "") -> float:
    """Print one estimate against the reference; returns its relative error."""
    est = estimate(log_w, failed, np.zeros(log_w.size))
    mu = math.exp(est.log_mu_hat) if failed.any() else 0.0
    lo, hi = np.exp(est.log_ci) if failed.any() else (0.0, 1.0)
    err = abs(mu / REFERENCE - 1.0)
    print(
        f"{label}: {mu:.3e} [{lo:.2e}, {hi:.2e}] (reference {REFERENCE:.3e} "
        f"{'inside' if lo <= REFERENCE <= hi else 'OUTSIDE'}), relative error {err:.3f}, {int(failed.sum())} "
        f"failures, ESS {est.ess:.1f}, {est.verdict}{extra}",
        flush=True,
    )
    return err


def describe_failures(u: np.ndarray, decisive: np.ndarray, weight: np.ndarray) -> None:
    """Print how p_fail splits by the number of decisive events of a failure (weights normalised), and where those
    events lie (objects, steps, components, tail probabilities: unweighted percentiles over the events)."""
    bins = bin_index(decisive)
    count = (bins >= 0).reshape(u.shape[0], -1).sum(1)
    for k in np.unique(count):
        share = weight[count == k].sum()
        print(f"  failures with {k} decisive event(s): {(count == k).sum()}, share of p_fail {share:.3f}")
    i, t, m, c = np.nonzero(bins >= 0)
    tail = np.minimum(u[i, t, m, c], 1.0 - u[i, t, m, c])
    print(
        f"  decisive events: objects {dict(zip(*np.unique(m, return_counts=True), strict=False))}, components "
        f"(detection, range, lateral) {np.bincount(c, minlength=3).tolist()}, "
        f"steps 5/50/95 % {np.percentile(t, [5, 50, 95]).tolist()}, "
        f"tail probability 5/50/95 % {np.percentile(tail, [5, 50, 95]).round(8).tolist()}",
        flush=True,
    )


def oracle(n_collect: int, n: int, seed: int) -> None:
    s = Study()
    rng = np.random.default_rng(seed)
    t_max, m_max = s.shape
    pi = np.zeros((t_max, m_max, 3, NB))
    pi[10:27, 0] = WIDTH[None] > 0
    broad = Events(pi, (0.05, 0.65, 0.3))
    us, log_ws, objects, fails = [], [], [], []
    for _ in range(0, n_collect, 10_000):
        u = broad.sample(10_000, s.shape, rng)
        rob, batch = s.run(u)
        log_w = -broad.log_density(u)
        report(f"broad events proposal, {u.shape[0]} rollouts", log_w, rob < 0)
        f = rob < 0
        us.append(u[f]), log_ws.append(log_w[f]), objects.append(batch.objects[f]), fails.append(int(f.sum()))
    u, log_w = np.concatenate(us), np.concatenate(log_ws)
    weight = np.exp(log_w - log_w.max())
    weight /= weight.sum()
    decisive = s.decisive(u, np.concatenate(objects), 0.0)
    describe_failures(u, decisive, weight)
    print(f"fitted to {u.shape[0]} failures ({s.simulations} simulations so far)", flush=True)
    for family in ("product", "events", "both"):
        q = fit(family, decisive, weight, None)
        draw = q.sample(n, s.shape, rng)
        rob, _ = s.run(draw)
        report(f"oracle {family}, {n} rollouts", -q.log_density(draw), rob < 0)


def adaptive(family: str, seed: int, budget: int, stage: int, final: int, quantile: float = 0.05) -> float:
    """One adaptive run (module docstring); returns its relative error."""
    s = Study()
    rng = np.random.default_rng(seed)
    proposals: list[tuple[int, object]] = []
    failing: list[np.ndarray] = []
    failures_u: list[np.ndarray] = []
    failures_w: list[np.ndarray] = []
    q = None
    while True:
        last = s.simulations + stage + final > budget
        n = budget - s.simulations if last else stage
        u = rng.random((n, *s.shape, 3)) if q is None else q.sample(n, s.shape, rng)
        log_w = np.zeros(n) if q is None else -q.log_density(u)
        proposals.append((n, q))
        rob, batch = s.run(u)
        failed = rob < 0
        failing.append(u[failed])
        if last:
            break
        if failed.any():
            elite, level = failed, 0.0
        else:  # the lowest robustness, every tie with it
            gamma = np.quantile(np.maximum(rob, 0.0), quantile, method="inverted_cdf")
            elite = rob <= gamma
            if elite.mean() > 3 * quantile and (rob < gamma).any():
                elite = rob < gamma
            level = float(rob[elite].max())
        u_fit = s.decisive(u[elite], batch.objects[elite], level)
        w_fit = np.exp(log_w[elite]) / n  # each rollout's share of p_fail under its own stage's sampler
        if level == 0.0:  # every failure so far
            failures_u.append(u_fit)
            failures_w.append(w_fit)
            u_fit, w_fit = np.concatenate(failures_u), np.concatenate(failures_w)
        q = fit(family, u_fit, w_fit / w_fit.sum(), getattr(q, "pi", None))
    # every stage pooled by the balance heuristic: weight 1 / sum_k (n_k / N) q_k(u)
    total = sum(n for n, _ in proposals)
    u_f = np.concatenate(failing)
    density = np.zeros(u_f.shape[0])
    for n, prop in proposals:
        density += n / total * (1.0 if prop is None else np.exp(prop.log_density(u_f)))
    log_w = np.concatenate([-np.log(density), np.zeros(total - u_f.shape[0])])
    failed = np.arange(total) < u_f.shape[0]
    return report(f"{family}, seed {seed}, {s.simulations} simulations", log_w, failed)


def graded_score(problem, batch) -> np.ndarray:
    """min(classic robustness prefix, exp(-L)) [N, T], L the graded lateness of the module docstring."""
    rho = ams_running_score(problem, batch)
    o = batch.objects[:, :, 0, :]
    x_track = np.abs(o[..., OBJECT_NAMES.index("loc_x")] + o[..., OBJECT_NAMES.index("track_err_y_m")])
    outside = np.where(o[..., OBJECT_NAMES.index("tracked")] > 0.5, x_track - 1.0, 1.5).clip(0.0, None)
    following = (batch.objects[..., OBJECT_NAMES.index("followed")] > 0.5).any(axis=2)
    late = np.where(following, 0.0, outside)
    late[:, :12] = late[:, 40:] = 0.0
    return np.minimum(rho, np.exp(-np.cumsum(late, axis=1)))


ams_running_score = None
"""pemviz's own AMS score (the robustness prefix), kept while this study's replaces it."""


def splitting(seed: int, n: int, killed: int) -> float:
    global ams_running_score
    from pemviz.estimators import ams

    if ams_running_score is None:
        ams_running_score = ams.running_score
        ams.running_score = graded_score  # this study's score in place of the robustness
    s = Study()
    start = time.perf_counter()
    run = ams.run_ams(s.problem, n, killed, seed=seed)
    est = run.estimate()
    mu = math.exp(est.log_mu_hat) if est.n_failures else 0.0
    lo, hi = np.exp(est.log_ci)
    err = abs(mu / REFERENCE - 1.0)
    print(
        f"AMS graded lateness, seed {seed}, N {n}, k {killed}: {mu:.3e} [{lo:.2e}, {hi:.2e}], relative error "
        f"{err:.3f}, {run.n_simulations} simulations, {est.verdict} ({run.stop}), "
        f"{time.perf_counter() - start:.0f} s",
        flush=True,
    )
    return err


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--mode", choices=("oracle", "adaptive", "ams"), default="oracle")
    ap.add_argument("--family", choices=("product", "events", "both"), default="events")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--budget", type=int, default=5000, help="simulations of an adaptive run, replays included")
    ap.add_argument("--stage", type=int, default=1000, help="rollouts of an adaptive stage")
    ap.add_argument("--final", type=int, default=2000, help="at least this many rollouts in the last stage")
    ap.add_argument("--collect", type=int, default=30_000, help="oracle: rollouts of the broad proposal")
    ap.add_argument("--n", type=int, default=10_000, help="oracle: rollouts from each fitted family")
    ap.add_argument("--ams-n", type=int, default=400)
    ap.add_argument("--ams-k", type=int, default=40)
    args = ap.parse_args()
    print(f"# {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; reference {REFERENCE:.3e}", flush=True)
    if args.mode == "oracle":
        oracle(args.collect, args.n, seed=7)
        return
    if args.mode == "adaptive":
        errors = [adaptive(args.family, s, args.budget, args.stage, args.final) for s in range(args.seeds)]
    else:
        errors = [splitting(s, args.ams_n, args.ams_k) for s in range(args.seeds)]
    print(f"median relative error over {args.seeds} seeds: {np.median(errors):.3f}")


if __name__ == "__main__":
    main()
