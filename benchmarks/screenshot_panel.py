"""Screenshot of the ``pemviz serve`` panel explaining a failure, in headless Chromium, for the README.

    python benchmarks/screenshot_panel.py                        # writes assets/screenshots/viser_panel.png
    python benchmarks/screenshot_panel.py --preset quick --k 6 --out /tmp/panel.png
    python benchmarks/screenshot_panel.py --scenario cut-in --k 3 --set N=60 --set N_e=60 --set seed=1 \
        --width 1400 --height 900 --out /tmp/panel_cut_in.png

The commands that make the docs' panel screenshots are in the table of ``benchmarks/screenshots.py``;
``python benchmarks/docs_assets.py --screenshots`` runs them all and rewrites ``assets/screenshots/MANIFEST.md``.

What it does: starts the panel (:class:`pemviz.app.panel.PanelApp`, 127.0.0.1, a free port), opens it in
Chromium (Debian's ``chromium`` driven by Playwright, with ``--headless --no-sandbox --disable-gpu
--no-first-run --disable-background-networking --disable-component-update --disable-sync``), runs an
experiment from the browser's form (typing K, pressing Run), waits for the final estimate (the panel then
chooses the most likely failure found), opens the *Explain* tab, moves playback to the first decisive miss
(or the crash) and writes the PNG (to a temp file, then ``os.replace``); with ``--live-out`` also the *Live* tab
(what the sampler did over the visited states, the estimate per stage), and with ``--scene-out`` the 3D scene at the
step the 2 m line is crossed, beside the *Rollouts* tab. With ``--scenario cut-in`` (several cars), *Explain* shows
every car from above at the first decisive error, with which cars' errors decided the failure. Every wait is on a
condition.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
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


def wait_until(predicate, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > end:
            raise SystemExit(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.05)


def show_step(page, session, step: int) -> None:
    """Move the playback to ``step`` and wait until the browser's scene shows it (its ego label) and its fonts."""
    session.step_slider.value = step
    label = f"{session.record.short_label} {session.shown.name} t={step * 0.05:.2f}s"
    wait_until(
        lambda: page.evaluate(
            "() => window.__viserSceneTree.getState()['/ego/label']?.message?.props?.text ?? ''"
        ).startswith(label),
        30,
        f"the scene at step {step}",
    )
    page.wait_for_function("() => document.fonts.ready.then(() => true)")


def write(page, path: Path) -> None:
    """Screenshot the page to ``path`` (through a temp file, then ``os.replace``)."""
    partial = path.with_name(path.name + ".partial.png")
    page.screenshot(path=str(partial))
    os.replace(partial, path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "assets" / "screenshots" / "viser_panel.png")
    ap.add_argument("--preset", default="quick", help="the panel's preset (default quick)")
    ap.add_argument("--k", default="8", help="K typed into the form (default 8)")
    ap.add_argument("--metric", default=None, help="the metric chosen in the form (default: the preset's)")
    ap.add_argument("--scenario", default=None, help="the scenario chosen in the form (default: braking)")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="LABEL=VALUE",
        help="type VALUE into the form's field LABEL (e.g. alpha=0.2); repeatable",
    )
    ap.add_argument("--live-out", type=Path, default=None, help="also write the Live tab here")
    ap.add_argument(
        "--scene-out", type=Path, default=None, help="also write the scene at the breach, beside the Rollouts tab, here"
    )
    ap.add_argument("--width", type=int, default=1600)
    ap.add_argument("--height", type=int, default=1000)
    args = ap.parse_args()

    from playwright.sync_api import sync_playwright

    sys.path.insert(0, str(REPO))
    from pemviz.app.panel import PanelApp

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        raise SystemExit("chromium not found: apt-get install -y chromium")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(args.out.name + ".partial.png")
    app = PanelApp("127.0.0.1", 0, recordings_dir=Path(tempfile.gettempdir()) / "pemviz-screenshot", preset=args.preset)
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_FLAGS)
            page = browser.new_page(viewport={"width": args.width, "height": args.height})
            known = set(app.sessions)
            page.goto(app.url)
            session = app.wait_for_session(known)
            page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")
            labels = {h.label: h for h in session.fields.values()}
            for label, value in [("K", args.k)] + [tuple(kv.split("=", 1)) for kv in args.set]:
                box = page.locator(
                    f"xpath=//label[normalize-space()='{label}']/ancestor::div[.//input][1]//input"
                ).first
                box.fill(value)
                box.press("Tab")
                wait_until(
                    lambda: labels[label].value == value,  # noqa: B023 (called within the iteration)
                    30,
                    f"{label} to reach the server",
                )
            for key, value in (("metric", args.metric), ("scenario", args.scenario)):
                if value:
                    page.get_by_label(key, exact=True).click()
                    page.get_by_role("option", name=value, exact=True).click()
                    wait_until(
                        lambda: session.choices[key].value == value,  # noqa: B023 (called within the iteration)
                        30,
                        f"the {key} to reach the server",
                    )
            page.get_by_role("button", name="Run", exact=True).click()
            wait_until(lambda: session.record is not None and session.record.done, 600, "the run to finish")
            if args.scenario not in (None, "braking"):
                wait_until(lambda: session.objects_ex is not None, 60, "the failure explanation")
                page.get_by_role("tab", name="Explain").click()
                page.get_by_text("Which errors decided it", exact=False).wait_for(timeout=30_000)
                step = session.shown_step
                page.get_by_text(f"From above at step {step}", exact=False).wait_for(timeout=30_000)
                page.wait_for_function("() => document.fonts.ready.then(() => true)")
                write(page, args.out)
                browser.close()
                print(f"{args.out}: {session.record.label}, {session.shown.name} at step {step}", flush=True)
                return 0
            wait_until(lambda: session.explanation is not None, 30, "the failure explanation")
            page.get_by_role("tab", name="Explain").click()
            page.get_by_text("Counterfactual", exact=False).wait_for(timeout=30_000)
            ex, shown = session.explanation, session.shown
            step = int(ex.decisive[0]) if ex.decisive.size else int((shown.signal("gap_m") < 2.0).argmax())
            show_step(page, session, step)
            page.screenshot(path=str(tmp))
            if args.live_out is not None:
                page.get_by_role("tab", name="Live").click()
                page.get_by_text("over the visited states", exact=False).first.wait_for(timeout=30_000)
                write(page, args.live_out)
            if args.scene_out is not None and ex.severity.breach_step is not None:
                page.get_by_role("tab", name="Explain").click()
                page.get_by_role("tab", name="Rollouts").click()
                page.get_by_text("Scene:", exact=False).first.wait_for(timeout=30_000)
                show_step(page, session, ex.severity.breach_step)
                write(page, args.scene_out)
            browser.close()
        os.replace(tmp, args.out)
        print(f"{args.out}: {session.record.label}, {shown.name} at step {step}", flush=True)
    finally:
        tmp.unlink(missing_ok=True)
        app.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
