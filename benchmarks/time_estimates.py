"""How right the time estimates are: the range the first progress line gives (the planned stages, up to their retry
and plain Monte Carlo's cap) and the panel's cost line (the same words, :func:`pemviz.app.form.run_cost`) against what
the run then took, for the default braking, crossing and cut-in runs (each scene's own default: the cut-in's tilt).

Each run is a fresh ``pemviz run --no-record`` (``--repeat`` times per scene); every progress line is read as it
arrives, and the run ends at its estimate (the "from N simulations in S s" line; the explanation and the teardown
after it are not the run). A line's prediction of the whole run is its "elapsed E s" plus its "run ~X s left" (and its
"up to ~Y": the upper end). Per run it prints:

- first: the first line's range, low-high, and whether it holds the wall time (low / 1.25 <= wall <= high);
- end: the estimate at the run's planned end, against the wall (target: within 25 %): for a run that ends with its
  planned stages, the first line's low end; for a run that falls back to plain Monte Carlo, the line of the plain
  rollouts' first batch (its low-high) and, once it has seen failures, its estimate after that first batch;
- panel: the cost line's range, made just before the run starts, and whether it holds the wall time.

Both price the run by a pilot of the scene's own rollouts (:func:`pemviz.engine.cost.pilot_speed`) and the
machine's load (:func:`pemviz.engine.resources.load_slowdown`); the load average is printed before and after.
``--busy K`` runs K busy loops (other processes) throughout.

    nice -n 5 python benchmarks/time_estimates.py             # 1 run of each scene (~3-10 min on 2 loaded cores)
    nice -n 5 python benchmarks/time_estimates.py --scenes crossing-mc-1 crossing-mc   # one worker against every core
    python benchmarks/time_estimates.py --repeat 3 --scenes braking cut-in
    python benchmarks/time_estimates.py --log runs.log       # also every line of the runs, with its second
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time

SCENES = {
    "braking": ["run", "--no-record"],
    "crossing": ["run", "--scenario", "crossing", "--no-record"],
    "cut-in": ["run", "--scenario", "cut-in", "--no-record"],
    "crossing-mc": ["run", "--scenario", "crossing", "--method", "mc", "--n", "200000", "--no-record"],
    "crossing-mc-1": [
        "run",
        "--scenario",
        "crossing",
        "--method",
        "mc",
        "--n",
        "200000",
        "--workers",
        "1",
        "--no-record",
    ],
}
"""Scene -> its run; ``crossing-mc`` and ``crossing-mc-1``: 200,000 plain crossing rollouts on every core and on one
worker."""
UNIT = {"s": 1.0, "min": 60.0, "h": 3600.0}
LINE = re.compile(
    r"^\s*(?P<label>[^:]+): (?P<n>\d+) rollouts .*elapsed (?P<e>[0-9.]+) s.*run ~(?P<lo>[0-9.]+) (?P<lu>s|min|h) left"
    r"(?:, up to ~(?P<hi>[0-9.]+) (?P<hu>s|min|h))?"
)
TARGET = 0.25


def seconds(value: str, unit: str) -> float:
    return float(value) * UNIT[unit]


def panel_range(argv: list[str]) -> tuple[float, float]:
    """The panel's cost line's seconds for the run ``argv`` (its settings as ``pemviz run`` reads them), now: as
    planned, and with all that may follow (or, where nothing may, the load's drift)."""
    from pemviz.app.form import run_cost
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args
    from pemviz.engine.cost import with_drift

    cost = run_cost(config_from_args(build_parser("run").parse_args(argv)))
    if cost.then_simulations <= 0:  # nothing may follow: the range ends at the load's drift, as the panel says
        return cost.seconds, with_drift(cost.seconds, cost.slowdown)
    return cost.seconds, cost.seconds + cost.then_seconds


def busy_loop() -> None:
    """Spin until killed (a busy process)."""
    while True:
        pass


def one_run(argv: list[str], log=None) -> dict:
    """The panel's range, each progress line's (label, elapsed, predicted total low, high) and the wall seconds (and
    every line with its second since the start, to ``log``, an open text file, where given)."""
    panel = panel_range(argv)
    env = {**os.environ, "RERUN_ANALYTICS": "false", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-u", "-m", "pemviz.cli", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        bufsize=1,
    )
    assert proc.stdout is not None
    lines: list[tuple[str, float, float, float]] = []
    end, start, stop = None, time.perf_counter(), ""
    for line in proc.stdout:
        now = time.perf_counter()
        if log is not None:
            log.write(f"{now - start:8.2f} {line}")
        m = LINE.search(line)
        if m:
            elapsed = float(m["e"])
            if not lines:  # the run's own clock starts at its first line: the imports before it are not the run
                start = now - elapsed
            low = elapsed + seconds(m["lo"], m["lu"])
            high = elapsed + seconds(m["hi"], m["hu"]) if m["hi"] else low
            lines.append((m["label"].strip(), now - start, low, high))
        elif end is None and re.search(r"from \d+ simulations in [0-9.]+ s", line):
            end = now
        elif line.startswith("stop:"):
            stop = line
    proc.wait()
    if proc.returncode != 0 or end is None or not lines:
        raise SystemExit(f"pemviz {' '.join(argv)} exited {proc.returncode} (or printed no estimate)")
    ended = "plain MC" if "plain Monte Carlo after" in stop else "retry" if "once more" in stop else "planned"
    return {"panel": panel, "lines": lines, "wall": end - start, "ended": ended}


def error(predicted: float, wall: float) -> float:
    return abs(predicted - wall) / wall


def report(scene: str, run: dict) -> tuple[str, bool]:
    """One row of the table, and whether the run met both targets."""
    wall, lines = run["wall"], run["lines"]
    _, _, low, high = lines[0]
    holds = low / (1 + TARGET) <= wall <= high
    p_low, p_high = run["panel"]
    panel_holds = p_low / (1 + TARGET) <= wall <= p_high
    if run["ended"] == "planned":
        end = f"planned end: low {low:.1f} s, error {error(low, wall):.2f}"
        met = error(low, wall) <= TARGET
    elif run["ended"] == "retry":  # the stages once more: from their first line (the plan's first label again)
        again = next(i for i in range(1, len(lines)) if lines[i][0] == lines[0][0])
        _, at, r_low, r_high = lines[again]
        end = f"retry from {at:.0f} s: low {r_low:.1f} s, error {error(r_low, wall):.2f}"
        met = error(r_low, wall) <= TARGET
    else:  # plain Monte Carlo's batches: a final batch right after a final batch
        first = next(i for i in range(1, len(lines)) if lines[i][0] == lines[i - 1][0] == "final batch")
        _, at, f_low, f_high = lines[first]
        after = lines[first + 1][2] if first + 1 < len(lines) else f_low
        inside = f_low / (1 + TARGET) <= wall <= f_high
        end = (
            f"plain MC from {at:.0f} s: {f_low:.0f}-{f_high:.0f} s ({'holds' if inside else 'MISSED'}), after its "
            f"first batch {after:.0f} s, error {error(after, wall):.2f}"
        )
        met = error(after, wall) <= TARGET and inside
    met = met and holds
    row = (
        f"| {scene} | {run['ended']} | {wall:.1f} s | {low:.1f}-{high:.0f} s "
        f"({'holds' if holds else 'MISSED'}) | {end} | {p_low:.1f}-{p_high:.0f} s "
        f"({'holds' if panel_holds else 'MISSED'}) | {'MET' if met else 'MISSED'} |"
    )
    return row, met


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--scenes", nargs="+", default=["braking", "crossing", "cut-in"], choices=list(SCENES))
    ap.add_argument("--busy", type=int, default=0, help="busy loops running throughout (a loaded machine)")
    ap.add_argument("--log", default=None, help="write every line of the runs here, with its second")
    a = ap.parse_args()
    import multiprocessing

    loops = [multiprocessing.Process(target=busy_loop, daemon=True) for _ in range(a.busy)]
    for loop in loops:
        loop.start()
    log = open(a.log, "w", encoding="utf-8") if a.log else None  # noqa: SIM115 (closed below)
    try:
        if loops:
            time.sleep(65.0)  # the 1-minute load average sees them, as it sees a machine that has been busy a while
        print(
            f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores, nice {os.nice(0)}, "
            f"{a.busy} busy loop(s)"
        )
        print("| scene | ended | wall | first line: range | at its planned end (target 25 %) | panel: range | |")
        print("|---|---|---|---|---|---|---|")
        for scene in a.scenes:
            for _ in range(a.repeat):
                if log is not None:
                    log.write(f"== {scene}\n")
                row, _ = report(scene, one_run(SCENES[scene], log))
                print(row, flush=True)
        print(f"load average {os.getloadavg()[0]:.2f} at the end")
    finally:
        for loop in loops:
            loop.kill()
        if log is not None:
            log.close()


if __name__ == "__main__":
    main()
