"""What the rerun recording adds to ``pemviz run``'s wall time, and the recording's size.

    python benchmarks/recording_overhead.py            # the default experiment (1,200 rollouts x 100 steps)
    python benchmarks/recording_overhead.py --repeats 5 --args --k 3 --n 50

Runs ``pemviz run --no-record`` and ``pemviz run --save X.rrd`` (same seed) back to back, alternating
which goes first, ``--repeats`` times each, and prints the wall time of every run, the median ratio
save / no-record, and the size of the ``.rrd``. The target (issue 8): ratio <= 1.20 and <= 50 MB.
The load average (``os.getloadavg``) is printed before and after: on a shared machine compare runs taken
back to back only.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def timed_run(extra: list[str]) -> tuple[float, float]:
    """(wall s, CPU s) of one ``python -m pemviz.cli run ...`` (interpreter start and imports included).

    CPU = user + system time of the child and all its threads (``RUSAGE_CHILDREN``): on a machine shared
    with other jobs it varies much less than the wall time.
    """
    cmd = [sys.executable, "-m", "pemviz.cli", "run", *extra]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stderr}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--args", nargs=argparse.REMAINDER, default=[], help="extra arguments for pemviz run")
    args = ap.parse_args()
    os.environ.setdefault("RERUN_ANALYTICS", "false")
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())} ({os.cpu_count()} cores)")
    plain, saved, plain_cpu, saved_cpu, size = [], [], [], [], 0
    with tempfile.TemporaryDirectory() as tmp:
        rrd = Path(tmp) / "bench.rrd"
        for i in range(args.repeats):
            order = ("plain", "save") if i % 2 == 0 else ("save", "plain")
            for what in order:
                if what == "plain":
                    wall, cpu = timed_run([*args.args, "--no-record"])
                    plain.append(wall)
                    plain_cpu.append(cpu)
                    print(f"  run {i + 1} --no-record: {wall:6.1f} s wall {cpu:6.1f} s CPU", flush=True)
                else:
                    rrd.unlink(missing_ok=True)  # `pemviz run --save` refuses to replace a file
                    wall, cpu = timed_run([*args.args, "--save", str(rrd)])
                    saved.append(wall)
                    saved_cpu.append(cpu)
                    size = rrd.stat().st_size
                    print(
                        f"  run {i + 1} --save:      {wall:6.1f} s wall {cpu:6.1f} s CPU ({size / 1e6:.2f} MB)",
                        flush=True,
                    )
    ratios = [s / p for s, p in zip(saved, plain, strict=False)]
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"median wall: --no-record {statistics.median(plain):.1f} s, --save {statistics.median(saved):.1f} s")
    print(f"pair ratios save / no-record: {' '.join(f'{r:.3f}' for r in ratios)}")
    print(f"wall ratio (median / median): {statistics.median(saved) / statistics.median(plain):.3f}  (target <= 1.20)")
    print(f"wall ratio (min / min):       {min(saved) / min(plain):.3f}")
    print(f"CPU ratio (median / median):  {statistics.median(saved_cpu) / statistics.median(plain_cpu):.3f}")
    print(f"recording size: {size / 1e6:.2f} MB  (target <= 50 MB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
