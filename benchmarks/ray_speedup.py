"""Ray against serial for an expensive black-box simulator: the highway-env braking scenario, one experiment
with ``executor="serial"`` and one with ``executor="ray"`` on a local cluster of 2 workers, same seed.

    python benchmarks/ray_speedup.py                   # K = 2, N = 300, N_e = 300 (~1,000 highway-env rollouts each)
    python benchmarks/ray_speedup.py --n 600 --k 3

The Ray workers are started (and import pemviz, torch, highway-env: a few seconds, once per cluster) before the
timed run. Prints each run's wall time, the time spent simulating (the executor's ``simulate``), the speed-up of the
simulation and of the whole run, and both estimates (they must agree: the same rollouts, up to the last bit of
the proposal's torch evaluation per chunk). The load average is printed with the figures: on a machine shared
with other jobs, 2 workers cannot get 2 cores.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's pemviz


def run(config, problem):
    import pemviz.engine.executors as executors
    from pemviz.engine.experiment import Experiment
    from pemviz.engine.resources import torch_threads

    spent = [0.0]
    ex = executors.get_executor(config.execution.executor, config.execution.ray_address)
    simulate = ex.simulate

    def timed(*a, **k):
        t0 = time.perf_counter()
        try:
            return simulate(*a, **k)
        finally:
            spent[0] += time.perf_counter() - t0

    ex.simulate = timed
    t0 = time.perf_counter()
    with torch_threads(1):
        done = Experiment(config, problem=problem).run()
    return done, time.perf_counter() - t0, spent[0]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=300, help="rollouts per stage and final rollouts (default 300)")
    ap.add_argument("--k", type=int, default=2, help="CE stages (default 2)")
    ap.add_argument("--workers", type=int, default=2, help="local Ray workers (default 2)")
    args = ap.parse_args()
    os.environ.setdefault("RERUN_ANALYTICS", "false")
    import ray
    from pemviz.config import ExperimentConfig
    from pemviz.engine.executors import close_executors
    from pemviz.scenarios.problems import problem_for

    base = ExperimentConfig.of(
        sim="highway-env", n_stages=args.k, n_per_stage=args.n, n_final=args.n, pretrain_rollouts=args.n, seed=0
    )
    problem = problem_for(base)
    serial, wall_s, sim_s = run(base, problem)
    ray.init(num_cpus=args.workers, include_dashboard=False, log_to_driver=False)
    try:  # start the workers (a process each, importing pemviz, torch and highway-env) before timing
        import numpy as np
        from pemviz.engine.executors import get_executor

        t0 = time.perf_counter()
        get_executor("ray").simulate(
            problem, 2 * args.workers, problem.target, problem.target, np.random.default_rng(0)
        )
        startup = time.perf_counter() - t0
        remote, wall_r, sim_r = run(base.replace(executor="ray"), problem)
    finally:
        close_executors()
        ray.shutdown()
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(
        f"highway-env, {base.n_simulations} rollouts per run (K = {args.k}, N = N_e = {args.n}), {os.cpu_count()} "
        f"cores, load {load}"
    )
    print(f"{'executor':<16} {'wall s':>8} {'simulate s':>11} {'mu_hat':>12} failures")
    for name, done, wall, sim in (("serial", serial, wall_s, sim_s), (f"ray x{args.workers}", remote, wall_r, sim_r)):
        e = done.final.estimate
        print(f"{name:<16} {wall:>8.1f} {sim:>11.1f} {e.mu_hat:>12.4g} {e.n_failures}/{e.n}")
    print(
        f"speed-up: simulation {sim_s / sim_r:.2f}x, whole run {wall_s / wall_r:.2f}x (after a one-off Ray start-up "
        f"of {startup:.1f} s: worker processes importing pemviz, torch, highway-env)"
    )
    s, r = serial.final.estimate, remote.final.estimate
    same = s.n_failures == r.n_failures and abs(s.log_mu_hat - r.log_mu_hat) <= 1e-9 * max(1.0, abs(s.log_mu_hat))
    print("same estimate as serial: " + ("yes" if same else f"NO ({s.log_mu_hat} vs {r.log_mu_hat})"))
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
