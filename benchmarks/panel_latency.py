"""How long the browser panel takes to show a run's first stage after the click on Run, in headless Chromium.

    python benchmarks/panel_latency.py                  # the quick preset, 5 runs
    python benchmarks/panel_latency.py --preset state-ce --runs 3

Starts the panel (:class:`pemviz.app.panel.PanelApp`, 127.0.0.1, a free port) with the preset, opens it in Debian's
Chromium driven by Playwright (the flags of ``benchmarks/screenshot_panel.py``), waits until the panel has warmed up,
then for each run clicks Run and measures, in the browser's own clock from the click event, the time until the page's
status line names a stage after the pretraining (stage 0 has finished and its row is on the page), and until the run has
finished; and on the server, from the run's start to the end of its first stage. Prints
one line per run and the median: a benchmark for people, not a test (the target: the first stage in under 1 s).
Every wait is on a condition (Playwright's ``wait_for_function``), none on a sleep.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def _watch_first_stage(app, run_id: int, out: list[float]) -> threading.Thread:
    """A thread that appends the seconds from run ``run_id``'s start on the server (the click received) until its first
    stage has finished there (polled every 2 ms)."""

    def watch() -> None:
        end = time.perf_counter() + 120
        while time.perf_counter() < end:
            for session in list(app.sessions.values()):
                record = session.record
                if record is not None and record.run_id == run_id and record.stages:
                    out.append(time.perf_counter() - record.clock.t0)
                    return
            time.sleep(0.002)
        out.append(float("nan"))

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="quick", help="the panel's preset (default quick)")
    ap.add_argument("--runs", type=int, default=5, help="runs to time (default 5)")
    args = ap.parse_args()
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("chromium not found: apt-get install -y chromium")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        raise SystemExit("playwright is not installed: pip install -e '.[test]'") from None
    sys.path.insert(0, str(REPO))
    from pemviz.app.panel import PanelApp

    app = PanelApp("127.0.0.1", 0, recordings_dir=Path(tempfile.gettempdir()) / "pemviz-latency", preset=args.preset)
    first, whole, server = [], [], []
    try:
        app.wait_warm()
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_FLAGS)
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.goto(app.url)
            run = page.get_by_role("button", name="Run", exact=True)
            run.wait_for(timeout=60_000)
            page.evaluate(
                "() => document.addEventListener('click', () => { window.__clicked = performance.now(); }," " true)"
            )
            for i in range(1, args.runs + 1):
                page.wait_for_function("() => !document.body.innerText.includes('is going')", timeout=120_000)
                done: list[float] = []
                watcher = _watch_first_stage(app, i, done)
                run.click()  # the page's own click listener notes when the click happened
                # the status line names a stage after the pretraining (or the run has already ended)
                page.wait_for_function(
                    f"() => /run {i}\\b[^\\n]*(CE stage|final batch)|Final estimate of run {i}\\b/"
                    ".test(document.body.innerText)",
                    timeout=60_000,
                )
                t_first = page.evaluate("() => performance.now() - window.__clicked") / 1000
                watcher.join()
                server.append(done[0])
                page.wait_for_function(
                    f"() => document.body.innerText.includes('Final estimate of run {i}')", timeout=300_000
                )
                t_whole = page.evaluate("() => performance.now() - window.__clicked") / 1000
                first.append(t_first)
                whole.append(t_whole)
                print(
                    f"run {i}: first stage shown {t_first:.2f} s after the click (finished {server[-1]:.2f} s after "
                    f"the server had the click), final estimate {t_whole:.2f} s",
                    flush=True,
                )
            browser.close()
    finally:
        app.close()
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(
        f"median over {len(first)} runs of {args.preset}: first stage {statistics.median(first):.2f} s, final "
        f"estimate {statistics.median(whole):.2f} s (load average {load})"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
