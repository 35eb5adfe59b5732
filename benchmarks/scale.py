"""How an experiment's cost grows with N: wall time, time per simulation split into simulation / fit / other,
peak memory and recording size, for N = 10^2 .. 10^5 rollouts per stage (default sampler, batched twin).

    python benchmarks/scale.py                          # N = 100, 1000, 10000, 100000; --no-record
    python benchmarks/scale.py --n 100 1000 --record    # also write a recording and report its size
    python benchmarks/scale.py --args --preset paper    # extra ExperimentConfig settings via pemviz run flags

Each N runs in a fresh subprocess (``pemviz run --n N --n-final N``), so that its peak resident memory
(``ru_maxrss``) is its own. Inside, the time spent simulating (``Problem.simulate`` / ``Problem.stream``,
detector evaluations included) and fitting the proposal (:func:`pemviz.sampling.fit_proposal`) is summed; "other"
is the engine's wall time minus both (robustness, weights, elites, estimates, events, sinks). Times are
wall (``perf_counter``) and CPU (user + system, ``RUSAGE_SELF``); the load average is printed with each row:
on a machine shared with other jobs compare CPU times. The target (a million rollouts in minutes): at
N >= 10^4 everything but simulation costs at most 2x the simulation time.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _child(argv: list[str]) -> None:
    """Run one ``pemviz run`` in this process with timing hooks; print one JSON line of figures."""
    sys.path.insert(0, str(REPO))  # this checkout's pemviz, as ``python -m pemviz.cli`` from the repository root
    import pemviz.engine as engine
    import pemviz.problems as problems
    import pemviz.estimators.cross_entropy as cross_entropy
    from pemviz.cli import main

    spent = {"simulation": 0.0, "fit": 0.0, "run": 0.0}

    def timed(key, fn):
        def wrapper(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                spent[key] += time.perf_counter() - t0

        return wrapper

    def timed_iter(fn):
        def wrapper(*a, **k):
            it = iter(fn(*a, **k))
            while True:
                t0 = time.perf_counter()
                try:
                    chunk = next(it)
                except StopIteration:
                    spent["simulation"] += time.perf_counter() - t0
                    return
                spent["simulation"] += time.perf_counter() - t0
                yield chunk

        return wrapper

    braking = problems.braking_problem

    def hooked_problem(*a, **k):
        pb = braking(*a, **k)
        import dataclasses

        stream = timed_iter(pb.stream) if pb.stream is not None else None
        return dataclasses.replace(pb, simulate=timed("simulation", pb.simulate), stream=stream)

    problems.braking_problem = hooked_problem  # problems.problem_for builds the run's problem with it
    cross_entropy.fit_proposal = timed("fit", cross_entropy.fit_proposal)  # the name the CE stage calls
    engine.Experiment.run = timed("run", engine.Experiment.run)
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    sys.argv = ["pemviz", "run", *argv]
    rc = main()
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    spent["cpu"] = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    spent["peak_rss_mb"] = cpu1.ru_maxrss / 1024
    spent["rc"] = rc
    print("SCALE " + json.dumps(spent), flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[100, 1000, 10_000, 100_000], help="rollouts per stage")
    ap.add_argument("--record", action="store_true", help="also write a recording and report its size")
    ap.add_argument("--child", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    ap.add_argument("--args", nargs=argparse.REMAINDER, default=[], help="extra arguments for pemviz run")
    args = ap.parse_args()
    if args.child is not None:
        _child(args.child)
        return 0
    os.environ.setdefault("RERUN_ANALYTICS", "false")
    print(f"{os.cpu_count()} cores; times in seconds, per simulation in microseconds")
    print(f"{'N':>7} {'sims':>9} {'rec':>4} {'wall':>7} {'cpu':>7} {'engine':>7} {'sim/run':>8} {'fit/run':>8} "
          f"{'other/run':>9} {'other+fit / sim':>15} {'peak MB':>8} {'rrd MB':>7}  load")  # fmt: skip
    for n in args.n:
        for record in (False, True) if args.record else (False,):
            with tempfile.TemporaryDirectory() as tmp:
                rrd = Path(tmp) / "scale.rrd"
                extra = ["--n", str(n), "--n-final", str(n), *args.args]
                extra += ["--save", str(rrd)] if record else ["--no-record"]
                t0 = time.perf_counter()
                proc = subprocess.run([sys.executable, __file__, "--child", *extra], cwd=REPO, capture_output=True,
                                      text=True)  # fmt: skip
                wall = time.perf_counter() - t0
                line = [x for x in proc.stdout.splitlines() if x.startswith("SCALE ")]
                if proc.returncode != 0 or not line:
                    raise SystemExit(f"N = {n} failed:\n{proc.stderr[-3000:]}")
                f = json.loads(line[0][6:])
                sims = [x for x in proc.stdout.splitlines() + proc.stderr.splitlines() if "simulations" in x]
                n_sims = int(sims[-1].split(" from ")[1].split()[0]) if sims else 0
                per = 1e6 / max(n_sims, 1)
                other = f["run"] - f["simulation"] - f["fit"]
                size = rrd.stat().st_size / 1e6 if record and rrd.exists() else float("nan")
                load = " ".join(f"{x:.2f}" for x in os.getloadavg())
                print(f"{n:>7} {n_sims:>9} {'yes' if record else 'no':>4} {wall:>7.1f} {f['cpu']:>7.1f} "
                      f"{f['run']:>7.1f} {f['simulation'] * per:>8.1f} {f['fit'] * per:>8.1f} {other * per:>9.1f} "
                      f"{(other + f['fit']) / max(f['simulation'], 1e-9):>15.2f} {f['peak_rss_mb']:>8.0f} "
                      f"{size:>7.1f}  {load}", flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
