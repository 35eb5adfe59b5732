"""Speed of the braking scenario's two back-ends, and where the time of ``pemviz run`` goes (issue 7).

Prints, in one run:

1. rollouts per second of the highway-env back-end and of the batched back-end (PEM detector, T = 100),
   and their ratio (target >= 100x), after checking that both gave the same rollouts;
2. 10^6 rollouts x 100 steps with the PEM detector, streamed in chunks (``iter_batched``), in a
   fresh process: seconds (target <= 60 s on 2 cores) and peak resident memory (target <= 4 GiB);
3. the time split of the default ``pemviz run`` (simulation, PEM, proposal sampling, proposal training,
   STL, recording, console, other), measured by wrapping those functions from the outside;
4. wall-clock (and CPU) seconds of the ``pemviz run`` command itself (target <= 10 s with ``--sim batched``) and
   of ``pemviz run --method mc --n 1000000 --sim batched --no-record`` (target <= 60 s), with the peak
   resident memory of each command;
5. plain Monte Carlo on the cut-in scenario against the braking scenario: rollouts per second of ``pemviz run
   --scenario cut-in --method mc --n 20000 --no-record`` and of ``pemviz run --method mc --n 200000 --no-record``
   (each from its "from N simulations in S s" line), run back to back, and their ratio braking / cut-in (target
   <= 14); with ``--before TREE`` (a git worktree of older code, e.g. ``git worktree add /tmp/before HEAD``) the
   same for that code, run by this Python with ``PYTHONPATH=TREE``.

The machine may be shared: the 1-minute load average is printed before and after; re-measure when it
is low (``uptime``). Run from the repository root:

    python benchmarks/sim_speed.py              # everything (~2-3 minutes)
    python benchmarks/sim_speed.py --quick      # parts 1-3 and 5, the highway-env split skipped
    python benchmarks/sim_speed.py --quick --highway-rollouts 10 --batched-rollouts 2000 --million 20000 \
        --mc-rollouts 2000 20000  # ~20 s
    python benchmarks/sim_speed.py --cut-in [--before /tmp/before] [--repeat 2]   # part 5 only (~1-2 minutes)
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
TARGET_RATIO = 100.0
TARGET_MILLION_S = 60.0
TARGET_RSS_GIB = 4.0
TARGET_RUN_S = 10.0
TARGET_CUT_IN_RATIO = 14.0
"""Part 5: braking's plain Monte Carlo rollouts/s over the cut-in's, at most (about 69 before the cut-in's detector
evaluated each head once per step)."""
CUT_IN_MC_N, BRAKING_MC_N = 20_000, 200_000
"""Part 5's rollouts: ``pemviz run --scenario cut-in --method mc --n 20000`` and ``pemviz run --method mc --n 200000``
(``--mc-rollouts CUT_IN BRAKING``; fewer measure the start-up more than the rollouts)."""


def mc_command(scenario: str, n: int) -> list[str]:
    """The ``pemviz`` arguments of part 5's plain Monte Carlo run of ``n`` rollouts on ``scenario``."""
    return ["run", "--scenario", scenario, "--method", "mc", "--n", str(n), "--no-record"]


def load() -> str:
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f}, {five:.2f}, {fifteen:.2f} on {os.cpu_count()} cores"


def verdict(ok: bool) -> str:
    return "ok" if ok else "MISSED"


# -- 1. rollouts per second ------------------------------------------------------------------------------


def rollouts_per_second(n_highway: int, n_batched: int, seed: int) -> None:
    import torch

    torch.set_num_threads(1)
    from pemviz.core.detectors import PEMDetector
    from pemviz.pem import load_pem
    from pemviz.scenarios import simulate
    from pemviz.scenarios.braking.batched import simulate_batched
    from pemviz.scenarios.braking.simulator import BrakingParams, BrakingScenario

    p = BrakingParams()
    pem = PEMDetector(load_pem())
    simulate(lambda: BrakingScenario(p), 2, pem, pem, np.random.default_rng(0), p.n_steps)  # imports, caches
    t0 = time.perf_counter()
    black_box = simulate(lambda: BrakingScenario(p), n_highway, pem, pem, np.random.default_rng(seed), p.n_steps)
    highway_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    same_n = simulate_batched(p, n_highway, pem, pem, np.random.default_rng(seed))
    same_n_s = time.perf_counter() - t0
    fields = ("observations", "detected", "log_p", "log_q")
    identical = all(np.array_equal(getattr(black_box, f), getattr(same_n, f)) for f in fields)
    t0 = time.perf_counter()
    simulate_batched(p, n_batched, pem, pem, np.random.default_rng(seed))
    big_s = time.perf_counter() - t0
    hw, small, big = n_highway / highway_s, n_highway / same_n_s, n_batched / big_s
    print(f"1. rollouts per second (PEM detector, T = {p.n_steps}; {load()})")
    print(f"   highway-env  {n_highway:>9,} rollouts  {highway_s:8.2f} s  {hw:>12,.0f} rollouts/s")
    print(
        f"   batched      {n_highway:>9,} rollouts  {same_n_s:8.3f} s  {small:>12,.0f} rollouts/s  "
        f"({small / hw:,.0f}x)"
    )
    print(f"   batched      {n_batched:>9,} rollouts  {big_s:8.3f} s  {big:>12,.0f} rollouts/s  ({big / hw:,.0f}x)")
    print(f"   same rollouts on both back-ends: {identical}")
    ratio = big / hw
    print(
        f"   ratio batched / highway-env = {ratio:,.0f}x (target >= {TARGET_RATIO:.0f}x): "
        f"{verdict(ratio >= TARGET_RATIO)}"
    )


def peak_rss_gib() -> float:
    """This process's peak resident memory (GiB): VmHWM, which, unlike ru_maxrss, does not inherit the
    parent's peak across fork + exec."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024 / 2**30
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 2**30


# -- 2. a million rollouts in a fresh process ------------------------------------------------------------


def million_child(n: int, seed: int) -> None:
    """Child process: stream n PEM rollouts, print seconds, failures and peak RSS as JSON."""
    from pemviz.pem import load_pem
    from pemviz.scenarios.braking.batched import iter_batched
    from pemviz.scenarios.braking.problem import braking_problem

    problem = braking_problem(load_pem())
    pem = problem.target
    t0, c0 = time.perf_counter(), time.process_time()
    failures = sum(int(problem.failed(b).sum()) for b in iter_batched(None, n, pem, pem, np.random.default_rng(seed)))
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    rss_gib = peak_rss_gib()
    print(
        json.dumps(
            {
                "seconds": seconds,
                "cpu_s": cpu,
                "rss_gib": rss_gib,
                "failures": failures,
                "n": n,
            }
        )
    )


def million(n: int, seed: int) -> None:
    print(f"2. {n:,} rollouts x 100 steps, PEM detector, streamed in chunks ({load()})")
    out = subprocess.run(
        [sys.executable, __file__, "--million-child", str(n), "--seed", str(seed)],
        capture_output=True,
        text=True,
        check=True,
        cwd=REPO,
    )
    r = json.loads(out.stdout.strip().splitlines()[-1])
    print(
        f"   {r['seconds']:.1f} s wall, {r['cpu_s']:.1f} s CPU ({n / r['seconds']:,.0f} rollouts/s), "
        f"{r['failures']} failures of {r['n']:,}"
    )
    rss = r["rss_gib"]
    print(
        f"   time <= {TARGET_MILLION_S:.0f} s: {verdict(r['seconds'] <= TARGET_MILLION_S)}; "
        f"peak RSS {rss:.2f} GiB <= {TARGET_RSS_GIB:.0f} GiB: {verdict(rss <= TARGET_RSS_GIB)}"
    )


# -- 3. where the time of `pemviz run` goes -------------------------------------------------------------


class Split:
    """Exclusive wall time per category: nested wrapped calls are charged to the innermost one."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self._children = [0.0]

    def wrap(self, category: str, fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            self._children.append(0.0)
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - t0
                inner = self._children.pop()
                self.seconds[category] += elapsed - inner
                self._children[-1] += elapsed

        return timed


def time_split(sim: str) -> None:
    import pemviz.estimators.cross_entropy as cross_entropy
    import pemviz.scenarios.braking.problem as braking
    import pemviz.sinks.console as console
    import pemviz.sinks.recording as recording
    from pemviz import cli
    from pemviz.core.problems import Problem
    from pemviz.core.sampling import Proposal
    from pemviz.pem import PEM

    split = Split()
    patches = [  # the braking problem's rollout functions look these names up in its module at each call
        (braking, "simulate", "simulation"),
        (braking, "simulate_batched", "simulation"),
        (braking, "branch", "simulation"),
        (braking, "branch_rollouts", "simulation"),
        (PEM, "logit_at_gap", "PEM"),
        (Proposal, "detect_logit", "proposal sampling"),
        (cross_entropy, "pretrain_proposal", "proposal training"),
        (cross_entropy, "ce_update", "proposal training"),
        (cross_entropy.EliteSteps, "fit", "proposal training"),  # the default fit: every failure since the level
        (Problem, "robustness", "STL"),
        (recording.RerunSink, "__call__", "recording"),
        (recording.RerunSink, "close", "recording"),
        (console.ConsoleSink, "__call__", "console"),
    ]
    saved = [(owner, name, getattr(owner, name)) for owner, name, _ in patches]
    for owner, name, category in patches:
        setattr(owner, name, split.wrap(category, getattr(owner, name)))
    devnull = open(os.devnull, "w")
    try:
        with tempfile.TemporaryDirectory() as tmp:
            stdout, stderr = sys.stdout, sys.stderr
            sys.stdout = sys.stderr = devnull
            t0 = time.perf_counter()
            try:
                cli.main(["run", "--sim", sim, "--save", str(Path(tmp) / "split.rrd")])
            finally:
                total = time.perf_counter() - t0
                sys.stdout, sys.stderr = stdout, stderr
    finally:
        devnull.close()
        for owner, name, fn in saved:
            setattr(owner, name, fn)
    print(f"3. time split of `pemviz run --sim {sim}` (default experiment, recording to a .rrd; {load()})")
    order = ["simulation", "PEM", "proposal sampling", "proposal training", "STL", "recording", "console"]
    accounted = 0.0
    for category in order:
        s = split.seconds.get(category, 0.0)
        accounted += s
        print(f"   {category:<18} {s:7.2f} s  {100 * s / total:5.1f} %")
    print(f"   {'other':<18} {total - accounted:7.2f} s  {100 * (total - accounted) / total:5.1f} %")
    print(f"   {'total':<18} {total:7.2f} s   (in-process; simulation excludes the detectors' own time)")


# -- 4. the commands' wall time -------------------------------------------------------------------------


def command_wall(args: list[str]) -> tuple[float, float, float, int]:
    """Wall seconds, CPU seconds (user + system), peak RSS (GiB) and exit status of
    ``python -m pemviz.cli ARGS`` in a fresh process.

    A small wrapper process starts the command and reads its ru_maxrss (the wrapper is a fresh process,
    so the command does not inherit this benchmark's peak)."""
    cmd = [
        sys.executable,
        "-c",
        "import resource, subprocess, sys; "
        "r = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode; "
        "u = resource.getrusage(resource.RUSAGE_CHILDREN); print(u.ru_maxrss, u.ru_utime + u.ru_stime, r)",
        sys.executable,
        "-m",
        "pemviz.cli",
        *args,
    ]
    t0 = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, check=True, cwd=REPO)
    wall = time.perf_counter() - t0
    rss_kib, cpu_s, rc = out.stdout.split()
    return wall, float(cpu_s), int(rss_kib) * 1024 / 2**30, int(rc)


def commands(mc_million: bool) -> None:
    print(f"4. wall time of the commands, fresh processes ({load()})")
    runs = [
        (["run", "--sim", "batched", "--no-record"], TARGET_RUN_S),
        (["run", "--sim", "batched"], TARGET_RUN_S),
        (["run", "--sim", "highway-env", "--no-record"], None),
    ]
    if mc_million:
        runs.append((["run", "--method", "mc", "--n", "1000000", "--sim", "batched", "--no-record"], TARGET_MILLION_S))
    with tempfile.TemporaryDirectory() as tmp:
        for args, target in runs:
            if "--no-record" not in args:
                args = [*args, "--save", str(Path(tmp) / "run.rrd")]
            wall, cpu, rss, rc = command_wall(args)
            shown = " ".join(a if not a.endswith(".rrd") else "(tmp).rrd" for a in args)
            goal = "" if target is None else f"  target <= {target:.0f} s: {verdict(wall <= target and rc == 0)}"
            print(
                f"   pemviz {shown:<62} {wall:6.1f} s wall {cpu:6.1f} s CPU  peak RSS {rss:5.2f} GiB  "
                f"exit {rc}{goal}"
            )


# -- 5. plain Monte Carlo: the cut-in against the braking scenario ----------------------------------------


def mc_rate(args: list[str], tree: Path | None = None) -> tuple[float, int, float]:
    """(rollouts per second, rollouts, seconds) of ``python -m pemviz.cli ARGS`` in a fresh process, read from its
    "from N simulations in S s" line; ``tree``: run the code of that directory (``PYTHONPATH``) instead of this one.

    Raises:
        RuntimeError: the command failed or printed no such line.
    """
    import re

    env = dict(os.environ, RERUN_ANALYTICS="false")
    if tree is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(tree), *filter(None, [env.get("PYTHONPATH")])])
    out = subprocess.run(
        [sys.executable, "-m", "pemviz.cli", *args], capture_output=True, text=True, cwd=tree or REPO, env=env
    )
    found = re.search(r"from ([\d,]+) simulations in ([\d.]+) s", out.stdout)
    if out.returncode != 0 or found is None:
        raise RuntimeError(
            f"pemviz {' '.join(args)} (exit {out.returncode}) printed no 'from N simulations in S s' "
            f"line:\n{out.stdout[-2000:]}{out.stderr[-2000:]}"
        )
    n, seconds = int(found.group(1).replace(",", "")), float(found.group(2))
    return n / seconds, n, seconds


def cut_in_vs_braking(
    before: Path | None, repeat: int, n_cut_in: int = CUT_IN_MC_N, n_braking: int = BRAKING_MC_N
) -> list[float]:
    """Print part 5 for this code (and ``before``'s): each repeat runs braking's then the cut-in's command
    (``n_braking``, ``n_cut_in`` rollouts). Returns this code's ratios (braking's rollouts/s over the cut-in's), one
    per repeat."""
    print(f"5. plain Monte Carlo, cut-in against braking, fresh processes ({load()})")
    trees = [("after", None)] if before is None else [("before", before), ("after", None)]
    ratios = []
    for _ in range(repeat):
        for label, tree in trees:
            braking, nb, sb = mc_rate(mc_command("braking", n_braking), tree)
            cut_in, nc, sc = mc_rate(mc_command("cut-in", n_cut_in), tree)
            ratio = braking / cut_in
            ratios += [ratio] if tree is None else []
            print(
                f"   {label:<6} cut-in {cut_in:>8,.0f} rollouts/s ({nc:,} in {sc:.1f} s)  braking {braking:>8,.0f} "
                f"rollouts/s ({nb:,} in {sb:.1f} s)  ratio {ratio:5.1f} (target <= {TARGET_CUT_IN_RATIO:.0f}): "
                f"{verdict(ratio <= TARGET_CUT_IN_RATIO)}"
            )
    print(f"   ({load()})")
    return ratios


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--highway-rollouts", type=int, default=200, help="rollouts timed on highway-env")
    parser.add_argument("--batched-rollouts", type=int, default=100_000, help="rollouts timed on batched")
    parser.add_argument("--million", type=int, default=1_000_000, help="rollouts of part 2")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="skip the highway-env split and part 4")
    parser.add_argument("--no-mc-million", action="store_true", help="skip `pemviz run --method mc --n 1000000`")
    parser.add_argument("--cut-in", action="store_true", help="part 5 only: cut-in vs braking plain Monte Carlo")
    parser.add_argument(
        "--before",
        type=Path,
        default=None,
        help="part 5 also for the code of this directory (a git worktree), run first",
    )
    parser.add_argument("--repeat", type=int, default=1, help="part 5's measurements per code")
    parser.add_argument(
        "--mc-rollouts",
        type=int,
        nargs=2,
        default=[CUT_IN_MC_N, BRAKING_MC_N],
        metavar=("CUT_IN", "BRAKING"),
        help="part 5's plain Monte Carlo rollouts on the cut-in and on braking",
    )
    parser.add_argument("--million-child", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.million_child is not None:
        million_child(args.million_child, args.seed)
        return
    os.environ.setdefault("RERUN_ANALYTICS", "false")
    print(f"start: {load()}")
    if args.cut_in:
        cut_in_vs_braking(args.before, args.repeat, *args.mc_rollouts)
        print(f"end: {load()}")
        return
    rollouts_per_second(args.highway_rollouts, args.batched_rollouts, args.seed)
    million(args.million, args.seed)
    for sim in ("batched",) if args.quick else ("batched", "highway-env"):
        time_split(sim)
    if not args.quick:
        commands(not args.no_mc_million)
    cut_in_vs_braking(args.before, args.repeat, *args.mc_rollouts)
    print(f"end: {load()}")


if __name__ == "__main__":
    main()
