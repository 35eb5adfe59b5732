"""Run the browser tests again and again under load and print one table row per run.

The streak is how the panel's Chromium tests show they wait on conditions rather than on luck: every
counted run starts with the 1-minute load average at or above ``--min-load``. When the machine's own
load is lower, busy-loop processes are started (and ended at exit) until it is reached. The streak
stops at the first failing run unless ``--keep-going`` is given; each run's pytest output is kept in
``--log-dir``.

Example (from the repository root)::

    python scripts/browser_streak.py --runs 20 --min-load 3
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BROWSER_TESTS = ["tests/app/test_app.py", "tests/app/test_app_explain.py"]
BUSY = "while True: pass"


def load1() -> float:
    """The 1-minute load average (runnable processes, from /proc/loadavg)."""
    return float(Path("/proc/loadavg").read_text().split()[0])


class Burners:
    """Busy-loop processes that raise the load average; all ended by ``stop``."""

    def __init__(self, most: int) -> None:
        self.most = most
        self.procs: list[subprocess.Popen] = []

    def add(self) -> bool:
        if len(self.procs) >= self.most:
            return False
        self.procs.append(subprocess.Popen([sys.executable, "-c", BUSY]))
        return True

    def remove(self) -> None:
        if self.procs:
            p = self.procs.pop()
            p.terminate()
            p.wait(10)

    def stop(self) -> None:
        while self.procs:
            self.remove()


def reach_load(min_load: float, burners: Burners, timeout_s: float) -> float:
    """Add burners until the 1-minute load is at least ``min_load``; the load reached.

    The load average follows the number of runnable processes with a one-minute time constant, so it is
    polled (every 5 s) until the condition holds. Burners beyond what is needed are ended first.
    Raises TimeoutError when the load is not reached within ``timeout_s`` seconds.
    """
    while burners.procs and load1() > min_load + 2.0:
        burners.remove()
    end = time.monotonic() + timeout_s
    added_at = time.monotonic()
    while (now := load1()) < min_load:
        if time.monotonic() > end:
            raise TimeoutError(f"load {now:.2f} < {min_load} after {timeout_s:.0f} s with {len(burners.procs)} burners")
        # one more burner when the load has had 20 s to respond to the last change and is still short
        # (n busy processes alone bring the load towards n, never above it: the target needs more than it)
        if not burners.procs or time.monotonic() - added_at > 20:
            if burners.add():
                added_at = time.monotonic()
        time.sleep(5)  # polling the load average, not a synchronisation of the tests
    return now


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=20, help="runs in a row to pass (default 20)")
    ap.add_argument("--min-load", type=float, default=3.0, help="1-minute load average at each run's start")
    ap.add_argument("--max-burners", type=int, default=5, help="most busy-loop processes to add (default 5)")
    ap.add_argument("--first", type=int, default=1, help="number of the first run (to continue a streak)")
    ap.add_argument("--keep-going", action="store_true", help="go on after a failing run")
    ap.add_argument("--log-dir", type=Path, default=Path("/tmp/browser_streak"), help="pytest output per run")
    ap.add_argument(
        "tests",
        nargs="*",
        default=BROWSER_TESTS,
        help="test files (default: tests/app/test_app.py and test_app_explain.py)",
    )
    args = ap.parse_args(argv)
    args.log_dir.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "RERUN_ANALYTICS": "false"}
    burners = Burners(args.max_burners)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--durations=5", *args.tests]
    print("command:", " ".join(command[1:]), flush=True)
    print(f"{'run':>3} {'result':<6} {'seconds':>7} {'load start':>10} {'load end':>8} {'burners':>7}", flush=True)
    passed_in_a_row = 0
    try:
        for run in range(args.first, args.first + args.runs):
            start_load = reach_load(args.min_load, burners, timeout_s=300)
            n_burners = len(burners.procs)
            t0 = time.monotonic()
            log = args.log_dir / f"run{run:02d}.log"
            with log.open("w") as out:
                rc = subprocess.call(command, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT)
            seconds = time.monotonic() - t0
            result = "pass" if rc == 0 else f"FAIL{rc}"
            print(
                f"{run:>3} {result:<6} {seconds:>7.1f} {start_load:>10.2f} {load1():>8.2f} {n_burners:>7}", flush=True
            )
            if rc == 0:
                passed_in_a_row += 1
            else:
                passed_in_a_row = 0
                print(f"    see {log}", flush=True)
                if not args.keep_going:
                    break
    finally:
        burners.stop()
    print(f"{passed_in_a_row} runs passed in a row (of {args.runs} asked, from run {args.first})", flush=True)
    return 0 if passed_in_a_row == args.runs else 1


if __name__ == "__main__":
    sys.exit(main())
