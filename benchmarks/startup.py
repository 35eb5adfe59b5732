"""What a default ``pemviz run`` spends before its first stage, and its wall time against the estimate's own time.

    python benchmarks/startup.py                 # 5 default runs with their recording (a temporary .rrd)
    python benchmarks/startup.py --repeats 9 --args --no-record

Prints:

1. each heavy import's cumulative time (``python -X importtime``, one run) in the run's own process: torch, rerun,
   viser, scipy.stats, pyarrow, and the others named in :data:`HEAVY`; a module the run never imports is listed as
   "not imported" (a recording's rerun and pyarrow are imported by its recording process, beside the run:
   :mod:`pemviz.sinks.recording_process`);
2. per run: the seconds from the process's start to its first stage (the first progress line on stderr), the
   estimate's own time (the console's ``from N simulations in S s``: the experiment from the estimator's set-up to
   the final estimate) and the whole process's wall time; then their medians and the ratio wall / estimate.

The runs read compiled modules, as an installed pemviz does: the script compiles pemviz first and runs it without
``PYTHONDONTWRITEBYTECODE`` (:func:`run_env`).

Targets (a quiet machine): at most 0.7 s before the first stage; wall / estimate at most 1.3 (median of 5). The
load average is printed before and after: compare figures taken on a quiet machine only.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
HEAVY = (
    "torch",
    "rerun",
    "viser",
    "scipy.stats",
    "scipy.special",
    "scipy.optimize",
    "pyarrow",
    "pandas",
    "sklearn",
    "numpy",
    "highway_env",
    "gymnasium",
    "pyro",
    "arviz",
    "pemviz.engine.experiment",
    "pemviz.sinks.recording",
)
STAGE_LINE = re.compile(r"^\s+(pretraining|CE stage|stage|final batch|Monte Carlo|AMS)\b.*\.\.\.")
ESTIMATE_TIME = re.compile(r"from [\d,]+ simulations in ([\d.]+) s")


def run_env() -> dict[str, str]:
    """The runs' environment: this one, without rerun's analytics and without ``PYTHONDONTWRITEBYTECODE``, so that
    pemviz's modules load from their compiled files as in an installed pemviz (pip compiles a package's modules when
    it installs it; an editable install's are compiled at their first import). With the variable set, as in some
    containers, every run compiles pemviz's modules from source again: about 0.1 s in the run and as much in its
    recording process, which no user pays."""
    env = {**os.environ, "RERUN_ANALYTICS": "false"}
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def compile_modules() -> None:
    """Write pemviz's compiled files (``python -m compileall -q pemviz``), as pip does at install."""
    subprocess.run(
        [sys.executable, "-m", "compileall", "-q", str(REPO / "pemviz")],
        cwd=REPO,
        env=run_env(),
        check=True,
        timeout=600,
    )


def command(extra: list[str], folder: Path, i: int) -> list[str]:
    record = [] if "--no-record" in extra or "--save" in extra else ["--save", str(folder / f"run{i}.rrd")]
    return [sys.executable, "-c", "import sys; from pemviz.cli import main; sys.exit(main())", "run", *record, *extra]


def import_times(extra: list[str], folder: Path) -> dict[str, float | None]:
    """Cumulative import seconds of each module of :data:`HEAVY` in one run (None: not imported)."""
    proc = subprocess.run(
        [sys.executable, "-X", "importtime", *command(extra, folder, 99)[1:]],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        env=run_env(),
    )
    found: dict[str, float | None] = dict.fromkeys(HEAVY)
    for line in proc.stderr.splitlines():
        m = re.match(r"import time:\s+\d+ \|\s+(\d+) \|(\s*)(\S+)$", line)
        if m and m.group(3) in found and found[m.group(3)] is None:
            found[m.group(3)] = int(m.group(1)) / 1e6
    return found


def timed(extra: list[str], folder: Path, i: int) -> tuple[float, float, float]:
    """(seconds to the first stage, the estimate's own seconds, wall seconds) of one run."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        command(extra, folder, i), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=run_env()
    )
    first: list[float] = []

    def watch() -> None:
        for line in proc.stderr:
            if not first and STAGE_LINE.match(line):
                first.append(time.perf_counter() - t0)

    reader = threading.Thread(target=watch)
    reader.start()
    out = proc.stdout.read()
    proc.wait(timeout=600)
    reader.join()
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"the run failed (exit {proc.returncode})")
    m = ESTIMATE_TIME.search(out)
    if m is None or not first:
        raise SystemExit("no estimate time or no progress line in the run's output")
    return first[0], precise_estimate_s(folder, i, float(m.group(1))), wall


def precise_estimate_s(folder: Path, i: int, printed: float) -> float:
    """The estimate's own seconds from the recording's result document (``wall_s``, unrounded), else the
    console's (printed to 0.1 s: a ratio read from it is off by up to 0.05 / estimate)."""
    doc = folder / f"run{i}.result.json"
    try:
        return float(json.loads(doc.read_text())["wall_s"])
    except (OSError, KeyError, TypeError, ValueError):
        return printed


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--args", nargs=argparse.REMAINDER, default=[], help="more flags for pemviz run")
    a = p.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.2f}")
    compile_modules()  # the runs read compiled modules, as an installed pemviz does (run_env)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        print("\n| module | cumulative import s |\n|---|---|")
        for name, s in import_times(a.args, folder).items():
            print(f"| {name} | {'not imported' if s is None else f'{s:.3f}'} |")
        print("\n| run | to first stage s | estimate s | wall s | wall / estimate |\n|---|---|---|---|---|")
        rows = []
        for i in range(a.repeats):
            first, est, wall = timed(a.args, folder, i)
            rows.append((first, est, wall))
            print(f"| {i} | {first:.2f} | {est:.2f} | {wall:.2f} | {wall / est:.2f} |")
    first, est, wall = (statistics.median(col) for col in zip(*rows, strict=False))
    print(
        f"\nmedian: {first:.2f} s to the first stage (target <= 0.7), estimate {est:.2f} s, wall {wall:.2f} s, "
        f"wall / estimate {wall / est:.2f} (target <= 1.3)"
    )
    print(f"load average after: {os.getloadavg()[0]:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
