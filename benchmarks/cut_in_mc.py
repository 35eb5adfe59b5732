"""Plain Monte Carlo of the cut-in scenario under the shipped PEMs, and the batched twin's cost per rollout.

Each step, for every rollout and object: the detection PEM (``pemviz.pem.load_pem()``, the default ml-nn) gives
p(detected | salient variables) of the object row's 11 KITTI columns; the object is detected iff ``u < p`` and it is
visible; the noise PEM (``pemviz.pem.store.load_noise_pem("hetero-t")``: Student-t range and lateral errors, metres)
draws its measurement error. The rollout fails when the robustness of
:data:`pemviz.scenarios.cut_in.scenario.FAILURE_FORMULA` is negative (pemviz's STL, classic semantics). The estimate is
the failure fraction with its Clopper-Pearson 95 % interval (:func:`pemviz.core.estimate.estimate` with unit weights).

Settings (``--setting``): ``default`` (:class:`~pemviz.scenarios.cut_in.scenario.CutInParams` as it is), ``moderate``
and ``rare`` (:data:`pemviz.scenarios.cut_in.scenario.RARITY_SETTINGS`), with ``--set NAME=VALUE`` overrides. Run from
the repository root, e.g.:

    python benchmarks/cut_in_mc.py --setting moderate --n 1000000
    python benchmarks/cut_in_mc.py --cost            # the twin's cost per rollout (no PEM), N = 4096
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pemviz.scenarios.cut_in.scenario import (  # noqa: E402
    FAILURE_FORMULA,
    OBJECT_NAMES,
    RARITY_SETTINGS,
    SALIENT_COLUMNS,
    CutInParams,
)
from pemviz.scenarios.cut_in.batched import BatchedCutIn, cached_trajectory  # noqa: E402

SETTINGS: dict[str, dict] = {"default": {}, **RARITY_SETTINGS}
"""Overrides of :class:`CutInParams` per named setting (:data:`pemviz.scenarios.cut_in.scenario.RARITY_SETTINGS`)."""
VISIBLE = OBJECT_NAMES.index("visible")


def load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f}, {five:.2f}, {fifteen:.2f} on {os.cpu_count()} cores"


def params_for(setting: str, overrides: list[str]) -> CutInParams:
    """The named setting's parameters with ``name=value`` overrides (floats or ints)."""
    kw = dict(SETTINGS[setting])
    for item in overrides:
        name, _, value = item.partition("=")
        kw[name] = int(value) if value.lstrip("-").isdigit() else float(value)
    return dataclasses.replace(CutInParams(), **kw)


def run_chunk(params: CutInParams, n: int, pem, noise_pem, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """``n`` rollouts with detections and errors drawn from the PEMs: (failed bool [n], signals {name: [n, T]}).

    Per step, as the engine draws (one ``random(n * M)``, then the errors of every row): detected iff
    ``log u <= log_expit(logit p)`` and the object is visible; errors ``loc + scale * t_df`` per dimension."""
    from scipy.special import log_expit

    from pemviz.pem.encoding import encode_salient
    from pemviz.stl import robustness

    sim = BatchedCutIn(params, n)
    m, n_steps = params.n_objects, params.n_steps
    obs = np.empty((n_steps, n, len(sim.observation_names)))
    df = noise_pem.df
    for t in range(n_steps):
        sim.observation(out=obs[t])
        rows = sim.objects()
        features = encode_salient(rows[:, :, SALIENT_COLUMNS].reshape(n * m, -1), pem.norm)
        visible = rows[:, :, VISIBLE].reshape(-1) > 0.5
        detected = (np.log(rng.random(n * m)) <= log_expit(pem.logit_features(features))) & visible
        loc, log_scale = noise_pem.noise_params(features)
        draws = np.stack([rng.standard_t(df[d], size=n * m) for d in range(2)], axis=1)
        sim.step(detected.reshape(n, m), (loc + np.exp(log_scale) * draws).reshape(n, m, 2))
    signals = {name: obs[:, :, k].T for k, name in enumerate(sim.observation_names)}
    return robustness(FAILURE_FORMULA, signals) < 0.0, signals


def monte_carlo(params: CutInParams, n: int, chunk: int, seed: int) -> None:
    import torch

    from pemviz.core.estimate import estimate
    from pemviz.pem import load_pem
    from pemviz.pem.store import load_noise_pem

    torch.set_num_threads(1)
    pem, noise_pem = load_pem(), load_noise_pem("hetero-t")
    rng = np.random.default_rng(seed)
    cached_trajectory(params)
    failed = np.zeros(n, dtype=bool)
    collided = np.zeros(n, dtype=bool)
    start = time.perf_counter()
    print(f"# {load()}")
    for a in range(0, n, chunk):
        b = min(a + chunk, n)
        f, signals = run_chunk(params, b - a, pem, noise_pem, rng)
        failed[a:b] = f
        collided[a:b] = (signals["clearance_m"] < 0).any(axis=1)
        if (a // chunk) % 25 == 0:
            print(f"  {b:>9} rollouts, {failed[:b].sum()} failures, {time.perf_counter() - start:.0f} s", flush=True)
    elapsed = time.perf_counter() - start
    est = estimate(np.zeros(n), failed, np.zeros(n))
    print(f"setting: {params}")
    print(f"PEMs: {pem.name} (detection), {noise_pem.name} (noise); seed {seed}")
    print(f"{n} rollouts: {failed.sum()} failures ({collided.sum()} collisions)")
    lo, hi = np.exp(est.log_ci)
    print(
        f"p_fail = {np.exp(est.log_mu_hat):.3e}, 95 % interval [{lo:.3e}, {hi:.3e}], ESS {est.ess:.1f}, "
        f"{est.verdict} ({est.reason})"
    )
    print(f"{elapsed:.0f} s ({elapsed / n * 1e6:.0f} us per rollout with both PEMs); {load()}")


def cost(params: CutInParams, n: int, seed: int) -> None:
    """Microseconds per rollout of the twin alone with random detections and errors: the whole protocol
    (observation, objects, step) and the dynamics alone (step), best of 5 batches of ``n`` rollouts."""
    rng = np.random.default_rng(seed)
    cached_trajectory(params)
    m, n_steps = params.n_objects, params.n_steps
    detected = rng.random((n_steps, n, m)) < 0.95
    noise = rng.standard_normal((n_steps, n, m, 2)) * np.array([0.5, 0.05])
    sim = BatchedCutIn(params, n)
    obs = np.empty((n, len(sim.observation_names)))
    print(f"# {load()}")
    for label, report in (("observation + objects + step", True), ("step alone", False)):
        best = np.inf
        for _ in range(5):
            sim.reset()
            start = time.perf_counter()
            for t in range(n_steps):
                if report:
                    sim.observation(out=obs)
                    sim.objects()
                sim.step(detected[t], noise[t])
            best = min(best, time.perf_counter() - start)
        print(
            f"twin, {label}: N = {n}, T = {n_steps}, M = {m} (T*M = {n_steps * m} object-steps): "
            f"{best / n * 1e6:.1f} us per rollout (best of 5)"
        )
    print(f"# {load()}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--setting", choices=sorted(SETTINGS), default="moderate")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="override a CutInParams field")
    parser.add_argument("--n", type=int, default=100_000, help="rollouts")
    parser.add_argument("--chunk", type=int, default=4096, help="rollouts simulated together")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cost", action="store_true", help="measure the twin's cost per rollout instead")
    args = parser.parse_args()
    params = params_for(args.setting, args.set)
    if args.cost:
        cost(params, args.chunk, args.seed)
    else:
        monte_carlo(params, args.n, args.chunk, args.seed)


if __name__ == "__main__":
    main()
