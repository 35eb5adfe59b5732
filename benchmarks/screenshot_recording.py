"""Screenshot of a pemviz recording in rerun's web viewer, in headless Chromium, for the README.

    python benchmarks/screenshot_recording.py                     # runs `pemviz run` (defaults, seed 0) first
    python benchmarks/screenshot_recording.py --rrd recordings/x.rrd --out assets/screenshots/rerun_recording.png

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
    rrd: Path, out: Path, width: int, height: int, min_wait_s: float, max_wait_s: float, step: int | None = None
) -> Path:
    """Serve ``rrd`` with rerun's web viewer and save a PNG of it from headless Chromium.

    ``step``: move the time cursor there (0..99) by clicking the collapsed time panel's scrub bar, where
    rerun 0.41 puts step 0 at x = 238 px and step 99 at ``width`` - 194 px (measured; best effort: if the
    layout changes the cursor lands elsewhere, the views are the same).
    """
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("chromium not found: apt-get install -y chromium")
    web_port, grpc_port = free_port(), free_port()
    rerun_cmd = [
        "rerun", "--serve-web", str(rrd), "--bind", "127.0.0.1",
        "--web-viewer-port", str(web_port), "--port", str(grpc_port),
    ]  # fmt: skip
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
                png = page.screenshot()
                elapsed = time.monotonic() - t0
                if (elapsed >= min_wait_s and png == previous) or elapsed >= max_wait_s:
                    break
                previous = png
            if step is not None:
                left, right = 238, width - 194  # step 0 and step 99, measured at 1600 px wide
                page.mouse.click(left + (right - left) * step / 99, height - 14)
                time.sleep(5.0)
                png = page.screenshot()
            browser.close()
        tmp.write_bytes(png)
        os.replace(tmp, out)
        print(f"screenshot after {elapsed:.0f} s: {out}", flush=True)
        return out
    finally:
        tmp.unlink(missing_ok=True)
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=10)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rrd", type=Path, default=None, help="recording to show (default: run pemviz's defaults first)")
    ap.add_argument("--out", type=Path, default=REPO / "assets" / "screenshots" / "rerun_recording.png")
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=1000)
    ap.add_argument("--min-wait", type=float, default=25.0, help="seconds before the page may count as drawn")
    ap.add_argument("--max-wait", type=float, default=120.0)
    ap.add_argument("--step", type=int, default=48, help="time cursor on the step timeline (-1: leave it at the end)")
    args = ap.parse_args()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        rrd = args.rrd
        if rrd is None:
            rrd = Path(tmp) / "default.rrd"
            record_default_run(rrd)
        step = None if args.step < 0 else args.step
        screenshot(rrd, args.out, args.width, args.height, args.min_wait, args.max_wait, step)
    return 0


if __name__ == "__main__":
    sys.exit(main())
