"""Screenshots of a pemviz recording in rerun's web viewer, in headless Chromium, for the README and the user guide.

    python benchmarks/screenshot_recording.py                     # runs `pemviz run` (defaults, seed 0) first
    python benchmarks/screenshot_recording.py --rrd recordings/x.rrd --tab all
    python benchmarks/screenshot_recording.py --rrd x.rrd --tab explain --out /tmp/explain.png

The commands that make the docs' recording screenshots are in the table of ``benchmarks/screenshots.py``;
``python benchmarks/docs_assets.py --screenshots`` runs them all and rewrites ``assets/screenshots/MANIFEST.md``.

``--tab`` picks the blueprint tab shown (:data:`pemviz.sinks.rerun_blueprint.TABS`): ``stages`` (the recording's own
layout, timeline ``stage``) -> ``assets/screenshots/rerun_recording.png``, ``rollouts`` (timeline ``step``) ->
``rerun_recording_step.png``, ``explain`` (timeline ``step``) -> ``rerun_recording_explain.png``; ``all`` makes the
three. For a tab other than the recording's default the same layout with that tab open and its timeline selected
(:func:`pemviz.sinks.rerun_blueprint.default_blueprint` with ``tab``, the braking scenario's views and ``--lanes``
scene lanes) is saved as a blueprint file (``.rbl``) and shown with a copy of the recording that has no blueprint of
its own.

What it does: ``rerun --serve-web RRD`` hosts the web viewer bundled with rerun-sdk on localhost (no
internet needed) and serves the recording over gRPC; Chromium (Debian's ``chromium``, driven by
Playwright) opens ``http://127.0.0.1:PORT/?url=rerun+http://127.0.0.1:GRPC/proxy``, waits until the wasm
viewer has drawn the recording (two equal screenshots in a row, at least ``--min-wait`` seconds after
loading), moves the time cursor to ``--step`` (default 48: safe rollouts brake, the crashing ones still miss), and
writes the PNG (to a temp file, then ``os.replace``). Chromium is started with
``--headless --no-sandbox --disable-gpu --no-first-run --disable-background-networking
--disable-component-update --disable-sync --user-data-dir=<temp>``; WebGL falls back to its software
rasterizer.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_http(url: str, timeout_s: float) -> None:
    t0 = time.monotonic()
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2):
                return
        except OSError:
            if time.monotonic() - t0 > timeout_s:
                raise RuntimeError(f"no answer from {url} after {timeout_s:.0f} s") from None
            time.sleep(0.3)


def record_default_run(out: Path) -> None:
    """``pemviz run --save OUT`` with the shipped defaults (seed 0)."""
    cmd = [sys.executable, "-m", "pemviz.cli", "run", "--save", str(out)]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True, cwd=REPO)


def screenshot(
    rrd: Path,
    out: Path,
    width: int,
    height: int,
    min_wait_s: float,
    max_wait_s: float,
    step: int | None = None,
    blueprint: Path | None = None,
) -> Path:
    """Serve ``rrd`` with rerun's web viewer and save a PNG of it from headless Chromium.

    ``step``: move the time cursor there (0..99) by clicking the collapsed time panel's scrub bar, where
    rerun 0.41 puts step 0 at x = 334 px and step 99 at ``width`` - 106 px (measured at 1600 px with the timeline
    ``step`` selected and paused; best effort: if the layout changes the cursor lands elsewhere, the views are the
    same). ``blueprint``: a ``.rbl`` file loaded after the recording (its layout becomes the active one).
    """
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("chromium not found: apt-get install -y chromium")
    web_port, grpc_port = free_port(), free_port()
    rerun_cmd = [
        "rerun",
        "--serve-web",
        str(rrd),
        *([str(blueprint)] if blueprint is not None else []),
        "--bind",
        "127.0.0.1",
        "--web-viewer-port",
        str(web_port),
        "--port",
        str(grpc_port),
    ]
    env = dict(os.environ, RERUN_ANALYTICS="false")
    # its own process group: `rerun` may be a launcher script whose child is the real server
    server = subprocess.Popen(
        rerun_cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, start_new_session=True
    )
    tmp = out.with_name(out.name + ".partial.png")
    try:
        wait_http(f"http://127.0.0.1:{web_port}/", 60)
        grpc = urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc_port}/proxy", safe="")
        url = f"http://127.0.0.1:{web_port}/?url={grpc}"
        print("viewer:", url, flush=True)
        with tempfile.TemporaryDirectory() as profile, sync_playwright() as pw:
            browser = pw.chromium.launch_persistent_context(
                profile,
                executable_path=chromium,
                headless=True,
                args=CHROMIUM_FLAGS,
                viewport={"width": width, "height": height},
            )
            page = browser.new_page()
            page.goto(url)
            t0 = time.monotonic()
            previous = b""
            while True:
                time.sleep(3.0)
                png = page.screenshot(timeout=180_000)
                elapsed = time.monotonic() - t0
                if (elapsed >= min_wait_s and png == previous) or elapsed >= max_wait_s:
                    break
                previous = png
            if step is not None:
                left, right = 334, width - 106  # step 0 and step 99, measured at 1600 px wide
                page.mouse.click(left + (right - left) * step / 99, height - 14)
                time.sleep(5.0)
                png = page.screenshot(timeout=180_000)
            browser.close()
        tmp.write_bytes(png)
        os.replace(tmp, out)
        print(f"screenshot after {elapsed:.0f} s: {out}", flush=True)
        return out
    finally:
        tmp.unlink(missing_ok=True)
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=10)


SHOTS = REPO / "assets" / "screenshots"
OUT = {
    "stages": SHOTS / "rerun_recording.png",
    "rollouts": SHOTS / "rerun_recording_step.png",
    "explain": SHOTS / "rerun_recording_explain.png",
}
"""Where each tab's screenshot goes by default."""


def tab_recording(
    rrd: Path, tab: str, n_lanes: int, folder: Path, scenario: str = "braking"
) -> tuple[Path, Path | None]:
    """(recording, blueprint) to show ``tab``: the recording itself for its own default (``stages``); else a copy
    without its blueprint (``folder/data.rrd``, so that no blueprint competes with ours, whatever the order the
    viewer receives them in) and the recording's layout with ``tab`` open, its timeline selected and paused (so that
    ``--step`` can place the cursor), saved as ``folder/TAB.rbl``."""
    if tab == "stages":
        return rrd, None
    from pemviz.sinks.recording import APP_ID
    from pemviz.sinks.rerun_blueprint import default_blueprint
    from rerun.chunk import RrdReader

    data = folder / "data.rrd"
    if not data.exists():
        reader = RrdReader(rrd)
        (store,) = reader.recordings()
        reader.stream(store=store).write_rrd(data, application_id=store.application_id, recording_id=store.recording_id)
    path = folder / f"{tab}.rbl"
    from pemviz.config import ExperimentConfig
    from pemviz.scenarios.problems import problem_for

    view = problem_for(ExperimentConfig.of(scenario=scenario)).view  # that scenario's views (e.g. the cut-in's objects)
    default_blueprint(n_lanes, view, tab=tab, paused=True).save(APP_ID, str(path))
    return data, path


def main() -> int:
    from pemviz.sinks.rerun_blueprint import TABS, TIMELINE

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rrd", type=Path, default=None, help="recording to show (default: run pemviz's defaults first)")
    ap.add_argument("--tab", choices=(*TABS, "all"), default="stages", help="the tab to show (all: one PNG each)")
    ap.add_argument("--out", type=Path, default=None, help="PNG to write (one --tab only; default: assets/screenshots)")
    ap.add_argument("--scenario", default="braking", help="the recording's scenario (its views; default braking)")
    ap.add_argument("--lanes", type=int, default=12, help="scene lanes of the recording (its stages; default run: 12)")
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=1000)
    ap.add_argument("--min-wait", type=float, default=25.0, help="seconds before the page may count as drawn")
    ap.add_argument("--max-wait", type=float, default=120.0)
    ap.add_argument(
        "--step",
        type=int,
        default=48,
        help="time cursor on the step timeline, for the step tabs (-1: leave it at the end)",
    )
    args = ap.parse_args()
    tabs = TABS if args.tab == "all" else (args.tab,)
    if args.out is not None and len(tabs) > 1:
        ap.error("--out takes one --tab")
    with tempfile.TemporaryDirectory() as tmp:
        rrd = args.rrd
        if rrd is None:
            rrd = Path(tmp) / "default.rrd"
            record_default_run(rrd)
        for tab in tabs:
            out = args.out or OUT[tab]
            out.parent.mkdir(parents=True, exist_ok=True)
            step = None if args.step < 0 or TIMELINE[tab] != "step" else args.step
            shown, blueprint = tab_recording(rrd, tab, args.lanes, Path(tmp), args.scenario)
            screenshot(shown, out, args.width, args.height, args.min_wait, args.max_wait, step, blueprint)
    return 0


if __name__ == "__main__":
    sys.exit(main())
