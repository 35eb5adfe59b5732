"""The table of hostile cases tried against pemviz: group, count, passed.

Runs the fault-injection tests (``tests/files/test_faults.py``, with ``FAULT_SEEDS`` random kill points per signal) and
counts their cases by group, then fuzzes the STL parser with ``--stl`` hypothesis-generated strings (the three
text strategies of ``tests/stl/test_stl_fuzz.py``) and counts the strings that raised nothing but ``STLSyntaxError``.

    python scripts/hostile_cases.py                 # 10,000 STL strings, 3 kill points per signal
    python scripts/hostile_cases.py --stl 2000 --seeds 1
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests" / "stl")]  # this checkout's pemviz and the fuzz strategies
GROUPS = {
    "test_signal_": "SIGINT / SIGTERM / SIGKILL at random points (run, estimate, --save-rollouts)",
    "test_disk_": "full disk / file too large",
    "test_concurrent_": "concurrent writers to one path",
    "test_sidecar_": "hostile sidecars and rollout units",
    "test_cli_": "command-line reproductions (outputs, resources, hosts, Ray)",
    "test_writer_": "writer primitives (special files, interrupts)",
}


def fault_cases(seeds: int) -> tuple[Counter, Counter]:
    env = {**os.environ, "FAULT_SEEDS": str(seeds), "RERUN_ANALYTICS": "false"}
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-rA", "-p", "no:warnings", "tests/files/test_faults.py"],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
    )
    tried, passed = Counter(), Counter()
    for m in re.finditer(r"^(PASSED|FAILED|ERROR|SKIPPED) tests/files/test_faults\.py::(\w+)", proc.stdout, re.M):
        group = next((g for p, g in GROUPS.items() if m.group(2).startswith(p)), "other")
        tried[group] += 1
        passed[group] += m.group(1) == "PASSED"
    if not tried:  # a moved test file or a changed report format must not read as "nothing failed"
        tail = (proc.stdout + proc.stderr).strip().splitlines()[-3:]
        raise SystemExit(f"hostile_cases.py: pytest reported no fault-injection case (exit {proc.returncode}): {tail}")
    return tried, passed


def stl_cases(n: int) -> tuple[int, int, Counter]:
    """``n`` strings over the three strategies; returns (tried, passed, outcome counts)."""
    import test_stl_fuzz as fuzz
    from hypothesis import HealthCheck, given, settings

    outcomes: Counter = Counter()
    per = -(-n // 3)
    for strategy in (fuzz.token_text, fuzz.squashed_text, fuzz.any_text):

        @settings(
            max_examples=per, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck)
        )
        @given(strategy)
        def one(text: str) -> None:
            try:
                fuzz.check(text)
                outcomes["parsed or STLSyntaxError"] += 1
            except Exception as exc:  # noqa: BLE001 - counted as a failure of the contract
                outcomes[f"{type(exc).__name__}"] += 1

        one()
    tried = sum(outcomes.values())
    return tried, outcomes["parsed or STLSyntaxError"], outcomes


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stl", type=int, default=10_000, help="STL strings to generate (default 10000)")
    ap.add_argument("--seeds", type=int, default=3, help="random kill points per signal and command (default 3)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    tried, passed = fault_cases(args.seeds)
    stl_tried, stl_passed, outcomes = stl_cases(args.stl)
    rows = [(g, tried[g], passed[g]) for g in GROUPS.values() if tried[g]]
    rows.append(("STL strings (hypothesis): nothing but STLSyntaxError", stl_tried, stl_passed))
    width = max(len(r[0]) for r in rows)
    print(f"| {'group':<{width}} | count | passed |")
    print(f"|{'-' * (width + 2)}|------:|-------:|")
    for group, count, ok in rows:
        print(f"| {group:<{width}} | {count:>5} | {ok:>6} |")
    total, total_ok = sum(r[1] for r in rows), sum(r[2] for r in rows)
    print(f"| {'total':<{width}} | {total:>5} | {total_ok:>6} |")
    print(f"\nSTL outcomes: {dict(outcomes)}; {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    return 0 if total == total_ok else 1


if __name__ == "__main__":
    sys.exit(main())
