"""Scene-neutral candidates on the crossing, measured against what a tenth of plain Monte Carlo's cost demands.

The crossing (two pedestrians, the noise PEM, a Kalman tracker, an emergency brake on confirmed tracks; p = 3.08e-4
by plain Monte Carlo) is the realistic stack on which every scene-neutral sampler of pemviz has stayed near plain
Monte Carlo's cost. This study asks why, with three of the field's candidates:

1. **Proposals over the perception's uniforms, fitted by cross-entropy** (an oracle). Every scene's perception is a
   function of uniforms: at each step, for each object, one uniform decides the detection (detected iff u <=
   p(detect)) and one per error component draws the measurement error by inverse CDF
   (:func:`pemviz.core.detectors.draw_step`). Under the PEMs these T x M x (1 + D) numbers are i.i.d. U(0, 1), so a
   proposal h over them needs nothing from the scene and its importance weight is 1 / h(u). Two families, each a
   defensive mixture (1 - eps) h + eps (Hesterberg 1995, Technometrics 37(2)), each coordinate's density piecewise
   constant on :data:`EDGES`: ``product``, h(u) = prod_j h_j(u_j), each coordinate's histogram fitted to the
   failures and kept only where a G-test says it differs from uniform (the screening of Rubinstein & Glynn 2009, "How
   to deal with the curse of dimensionality of likelihood ratios in Monte Carlo simulation", Stoch. Models 25(4));
   ``mixture``, h(u) = sum_j pi_j h_j(u_j), one coordinate tilted at a time, fitted by EM. Each is fitted to the
   failures of 300,000 plain rollouts (83), far more than a run could learn from, then drawn 5,000 times.
2. **The nominal look-ahead as a committor**: how often the rollouts whose look-ahead score
   (:mod:`pemviz.estimators.lookahead_score`) takes each value at a step fail.
3. **Interacting particles** on that score (:func:`smc`; Del Moral & Garnier 2005).

Plain Monte Carlo's rollouts for a median relative error m are 0.455 (1 - p) / (p m^2) and an importance sampler's
0.455 v / m^2, v the relative variance of its weighted failure indicator, so its cost is v p of plain Monte Carlo's
whatever m (learning not counted): a tenth needs v <= 0.1 / p, 325 on the crossing.

Recorded (2 cores; the seeds are fixed in the code)::

    python research/uniform_space_proposals.py                       # about 25 s
    plain rollouts: 300,000, failures 83
    product: 8 coordinates tilted; 56 failures of 5,000, mu_hat 1.99e-04, relative variance 1335 -> 0.41 of plain MC
    mixture: 9 components; 12 failures of 5,000, mu_hat 3.99e-04, relative variance 683 -> 0.21 of plain MC

    python research/uniform_space_proposals.py --lookahead-table 200000     # about 2 min; value: rollouts (failing)
    step 16: 4.3 m: 27 (0.0000), 5.5 m: 197019 (0.0002), 6.7 m: 2899 (0.0003)
    step 20: 1.9 m: 34 (0.0000), 3.1 m: 808 (0.0012), 4.3 m: 9095 (0.0015), 5.5 m: 160016 (0.0002), 6.7 m: 27604
             (0.0001), ...
    step 22: 0.7 m: 37 (0.0270), 1.9 m: 1260 (0.0167), 3.1 m: 2159 (0.0046), 4.3 m: 24104 (0.0005), 5.5 m: 131425
             (0.0000), ...
    step 24: 0.7 m: 242 (0.0826), 1.9 m: 1434 (0.0112), 3.1 m: 2518 (0.0000), 4.3 m: 23355 (0.0000), ...

    python research/uniform_space_proposals.py --smc 1 --seeds 20    # about 25 s
    interacting particles, lambda 1, 500 particles, resampled at steps 20, 22, 24: median relative error 0.58, 9/20
    within x2, mean ratio 1.02, cost 2,180 rollout-equivalents
    python research/uniform_space_proposals.py --smc 2 --seeds 20
    ... lambda 2 ...: median relative error 0.56, 10/20 within x2, mean ratio 0.77, cost 2,180 rollout-equivalents

What it shows (research/README.md; docs/validation.md, "A scene-neutral sampler"):

- The failures are pedestrian 0's large range errors (both tails) at steps 18-23 and its misses at steps 19-25: a
  gate missed restarts its track, whose lateral speed is then unknown, and the brake comes late. A failure needs the
  error AND what follows it, so neither independent tilts nor one tilted event at a time follow the failures' law:
  even fitted to 83 true failures both stay at a fifth to two fifths of plain Monte Carlo's cost (the product's mu_hat,
  two thirds of p, says its weights' tail is heavier than 5,000 draws show). A proposal that is a function of the
  step alone cannot reach a tenth; it must be a function of the state.
- The nominal look-ahead orders states by their committor from step 20 on (at step 22, 2.7 % of the rollouts scoring
  0.7 m fail, 0.05 % of those scoring 4.3 m and almost none at the nominal 5.5 m), not before (step 16: 0.02 % and
  0.03 %). It is a usable committor only inside the last few steps before the brake.
- Interacting particles resampled on it there are unbiased (mean ratio 1.02 over 20 runs) but cost 0.46 of plain
  Monte Carlo for their median error (0.56 at 2,180 rollout-equivalents, where plain Monte Carlo needs about 4,700),
  like the splitting of ``benchmarks/scene_neutral.py``: the score's levels (1.2 m apart) are too coarse, and each
  resampling step pays a look-ahead of every particle.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pemviz import stl  # noqa: E402
from pemviz.core.lockstep import draws_per_rollout, run_batched  # noqa: E402
from pemviz.core.rollouts import RolloutBatch  # noqa: E402

EDGES = np.array([0.0, 0.02, 0.07, 0.2, 0.5, 0.8, 0.93, 0.98, 1.0])
"""The bins of each coordinate's density: finer in both tails (misses are u near 1; an error's tails u near 0 and 1)."""
WIDTHS = np.diff(EDGES)
N_BINS = WIDTHS.size


class UniformProposal:
    """A defensive mixture (1 - eps) h + eps over the J = T x M x (1 + D) uniforms of a rollout (module docstring).

    Args:
        problem: a problem whose rollouts are simulated by ``make(n)`` (a batched simulator) for ``n_steps`` steps.
        family: ``product`` or ``mixture``.
        eps: the uniform's share.
    """

    def __init__(
        self, problem: Any, make: Callable[[int], Any], n_steps: int, family: str = "product", eps: float = 0.1
    ) -> None:
        self.problem, self.make, self.n_steps, self.family, self.eps = problem, make, n_steps, family, eps
        self.per_step = draws_per_rollout(make(1), problem.target)  # M (1 + D)
        self.n_coords = n_steps * self.per_step
        self.mass = np.tile(WIDTHS, (self.n_coords, 1))  # [J, B] each coordinate's bin masses (uniform: the widths)
        self.pi = np.zeros(0)  # the mixture's shares over its components
        self.components = np.zeros(0, np.int64)  # the mixture's tilted coordinates

    def log_density(self, bins: np.ndarray) -> np.ndarray:
        """log of the proposal's density at each rollout's uniforms, float64 [n] (nats; the uniform's is 0), from
        their bins, int [n, J]."""
        rows = np.arange(self.n_coords)[None, :]
        dens = self.mass[rows, bins] / WIDTHS[bins]  # [n, J]
        if self.family == "product":
            h = np.exp(np.log(dens).sum(axis=1))
        elif self.components.size:
            h = (self.pi[None, :] * dens[:, self.components]).sum(axis=1)
        else:
            h = np.ones(bins.shape[0])
        return np.log((1.0 - self.eps) * h + self.eps)

    def draw(
        self, n: int, rng: np.random.Generator, plain: bool = False
    ) -> tuple[RolloutBatch, np.ndarray, np.ndarray]:
        """``n`` rollouts (from the PEMs with ``plain``): (the batch, their uniforms' bins int [n, J], their log
        importance weights [n], nats)."""
        tilted = np.zeros(n, bool) if plain else rng.random(n) >= self.eps
        component = np.full(n, -1)
        if self.family == "mixture" and self.components.size and tilted.any():
            pick = np.searchsorted(np.cumsum(self.pi), rng.random(int(tilted.sum())) * self.pi.sum())
            component[tilted] = self.components[np.minimum(pick, self.components.size - 1)]
        bins = np.empty((n, self.n_coords), np.uint8)
        cum = np.cumsum(self.mass, axis=1)

        def uniforms() -> Iterator[np.ndarray]:
            for t in range(self.n_steps):
                u = rng.random((n, self.per_step))
                for c in range(self.per_step):
                    j = t * self.per_step + c
                    rows = np.flatnonzero(tilted if self.family == "product" else component == j)
                    if rows.size and not np.allclose(self.mass[j], WIDTHS):
                        b = np.minimum(
                            np.searchsorted(cum[j], rng.random(rows.size) * cum[j, -1], side="right"), N_BINS - 1
                        )
                        u[rows, c] = EDGES[b] + WIDTHS[b] * rng.random(rows.size)
                u = np.minimum(u, np.nextafter(1.0, 0.0))
                bins[:, t * self.per_step : (t + 1) * self.per_step] = np.searchsorted(EDGES, u, side="right") - 1
                yield u.reshape(-1)

        target = self.problem.target
        batch = run_batched(self.make(n), n, self.n_steps, target, target, uniforms(), keep_rows=False)
        return batch, bins, -self.log_density(bins) if not plain else np.zeros(n)

    def fit(self, bins: np.ndarray, log_w: np.ndarray, screen: float = 0.05, iterations: int = 30) -> int:
        """Fit to the rollouts ``bins`` [K, J] of weights ``log_w`` [K] (the failures); returns the coordinates tilted
        (``product``) or the components kept (``mixture``)."""
        from scipy.stats import chi2

        w = np.exp(log_w - log_w.max())
        w /= w.sum()
        n_eff = 1.0 / float((w**2).sum())
        hist = np.stack([(w[:, None] * (bins == b)).sum(axis=0) for b in range(N_BINS)], axis=-1)  # [J, B]
        hist = (hist + 0.5 * WIDTHS / n_eff) / (1.0 + 0.5 / n_eff)
        g = 2.0 * n_eff * (hist * np.log(hist / WIDTHS)).sum(axis=1)
        if self.family == "product":
            keep = g > chi2.ppf(1.0 - screen / self.n_coords, N_BINS - 1)
            self.mass = np.where(keep[:, None], hist, WIDTHS)
            return int(keep.sum())
        pi = np.maximum(g, 0.0) / max(float(g.sum()), 1e-300)
        for _ in range(iterations):  # EM over one-coordinate components
            dens = hist[np.arange(self.n_coords)[None, :], bins] / WIDTHS[bins]  # [K, J]
            resp = pi[None, :] * dens
            resp = w[:, None] * resp / resp.sum(axis=1, keepdims=True)
            pi = resp.sum(axis=0) / resp.sum()
            hist = np.stack([(resp * (bins == b)).sum(axis=0) for b in range(N_BINS)], axis=-1)
            hist = (hist + 0.5 * WIDTHS / n_eff) / (resp.sum(axis=0)[:, None] + 0.5 / n_eff)
        self.components = np.flatnonzero(pi > 0.002)
        self.pi = pi[self.components] / pi[self.components].sum()
        self.mass = np.tile(WIDTHS, (self.n_coords, 1))
        self.mass[self.components] = hist[self.components] / hist[self.components].sum(axis=1, keepdims=True)
        return int(self.components.size)


def robustness(problem: Any, batch: RolloutBatch) -> np.ndarray:
    """The formula's robustness of each rollout, float64 [n] (metres)."""
    return np.asarray(stl.robustness(problem.formula, problem.signal_arrays(batch)), dtype=np.float64)


def crossing_setup() -> tuple[Any, Callable[[int], Any], int, float]:
    """The crossing problem, its batched simulator, its steps and its plain Monte Carlo reference p."""
    from pemviz.scenarios.crossing.problem import MONTE_CARLO_REFERENCE, crossing
    from pemviz.scenarios.crossing.scene import BatchedCrossing, CrossingParams

    params = CrossingParams()
    failures, n = MONTE_CARLO_REFERENCE
    return crossing(), (lambda k: BatchedCrossing(params, k)), params.n_steps, failures / n


def lookahead_table(n: int, steps: tuple[int, ...] = (16, 20, 22, 24)) -> None:
    """Print, for ``n`` plain rollouts of the crossing, how often each value of the nominal look-ahead score at each of
    ``steps`` occurs and the fraction of those rollouts that fail: whether the score orders states by their
    committor (:mod:`pemviz.estimators.lookahead_score`)."""
    from pemviz.core.problems import step_robustness
    from pemviz.estimators.lookahead_score import MedianUniforms

    problem, _, _, _ = crossing_setup()
    batch = problem.simulate(n, problem.target, problem.target, np.random.default_rng(0))
    failed = step_robustness(problem, batch).min(axis=1) < 0.0
    for t in steps:
        ahead = problem.branch(batch, np.arange(n), np.full(n, t), problem.target, MedianUniforms())
        score = np.round(step_robustness(problem, ahead)[:, t:].min(axis=1), 2)
        values, counts = np.unique(score, return_counts=True)
        cells = [
            f"{v:g} m: {c} ({failed[score == v].mean():.4f})" for v, c in zip(values, counts, strict=True) if c >= 20
        ]
        print(f"step {t}: " + ", ".join(cells))


def smc(n: int, times: tuple[int, ...], lam: float, seed: int) -> tuple[float, int, float]:
    """One run of interacting particles on the crossing (Del Moral & Garnier, "Genealogical particle analysis of rare
    events", Ann. Appl. Probab. 15(4), 2005): ``n`` plain rollouts; at each step of ``times`` every particle is scored
    by the nominal look-ahead S (:mod:`pemviz.estimators.lookahead_score`), resampled with potential exp(-lam (S -
    S_before)) and continued from that step by the PEMs. Unbiased for any potential: p_hat = prod_k mean(G_k) x
    mean(1[fail] / prod_k G_k). Returns (log p_hat in nats, failures at the end, cost in rollout-equivalents: the
    rollouts, every continuation's and look-ahead's steps after its branching step, over T)."""
    from pemviz.core.problems import step_robustness
    from pemviz.estimators.lookahead_score import MedianUniforms
    from scipy.special import logsumexp

    problem, _, n_steps, _ = crossing_setup()
    rng = np.random.default_rng(seed)
    batch = problem.simulate(n, problem.target, problem.target, rng)
    steps, log_z, before, log_g = n * n_steps, 0.0, None, np.zeros(n)
    for t in times:
        ahead = problem.branch(batch, np.arange(n), np.full(n, t), problem.target, MedianUniforms())  # type: ignore
        score = step_robustness(problem, ahead)[:, t:].min(axis=1)
        score = np.where(step_robustness(problem, batch)[:, :t].min(axis=1) < 0.0, -1.0, score)
        lg = -lam * (score - (before if before is not None else score.max()))
        log_z += float(logsumexp(lg)) - np.log(n)
        pick = rng.choice(n, n, p=np.exp(lg - logsumexp(lg)))
        log_g, before = log_g[pick] + lg[pick], score[pick]
        batch = problem.branch(batch, pick, np.full(n, t), problem.target, rng)
        steps += 2 * n * (n_steps - t)
    failed = step_robustness(problem, batch).min(axis=1) < 0.0
    log_p = log_z + float(logsumexp(np.where(failed, -log_g, -np.inf))) - np.log(n) if failed.any() else -np.inf
    return log_p, int(failed.sum()), steps / n_steps


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--plain", type=int, default=300_000, help="plain rollouts whose failures are fitted")
    ap.add_argument("--draws", type=int, default=5_000, help="rollouts drawn from each fitted proposal")
    ap.add_argument(
        "--lookahead-table",
        type=int,
        default=0,
        metavar="N",
        help="instead: the nominal look-ahead's score against the failure rate over N plain rollouts",
    )
    ap.add_argument(
        "--smc",
        type=float,
        default=None,
        metavar="LAMBDA",
        help="instead: interacting particles on the nominal look-ahead with this potential's lambda (1/m)",
    )
    ap.add_argument("--particles", type=int, default=500)
    ap.add_argument("--seeds", type=int, default=10)
    a = ap.parse_args(argv)
    if a.lookahead_table:
        lookahead_table(a.lookahead_table)
        return 0
    if a.smc is not None:
        _, _, _, p = crossing_setup()
        runs = [smc(a.particles, (20, 22, 24), a.smc, seed) for seed in range(a.seeds)]
        ratios = np.array([np.exp(lp) / p for lp, _, _ in runs])
        print(
            f"interacting particles, lambda {a.smc:g}, {a.particles} particles, resampled at steps 20, 22, 24: "
            f"median relative error {np.median(np.abs(ratios - 1)):.2f}, {int(((ratios > 0.5) & (ratios < 2)).sum())}"
            f"/{a.seeds} within x2, mean ratio {ratios.mean():.2f}, cost {np.mean([c for _, _, c in runs]):,.0f} "
            "rollout-equivalents"
        )
        return 0
    problem, make, n_steps, p = crossing_setup()
    rng = np.random.default_rng(11)
    plain = UniformProposal(problem, make, n_steps)
    kept = []
    for start in range(0, a.plain, 50_000):
        batch, bins, _ = plain.draw(min(50_000, a.plain - start), rng, plain=True)
        kept.append(bins[robustness(problem, batch) < 0.0])
    failures = np.concatenate(kept)
    print(f"plain rollouts: {a.plain:,}, failures {len(failures)}")
    for family in ("product", "mixture"):
        proposal = UniformProposal(problem, make, n_steps, family)
        size = proposal.fit(failures, np.zeros(len(failures)))
        batch, _, log_w = proposal.draw(a.draws, np.random.default_rng(2))
        x = np.where(robustness(problem, batch) < 0.0, np.exp(log_w), 0.0)
        v = float(x.var() / x.mean() ** 2) if x.mean() > 0 else float("inf")
        what = "coordinates tilted" if family == "product" else "components"
        print(
            f"{family}: {size} {what}; {int((x > 0).sum())} failures of {a.draws:,}, mu_hat {x.mean():.2e}, "
            f"relative variance {v:.0f} -> {v * p:.2f} of plain MC"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
