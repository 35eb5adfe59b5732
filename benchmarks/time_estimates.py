"""How right the console's time estimates are: what each progress line says the run will take in all (its "elapsed
E s" plus its "run ~X s left") against what the run then took, for the default braking and cut-in runs.

Each run is a fresh ``pemviz run --no-record`` (``--repeat`` times per scene); every progress line is read as it
arrives, and the run ends at its estimate (the "from N simulations in S s" line; the explanation and the teardown
after it are not the run). Prints, per scene, the worst relative error of the predictions from the first stage on
(target: within 25 %), of the first prediction alone, and of the panel's cost line for the same settings
(:func:`pemviz.app.form.run_cost`, made just before the run starts, as the panel makes it when its form changes).
Both read the machine's load when they predict (:func:`pemviz.engine.resources.load_slowdown`); ``--busy K`` runs K
busy loops (other processes) throughout, to measure them on a loaded machine.

    python benchmarks/time_estimates.py                 # 5 runs of each scene (~2 minutes on 2 cores)
    python benchmarks/time_estimates.py --repeat 3 --busy 2
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time

SCENES = {"braking": ["run", "--no-record"], "cut-in": ["run", "--scenario", "cut-in", "--no-record"]}
LEFT = re.compile(r"elapsed ([0-9.]+) s.*run ~([0-9.]+) s left")
TARGET = 0.25


def panel_seconds(argv: list[str]) -> float:
    """The panel's cost line's seconds for the run ``argv`` (its settings as ``pemviz run`` reads them), now."""
    from pemviz.app.form import run_cost
    from pemviz.cli import build_parser
    from pemviz.commands.run import config_from_args

    return run_cost(config_from_args(build_parser("run").parse_args(argv))).seconds


def busy_loop() -> None:
    """Spin until killed (a busy process)."""
    while True:
        pass


def one_run(argv: list[str]) -> list[tuple[float, float]]:
    """(predicted seconds of the whole run, actual seconds) for the panel's cost line first, then each progress line
    with a prediction."""
    panel = panel_seconds(argv)
    env = {**os.environ, "RERUN_ANALYTICS": "false", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-u", "-m", "pemviz.cli", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
        bufsize=1,
    )
    seen: list[tuple[float, float]] = []
    end = None
    start = time.perf_counter()
    for line in proc.stdout:
        now = time.perf_counter()
        m = LEFT.search(line)
        if m:
            if not seen:  # the run's own clock starts at its first line: the imports before it are not the run
                start = now - float(m.group(1))
            seen.append((now, float(m.group(1)) + float(m.group(2))))
        elif end is None and re.search(r"from \d+ simulations in [0-9.]+ s", line):
            end = now
    proc.wait()
    if proc.returncode != 0 or end is None:
        raise SystemExit(f"pemviz {' '.join(argv)} exited {proc.returncode} (or printed no estimate)")
    return [(panel, end - start)] + [(pred, end - start) for _, pred in seen]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--busy", type=int, default=0, help="busy loops running throughout (a loaded machine)")
    a = ap.parse_args()
    import multiprocessing

    loops = [multiprocessing.Process(target=busy_loop, daemon=True) for _ in range(a.busy)]
    for loop in loops:
        loop.start()
    try:
        if loops:
            time.sleep(65.0)  # the 1-minute load average sees them, as it sees a machine that has been busy a while
        print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores, {a.busy} busy loop(s)")
        for scene, argv in SCENES.items():
            worst, first, panel = [], [], []
            for _ in range(a.repeat):
                pairs = one_run(argv)
                errors = [abs(p - real) / real for p, real in pairs if real > 0]
                panel.append(errors[0])
                worst.append(max(errors[1:]) if errors[1:] else float("nan"))
                first.append(errors[1] if errors[1:] else float("nan"))
            verdict = "MET" if max(worst + panel) <= TARGET else "MISSED"
            print(
                f"{scene:8s} {a.repeat} runs: worst relative error of any progress line {max(worst):.2f} (per run "
                f"{', '.join(f'{w:.2f}' for w in worst)}), of the first {max(first):.2f}, of the panel's cost line "
                f"{max(panel):.2f}: {verdict} (target {TARGET:.0%})"
            )
    finally:
        for loop in loops:
            loop.kill()


if __name__ == "__main__":
    main()
