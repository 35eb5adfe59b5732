"""How an experiment's cost grows with N: wall time, time per simulation split into simulation / fit / other,
peak memory and recording size, for N = 10^2 .. 10^5 rollouts per stage (default sampler, batched twin).

    python benchmarks/scale.py                          # N = 100, 1000, 10000, 100000; --no-record
    python benchmarks/scale.py --n 100 10000 --check    # exit 1 if at N = 10,000 (other + fit) / simulation > 1
    python benchmarks/scale.py --n 100 1000 --record    # also write a recording and report its size
    python benchmarks/scale.py --args --preset paper    # extra ExperimentConfig settings via pemviz run flags
    python benchmarks/scale.py --n 100000 --plain       # also plain Monte Carlo of the run's rollouts, the wall ratio
    python benchmarks/scale.py --cores                  # every core (the default) against --workers 1
    python benchmarks/scale.py --cores --cores-n 1000000 --cases crossing cut-in braking
    python benchmarks/scale.py --cores --cores-n 1000000 --cases crossing-save --once   # default workers only
    python benchmarks/scale.py --cores --ray 2 4 --cases crossing cut-in   # and a local Ray cluster of 2, 4 workers

Besides the table, one line per N gives the two ratios to watch: (other + fit) / simulation (what the sampler costs
beyond simulating; at most 1.0 at N = 10,000), and the experiment's simulation cost per rollout against the pure
batched twin's, measured in the same process (the braking scenario's N rollouts drawn i.i.d. from the PEM with no
proposal and no mixture, :func:`pemviz.scenarios.braking.batched.simulate_batched`): what the proposal network and the
mixture's bookkeeping add to each simulated step. ``--check`` is for people, not CI: timings depend on the machine.

``--plain`` then runs, per N, plain Monte Carlo of as many rollouts as the run simulated (``--method mc``, the
same seed) and prints the run's wall time over plain Monte Carlo's, the engine's alone and the whole process's: what
the sampler costs against simulating the same rollouts with no proposal (the target 1.5 at N = 10^5).

Each N runs in a fresh subprocess (``pemviz run --n N --n-final N --workers 1``: one process, whose thread times
cover the run), so that its peak resident memory (``ru_maxrss``) is its own. Inside, the time spent simulating
(``Problem.simulate`` / ``Problem.stream``, detector evaluations included) and fitting the proposal
(:func:`pemviz.core.sampling.fit_proposal`) is summed; "other" is the engine's wall time minus both (robustness,
weights, elites, estimates, events, sinks). Times are wall (``perf_counter``) and CPU (user + system,
``RUSAGE_SELF``; the split by the run's own thread, ``thread_time``: the run is single-threaded); the load average is
printed with each row: on a machine shared with other jobs compare the CPU ratios. The target (a million rollouts in
minutes): at N >= 10^4 everything but simulation costs at most 2x the simulation time.

``--cores`` times runs on every usable core (the default ``local`` executor) against ``--workers 1``, each in a fresh
``pemviz run`` process: plain Monte Carlo of ``--cores-n`` rollouts on the crossing and the cut-in (200,000 by
default: the issue asks 10^6, about 14 and 33 minutes a run with 1 worker on the 2-core machine at load 9-11),
braking's default run (2,100 rollouts: the pool never starts), and with ``--cases crossing-save`` plain Monte Carlo
streamed to a ``--save-rollouts`` file.
Per run it prints wall and CPU seconds (the run's and its reaped workers', user + system; a Ray cluster's workers
read from ``/proc`` every 0.2 s), the run's first time
estimate (its first ``run ~X left``), the peak resident memory (``VmHWM``) of the run's process and of its largest
worker, and the load average; per case the wall ratio. ``--pays-s 1`` starts the pool after the first block whatever
the blocks left cost (100,000 crossing rollouts, 12 blocks of about 1 s, stay in one process by default), to measure
its CPU on a short run. ``--ray 2 4`` also runs each case with ``--executor ray`` on a local Ray cluster of 2 and
of 4 worker processes (``ray.init(num_cpus=W)`` in the run's process, before ``pemviz run``: no network), and prints
the speed-up over ``--workers 1``, the ideal (W, at most the usable cores) and their ratio, by the run's own seconds
(the "in S s" of its estimate line: the cluster's start is not the run's) and by the process's wall. Figures:
docs/validation.md, "Every core".
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CHECK_N, CHECK_RATIO = 10_000, 1.0
"""``--check``: at N = 10,000, what the sampler costs beyond simulating is at most the simulation itself."""


def _child(argv: list[str]) -> None:
    """Run one ``pemviz run`` in this process with timing hooks; print one JSON line of figures."""
    sys.path.insert(0, str(REPO))  # this checkout's pemviz, as ``python -m pemviz.cli`` from the repository root
    import pemviz.engine.experiment as engine
    import pemviz.estimators.ce_fit as ce_fit
    import pemviz.scenarios.problems as problems
    from pemviz.cli import main

    spent = {"simulation": 0.0, "fit": 0.0, "run": 0.0, "simulation_cpu": 0.0, "fit_cpu": 0.0, "run_cpu": 0.0}

    def add(key: str, t0: float, c0: float) -> None:
        spent[key] += time.perf_counter() - t0
        spent[key + "_cpu"] += time.thread_time() - c0  # the run is single-threaded: robust to other jobs' load

    def timed(key, fn):
        def wrapper(*a, **k):
            t0, c0 = time.perf_counter(), time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                add(key, t0, c0)

        return wrapper

    def timed_iter(fn):
        def wrapper(*a, **k):
            it = iter(fn(*a, **k))
            while True:
                t0, c0 = time.perf_counter(), time.thread_time()
                try:
                    chunk = next(it)
                except StopIteration:
                    add("simulation", t0, c0)
                    return
                add("simulation", t0, c0)
                yield chunk

        return wrapper

    braking = problems.braking_problem

    def hooked_problem(*a, **k):
        pb = braking(*a, **k)
        import dataclasses

        stream = timed_iter(pb.stream) if pb.stream is not None else None
        return dataclasses.replace(pb, simulate=timed("simulation", pb.simulate), stream=stream)

    problems.braking_problem = hooked_problem  # problems.problem_for builds the run's problem with it
    ce_fit.fit_proposal = timed("fit", ce_fit.fit_proposal)  # the name the CE fits call
    engine.Experiment.run = timed("run", engine.Experiment.run)
    cpu0 = resource.getrusage(resource.RUSAGE_SELF)
    rc = main(["run", *argv])  # with its arguments given, main returns (run as the program, it ends the process)
    cpu1 = resource.getrusage(resource.RUSAGE_SELF)
    spent["cpu"] = (cpu1.ru_utime - cpu0.ru_utime) + (cpu1.ru_stime - cpu0.ru_stime)
    spent["peak_rss_mb"] = cpu1.ru_maxrss / 1024
    spent["rc"] = rc
    spent["twin_us"], spent["twin_cpu_us"] = _pure_twin_us(int(argv[argv.index("--n") + 1]) if "--n" in argv else 100)
    print("SCALE " + json.dumps(spent), flush=True)


def _pure_twin_us(n: int) -> tuple[float, float]:
    """Microseconds per rollout of the pure batched twin, wall and CPU: ``min(n, 20,000)`` braking rollouts drawn
    i.i.d. from the shipped PEM (sampler and target the same detector), the best of three."""
    import numpy as np
    from pemviz.core.detectors import PEMDetector
    from pemviz.pem import load_pem
    from pemviz.scenarios.braking.batched import simulate_batched

    m, pem = min(n, 20_000), PEMDetector(load_pem())
    best, best_cpu = float("inf"), float("inf")
    for seed in range(3):
        t0, c0 = time.perf_counter(), time.thread_time()
        simulate_batched(None, m, pem, pem, np.random.default_rng(seed))
        best, best_cpu = min(best, time.perf_counter() - t0), min(best_cpu, time.thread_time() - c0)
    return best / m * 1e6, best_cpu / m * 1e6


CORES_CASES = {
    "crossing": ("--scenario", "crossing", "--method", "mc"),
    "cut-in": ("--scenario", "cut-in", "--method", "mc"),
    "braking": (),  # the default run: 2,100 rollouts, never the pool
    "crossing-default": ("--scenario", "crossing"),  # its stages, then plain Monte Carlo
    "crossing-save": ("--scenario", "crossing", "--method", "mc", "--save-rollouts"),  # streamed to a Parquet file
}
"""``--cores``: the runs timed with the default workers and with ``--workers 1``; the plain Monte Carlo ones at
``--cores-n`` rollouts."""


def _peaks(pid: int, peaks: dict[int, float], done: threading.Event, cpu: dict[int, float] | None = None) -> None:
    """Every 0.2 s until ``done``: the peak resident memory (``VmHWM``, MB) of ``pid`` and of each of its workers, into
    ``peaks``: its local executor's (children named ``LokyProcess``) and its Ray cluster's (descendants named
    ``ray::...``), whose CPU seconds (user + system, at the last look) go into ``cpu`` (they are not the run's
    children: ``RUSAGE_CHILDREN`` misses them)."""
    tick = os.sysconf("SC_CLK_TCK")
    while not done.wait(0.2):
        parent: dict[int, int] = {}
        stats: dict[int, list[str]] = {}
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit():
                try:
                    fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                except (OSError, IndexError):
                    continue
                parent[int(entry.name)], stats[int(entry.name)] = int(fields[1]), fields
        for p in parent:
            ancestor, depth = parent[p], 0
            while ancestor not in (pid, 0, 1) and depth < 8:
                ancestor, depth = parent.get(ancestor, 0), depth + 1
            try:
                cmd = (Path("/proc") / str(p) / "cmdline").read_bytes() if p != pid and ancestor == pid else b""
                ray = cmd.startswith(b"ray::")
                if p != pid and not ray and not (parent[p] == pid and b"LokyProcess" in cmd):
                    continue
                hwm = re.search(r"VmHWM:\s+(\d+) kB", (Path("/proc") / str(p) / "status").read_text())
            except (OSError, ValueError):
                continue
            if hwm:
                peaks[p] = max(peaks.get(p, 0.0), int(hwm.group(1)) / 1024)
            if ray and cpu is not None:
                cpu[p] = (int(stats[p][11]) + int(stats[p][12])) / tick


_PAYS = (
    "import sys; import pemviz.engine.resources as r; r.POOL_PAYS_S = %r; from pemviz import cli; "
    "sys.exit(cli.main(sys.argv[1:]))"
)
"""``--pays-s``: ``pemviz run`` with the pool's threshold set first (``python -c ... run ARGS``)."""


_RAY = (
    "import sys, ray; ray.init(num_cpus=%d, include_dashboard=False, log_to_driver=False); from pemviz import cli; "
    "code = cli.main(sys.argv[1:]); ray.shutdown(); sys.exit(code)"
)
"""``--ray W``: ``pemviz run --executor ray`` on a local cluster of W worker processes started first
(``python -c ... run ARGS``)."""

RUN_SECONDS = re.compile(r"from \d+ simulations in ([\d.]+) s")
"""The run's own seconds, from its estimate line."""


def _seconds(text: str) -> float:
    value, unit = text.split()
    return float(value) * {"s": 1.0, "min": 60.0, "h": 3600.0}[unit]


def cores(
    cases: list[str],
    n: int,
    workers: str | None,
    once: bool = False,
    pays_s: float | None = None,
    ray: list[int] | None = None,
) -> None:
    """Time each case with the default workers (or ``workers``) and (unless ``once``) with ``--workers 1``, in fresh
    processes: wall, CPU (the run's and its workers', user + system), the run's first time estimate, the peak memory of
    the run's process and of its largest worker, the load. ``pays_s``: the pool starts where the blocks left would
    take that many CPU seconds (:data:`pemviz.engine.resources.POOL_PAYS_S`; None: its value). ``ray``: also on a
    local Ray cluster of each of these sizes, with the speed-up over one worker and its ratio to the ideal."""
    print(f"{len(os.sched_getaffinity(0))} usable cores; load average before: {os.getloadavg()[0]:.2f}")
    print(
        f"{'case':>17} {'workers':>8} {'wall s':>7} {'cpu s':>7} {'first est. s':>12} {'est/wall':>8} {'run MB':>7} "
        f"{'worker MB':>9} {'workers':>7}  load (1, 5 min)"
    )
    for case in cases:
        args = [*(["--n", str(n)] if "mc" in CORES_CASES[case] else []), *CORES_CASES[case]]
        walls, runs = {}, {}
        sizes = [f"ray{r}" for r in ray or []]
        for w in [*((workers or "default",) if once else (workers or "default", "1")), *sizes]:
            tmp = tempfile.TemporaryDirectory()
            saved = [str(Path(tmp.name) / "rollouts.parquet")] if args[-1:] == ["--save-rollouts"] else []
            cmd = [sys.executable, "-m", "pemviz.cli"] if pays_s is None else [sys.executable, "-c", _PAYS % pays_s]
            cmd = [sys.executable, "-c", _RAY % int(w[3:])] if w.startswith("ray") else cmd
            cmd += ["run", "--no-record", *args, *saved]
            cmd += [] if w == "default" else ["--executor", "ray"] if w.startswith("ray") else ["--workers", w]
            peaks: dict[int, float] = {}
            ray_cpu: dict[int, float] = {}
            done = threading.Event()
            t0, c0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
            proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            watch = threading.Thread(target=_peaks, args=(proc.pid, peaks, done, ray_cpu), daemon=True)
            watch.start()
            out, err = proc.communicate()
            walls[w] = wall = time.perf_counter() - t0
            c1 = resource.getrusage(resource.RUSAGE_CHILDREN)  # the run and its workers, reaped
            done.set()
            watch.join()
            cpu = c1.ru_utime - c0.ru_utime + c1.ru_stime - c0.ru_stime + sum(ray_cpu.values())
            tmp.cleanup()
            if proc.returncode != 0:
                raise SystemExit(f"{case} --workers {w} failed:\n{err[-3000:]}")
            own = RUN_SECONDS.search(out + err)
            runs[w] = float(own.group(1)) if own else float("nan")
            first = re.search(r"run ~([\d.]+ (?:s|min|h)) left", err)
            est = _seconds(first.group(1)) if first else float("nan")
            run_mb = peaks.pop(proc.pid, float("nan"))
            worker_mb = max(peaks.values(), default=0.0)
            load = os.getloadavg()
            print(
                f"{case:>17} {w:>8} {wall:>7.1f} {cpu:>7.1f} {est:>12.1f} {est / wall:>8.2f} {run_mb:>7.0f} "
                f"{worker_mb:>9.0f} {len(peaks):>7}  {load[0]:.2f} {load[1]:.2f}",
                flush=True,
            )
        first_w = workers or "default"
        if once:
            continue
        print(f"{case:>17}: wall with {first_w} workers / with 1 = {walls[first_w] / walls['1']:.2f}", flush=True)
        cpus = len(os.sched_getaffinity(0))
        for w in sizes:
            ideal = min(int(w[3:]), cpus)
            run_up, wall_up = runs["1"] / runs[w], walls["1"] / walls[w]
            print(
                f"{case:>17}: Ray cluster of {w[3:]}: speed-up over 1 worker {run_up:.2f} (the run's seconds "
                f"{runs[w]:.1f} / {runs['1']:.1f}), {wall_up:.2f} by the process's wall; ideal {ideal} on {cpus} "
                f"cores: {run_up / ideal:.2f} of it ({wall_up / ideal:.2f} by wall)",
                flush=True,
            )


def _timed_child(extra: list[str], what: str) -> tuple[float, dict, int]:
    """Run ``pemviz run *extra`` in a fresh :func:`_child` process: (its wall seconds, its figures, the simulations it
    printed)."""
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, __file__, "--child", *extra], cwd=REPO, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    line = [x for x in proc.stdout.splitlines() if x.startswith("SCALE ")]
    if proc.returncode != 0 or not line:
        raise SystemExit(f"{what} failed:\n{proc.stderr[-3000:]}")
    sims = [x for x in proc.stdout.splitlines() + proc.stderr.splitlines() if "simulations" in x]
    return wall, json.loads(line[0][6:]), int(sims[-1].split(" from ")[1].split()[0]) if sims else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[100, 1000, 10_000, 100_000], help="rollouts per stage")
    ap.add_argument("--record", action="store_true", help="also write a recording and report its size")
    ap.add_argument("--child", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    ap.add_argument("--args", nargs=argparse.REMAINDER, default=[], help="extra arguments for pemviz run")
    ap.add_argument(
        "--check",
        action="store_true",
        help=f"exit 1 if at N = {CHECK_N:,} (other + fit) / simulation exceeds {CHECK_RATIO}",
    )
    ap.add_argument("--plain", action="store_true", help="also plain Monte Carlo of each run's rollouts")
    ap.add_argument("--cores", action="store_true", help="time every core against --workers 1 instead (see --cases)")
    ap.add_argument("--cases", nargs="+", default=["crossing", "cut-in", "braking"], choices=sorted(CORES_CASES))
    ap.add_argument("--cores-n", type=int, default=200_000, help="--cores: plain Monte Carlo's rollouts")
    ap.add_argument("--workers", default=None, help="--cores: the workers compared with 1 (default: every core)")
    ap.add_argument("--once", action="store_true", help="--cores: only with --workers (or the default), not with 1")
    ap.add_argument(
        "--pays-s", type=float, default=None, help="--cores: start the pool where the blocks left take this CPU (s)"
    )
    ap.add_argument("--ray", type=int, nargs="+", default=None, help="--cores: also on local Ray clusters of W workers")
    args = ap.parse_args()
    if args.child is not None:
        _child(args.child)
        return 0
    if args.cores:
        if args.ray and min(args.ray) < 1:
            raise SystemExit(f"--ray: cluster sizes of at least 1 worker, got {args.ray}")
        if args.ray and args.once:
            raise SystemExit("--ray needs the --workers 1 run to compare with: leave out --once")
        cores(args.cases, args.cores_n, args.workers, args.once, args.pays_s, args.ray)
        return 0
    os.environ.setdefault("RERUN_ANALYTICS", "false")
    print(f"{os.cpu_count()} cores; times in seconds, per simulation in microseconds")
    print(
        f"{'N':>7} {'sims':>9} {'rec':>4} {'wall':>7} {'cpu':>7} {'engine':>7} {'sim/run':>8} {'fit/run':>8} "
        f"{'other/run':>9} {'other+fit / sim':>15} {'peak MB':>8} {'rrd MB':>7}  load"
    )
    ratios: dict[int, float] = {}
    lines: list[str] = []
    one = [] if "--workers" in args.args else ["--workers", "1"]
    for n in args.n:
        for record in (False, True) if args.record else (False,):
            with tempfile.TemporaryDirectory() as tmp:
                rrd = Path(tmp) / "scale.rrd"
                extra = ["--n", str(n), "--n-final", str(n), *one, *args.args]
                extra += ["--save", str(rrd)] if record else ["--no-record"]
                wall, f, n_sims = _timed_child(extra, f"N = {n}")
                per = 1e6 / max(n_sims, 1)
                other = f["run"] - f["simulation"] - f["fit"]
                size = rrd.stat().st_size / 1e6 if record and rrd.exists() else float("nan")
                load = " ".join(f"{x:.2f}" for x in os.getloadavg())
                print(
                    f"{n:>7} {n_sims:>9} {'yes' if record else 'no':>4} {wall:>7.1f} {f['cpu']:>7.1f} "
                    f"{f['run']:>7.1f} {f['simulation'] * per:>8.1f} {f['fit'] * per:>8.1f} {other * per:>9.1f} "
                    f"{(other + f['fit']) / max(f['simulation'], 1e-9):>15.2f} {f['peak_rss_mb']:>8.0f} "
                    f"{size:>7.1f}  {load}",
                    flush=True,
                )
                if not record and args.plain:
                    mc = ["--method", "mc", "--n", str(n_sims), *one, *args.args, "--no-record"]
                    mc_wall, mc_f, _ = _timed_child(mc, f"plain Monte Carlo of {n_sims}")
                    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
                    lines.append(
                        f"N = {n}: {n_sims:,} rollouts: the run {f['run']:.1f} s, "
                        f"plain Monte Carlo {mc_f['run']:.1f} s "
                        f"(engine wall: {f['run'] / mc_f['run']:.2f} x; CPU {f['run_cpu'] / mc_f['run_cpu']:.2f} x; "
                        f"process wall {wall:.1f} / {mc_wall:.1f} s = {wall / mc_wall:.2f} x), load {load}"
                    )
                if not record:
                    ratios[n] = (other + f["fit"]) / max(f["simulation"], 1e-9)
                    other_cpu = f["run_cpu"] - f["simulation_cpu"] - f["fit_cpu"]
                    ratio_cpu = (other_cpu + f["fit_cpu"]) / max(f["simulation_cpu"], 1e-9)
                    lines.append(
                        f"N = {n}: (other + fit) / simulation = {ratios[n]:.2f} wall, {ratio_cpu:.2f} CPU; "
                        f"simulation {f['simulation'] * per:.1f} us per rollout = "
                        f"{f['simulation'] * per / f['twin_us']:.2f} x the pure twin's {f['twin_us']:.1f} us "
                        f"wall, {f['simulation_cpu'] * per / f['twin_cpu_us']:.2f} x CPU "
                        f"({f['simulation_cpu'] * per:.1f} / {f['twin_cpu_us']:.1f} us)"
                    )
    print("\n".join(lines))
    if args.check:
        if CHECK_N not in ratios:
            raise SystemExit(f"--check needs N = {CHECK_N} among --n")
        if ratios[CHECK_N] > CHECK_RATIO:
            print(
                f"check failed: at N = {CHECK_N:,} (other + fit) / simulation = {ratios[CHECK_N]:.2f} "
                f"> {CHECK_RATIO}"
            )
            return 1
        print(f"check passed: at N = {CHECK_N:,} (other + fit) / simulation = {ratios[CHECK_N]:.2f} <= {CHECK_RATIO}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
