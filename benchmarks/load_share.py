"""The CPU share a run gets beside its own session's other tasks and the machine's other sessions: a CPU-bound loop's
wall over its CPU seconds while K busy loops of its own session run (K = 0, 1, 2 by default), against what
:func:`pemviz.engine.resources.crowding` says from the other tasks' runnable time over the same seconds, and against
adding the session's tasks to the others' (the model before: (G + 1 + inside) / C).

    python benchmarks/load_share.py             # K = 0, 1, 2, ~6 s each
    python benchmarks/load_share.py 0 1 2 0 1 2 --seconds 4
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

from pemviz.engine.resources import competition, crowding, tasks_now, usable_cpus


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("loops", nargs="*", type=int, default=[0, 1, 2], help="busy loops of this session beside it")
    ap.add_argument("--seconds", type=float, default=6.0)
    args = ap.parse_args()
    cpus = usable_cpus()
    print(f"{cpus} CPUs, load average {os.getloadavg()[0]:.2f}")
    print("| own loops | wall / CPU | crowding (shared) | tasks added | other sessions G | inside | load average |")
    print("|---|---|---|---|---|---|---|")
    for k in args.loops:
        loops = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(k)]
        try:
            time.sleep(0.5)
            before, wall0, cpu0 = tasks_now(), time.perf_counter(), time.process_time()
            x = 0
            while time.perf_counter() - wall0 < args.seconds:
                for i in range(100_000):
                    x += i
            wall, cpu, after = time.perf_counter() - wall0, time.process_time() - cpu0, tasks_now()
        finally:
            for p in loops:
                p.kill()
                p.wait()
        if before is None or after is None:
            sys.exit("the tasks' runnable times cannot be read here (/proc/<pid>/task/<tid>/schedstat)")
        c = competition(before, after)
        g = sum(w * min(1.0, n) for w, n in c.groups)  # the sessions with a runnable task, by their share of it
        added = max(1.0, (g + 1 + c.inside) / cpus)
        print(
            f"| {k} | {wall / cpu:.2f} | {crowding(c, cpus):.2f} | {added:.2f} | {g:.2f} | {c.inside:.2f} "
            f"| {os.getloadavg()[0]:.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
