"""The cheap benchmarks still run: each in its quickest mode as a fresh process (``python benchmarks/X.py ...`` from the
repository root, as benchmarks/README.md says), exit 0 and print a real number where their figures go. Not a timing
check: the numbers only have to be there, finite and positive (about 20 s in all on 2 cores)."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys

from conftest import REPO


def run_benchmark(name: str, *args: str, timeout: float) -> str:
    """``python benchmarks/NAME ARGS`` from the repository root: its stdout, once it has exited 0."""
    proc = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / name), *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**os.environ, "RERUN_ANALYTICS": "false"},
    )
    assert proc.returncode == 0, f"{name} exited {proc.returncode}:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc.stdout


def number(pattern: str, text: str) -> float:
    """The number of the first match of ``pattern``'s group 1 (thousands commas allowed), finite and > 0."""
    found = re.search(pattern, text, re.M)
    assert found is not None, f"no line matches {pattern!r} in:\n{text[-3000:]}"
    value = float(found.group(1).replace(",", ""))
    assert math.isfinite(value) and value > 0, found.group(0)
    return value


def test_sim_speed_quick_prints_every_part_it_runs():
    """Parts 1-3 and 5 (``--quick``; part 3 wraps the run's functions where they are looked up now, so a moved
    function stops it with an AttributeError), at small sizes (part 5: a tenth of its plain Monte Carlo rollouts)."""
    out = run_benchmark(
        "sim_speed.py",
        "--quick",
        "--highway-rollouts",
        "10",
        "--batched-rollouts",
        "2000",
        "--million",
        "20000",
        "--mc-rollouts",
        "2000",
        "20000",
        timeout=240,
    )
    number(r"ratio batched / highway-env = ([\d,.]+)x", out)
    assert "same rollouts on both back-ends: True" in out
    number(r"^2\. .*\n.*\(([\d,]+) rollouts/s\)", out)
    assert number(r"^   simulation\s+([\d.]+) s", out) <= number(r"^   total\s+([\d.]+) s", out)
    number(r"ratio\s+([\d.]+) \(target <=", out)  # part 5: braking's rollouts/s over the cut-in's


def test_honest_intervals_on_one_braking_seed_meets_every_goal():
    """Seed 0 of the default sampler and of plain Monte Carlo on braking: each run's estimate against the exact
    answer (the adaptive run's ratio, ``x1.02``), and the study's verdict."""
    out = run_benchmark(
        "honest_intervals.py", "--seeds", "1", "--scenes", "braking", "--methods", "adaptive", "mc", timeout=180
    )
    ratio = number(r"^  braking adaptive seed 0: .*\(holds [^)]*\), x([\d.]+),", out)
    assert 0.5 < ratio < 2.0
    assert re.search(r"^  braking mc seed 0: ", out, re.M)
    assert "every goal met" in out
