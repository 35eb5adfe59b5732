"""Plain Monte Carlo of the cut-in scenario through pemviz's own rollouts, and the batched twin's cost per rollout.

The rollouts are the engine's (``Problem.stream`` of the registered cut-in, :func:`pemviz.core.lockstep.run_batched`):
each step, for every rollout and object, the detection PEM (the shipped ml-nn) gives p(detected | salient variables)
of the object row's 11 KITTI columns and the object is detected iff it is visible and ``log u <= log_expit(logit p)``;
a detected object's range and lateral errors come from the noise PEM (hetero-t, Student-t) by inverse CDF of its
other two uniforms. The rollout fails when the classic robustness of the scenario's failure formula is negative
(``Problem.failed``). So chunk ``k`` below is exactly ``pemviz run --scenario cut-in --method mc --n CHUNK --seed
SEED+k`` (with the same ``--param``), whatever the chunking: a line per chunk is written as it ends, so a run cut
short pools the chunks it finished. The estimate is the failure fraction with its Clopper-Pearson 95 % interval.
``tests/scenarios/test_cut_in_mc_paths.py`` checks these rollouts against a plain loop of its own.

Run from the repository root, e.g.:

    python benchmarks/cut_in_mc.py --n 10000000 --chunk 1000000 --seed 100     # the default scene's reference
    python benchmarks/cut_in_mc.py --param cut_in_gap_m=21 --n 10000000          # the cut-in at 21 m
    python benchmarks/cut_in_mc.py --param "cut_in_gap_m~uniform(19.5, 21.5)" --n 1000000   # over the ODD
    python benchmarks/cut_in_mc.py --cost            # the twin's cost per rollout (no PEM), N = 4096
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pemviz.scenarios.cut_in.batched import BatchedCutIn, cached_trajectory  # noqa: E402
from pemviz.scenarios.cut_in.scenario import CutInParams  # noqa: E402


def load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f}, {five:.2f}, {fifteen:.2f} on {os.cpu_count()} cores"


def chunk_failures(problem, n: int, seed: int) -> int:
    """Failures among the ``n`` rollouts ``pemviz run --method mc --n n --seed seed`` draws on ``problem``."""
    rng = np.random.default_rng(seed)
    target = problem.target
    return sum(int(problem.failed(b).sum()) for b in problem.stream(n, target, target, rng, keep_rows=False))


def monte_carlo(params: list[str], n: int, chunk: int, seed: int) -> None:
    """``n`` rollouts in chunks of ``chunk``, chunk ``k`` from seed ``seed + k``; a line per chunk, then the pool."""
    import threadpoolctl
    from pemviz.commands.run import scenario_params
    from pemviz.config import ExperimentConfig
    from pemviz.core.confidence import clopper_pearson
    from pemviz.scenarios.registry import problem_for

    threadpoolctl.threadpool_limits(1)
    pairs = scenario_params("cut-in", params) if params else ()
    problem = problem_for(ExperimentConfig.of(scenario="cut-in", scenario_params=pairs))
    print(f"# {problem.description}; --param {' '.join(params) or '(none)'}; {load()}", flush=True)
    failures = done = 0
    start = time.perf_counter()
    for k, a in enumerate(range(0, n, chunk)):
        m = min(chunk, n - a)
        f = chunk_failures(problem, m, seed + k)
        failures, done = failures + f, done + m
        print(f"chunk seed {seed + k}: {f} failures in {m} rollouts ({time.perf_counter() - start:.0f} s)", flush=True)
    elapsed = time.perf_counter() - start
    lo, hi = clopper_pearson(failures, done)
    print(f"{done} rollouts (seeds {seed}..{seed + k}): {failures} failures")
    print(f"p_fail = {failures / done:.3e}, 95 % interval [{lo:.3e}, {hi:.3e}] (Clopper-Pearson)")
    print(f"{elapsed:.0f} s ({elapsed / done * 1e6:.0f} us per rollout); {load()}")


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
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE", help="as pemviz run --param")
    parser.add_argument("--n", type=int, default=100_000, help="rollouts")
    parser.add_argument("--chunk", type=int, default=1_000_000, help="rollouts a seed (a line of output)")
    parser.add_argument("--seed", type=int, default=0, help="the first chunk's seed (the k-th chunk's: seed + k)")
    parser.add_argument("--cost", action="store_true", help="measure the twin's cost per rollout instead (N = 4096)")
    args = parser.parse_args()
    if args.cost:
        cost(CutInParams(), 4096, args.seed)
    else:
        monte_carlo(args.param, args.n, args.chunk, args.seed)


if __name__ == "__main__":
    main()
