"""``pemviz serve`` end to end in headless Chromium (issue 9 acceptance).

One panel server (in-process, 127.0.0.1, a free port) and one browser for the module. The browser sets
the controls the way a user does (labels, dropdown options, buttons); the server-side state and the
browser's own scene graph (``window.__viserMutable`` / ``__viserSceneTree``, viser's E2E hooks) are the
truth the tests compare against. Chromium is Debian's (``apt-get install chromium``; ``.ci/run`` installs it).
"""

from __future__ import annotations

import os
import tempfile
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO

sync_api = pytest.importorskip("playwright.sync_api", reason="the Python playwright package is not installed")
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
if not os.path.exists(CHROMIUM):
    pytest.skip("Debian's chromium is not installed (apt-get install chromium)", allow_module_level=True)

from pemviz.app.panel import DETECTED_RGB, MISSED_RGB, PanelApp  # noqa: E402
from pemviz.app.runs import scene_positions  # noqa: E402

CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
    "--disable-component-update", "--disable-sync",
]  # fmt: skip
SCREENSHOT = (
    REPO / "assets" / "screenshots" / "viser_panel.png"  # the README's picture: refresh it on purpose only
    if os.environ.get("PEMVIZ_UPDATE_SCREENSHOTS")
    else Path(tempfile.gettempdir()) / f"pemviz-viser_panel-{os.getpid()}.png"
)
VIEWPORT = {"width": 1600, "height": 1000}


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    recordings = tmp_path_factory.mktemp("serve") / "recordings"
    panel = PanelApp("127.0.0.1", 0, recordings_dir=recordings)
    yield panel
    panel.close()


@pytest.fixture(scope="module")
def browser():
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


def open_panel(browser, app: PanelApp):
    page = browser.new_page(viewport=VIEWPORT)
    page.goto(app.url)
    page.get_by_label("alpha", exact=True).wait_for(timeout=60_000)
    dismiss_software_gl_notice(page)
    return page


def dismiss_software_gl_notice(page) -> None:
    """Headless Chromium renders WebGL on the CPU and viser says so in a notification: close it."""
    notice = page.locator(".mantine-Notification-root", has_text="Software WebGL")
    try:
        notice.wait_for(timeout=3_000)
    except sync_api.TimeoutError:
        return
    notice.locator(".mantine-Notification-closeButton").click()
    notice.wait_for(state="detached", timeout=5_000)


@pytest.fixture(scope="module")
def page(browser, app):
    p = open_panel(browser, app)
    yield p
    p.close()


def choose(page, label: str, option: str) -> None:
    page.get_by_label(label, exact=True).click()
    page.get_by_role("option", name=option, exact=True).click()


def type_number(page, label: str, value: str) -> None:
    box = page.get_by_label(label, exact=True)
    box.fill(value)
    box.press("Tab")


def wait_until(predicate, timeout: float = 10.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def scene_in_browser(page) -> dict:
    """What this tab's three.js scene holds for the ego: position, colour and label text."""
    return page.evaluate(
        """() => {
            const ego = window.__viserMutable.nodeRefFromName['/ego'];
            const tree = window.__viserSceneTree.getState();
            return {x: ego.position.x, y: ego.position.y,
                    color: tree['/ego'].message.props.color,
                    label: tree['/ego/label'].message.props.text};
        }"""
    )


def test_agm_run_in_the_browser_reaches_a_final_estimate_and_plays_the_least_robust_rollout(app, browser, page):
    choose(page, "preset", "quick")
    choose(page, "metric", "agm")
    type_number(page, "alpha", "0.2")
    type_number(page, "sigma", "0.9")
    wait_until(lambda: app.read_config().quantile_level == 0.9, what="sigma to reach the server")
    page.get_by_role("button", name="Run", exact=True).click()
    page.get_by_text("Final estimate", exact=True).wait_for(timeout=90_000)

    record = app.current
    cfg = record.config
    assert (cfg.metric, cfg.smoothing, cfg.quantile_level) == ("agm", 0.2, 0.9)
    assert record.status == "finished" and record.final is not None
    page_text = page.inner_text("body")
    assert f"failures {record.final.estimate.n_failures}/{cfg.n_final}" in page_text
    assert len(record.stages) == cfg.n_stages + 2  # pretraining, K CE stages, final batch
    # the live proposal plot holds the PEM and one curve per stage (pretrained + K), as the browser draws it
    plots = page.evaluate(
        """() => Object.values(window.__viserTestpoints?.uplots ?? {}).map(u => ({
               title: u.chart.root.querySelector('.u-title')?.textContent ?? '',
               labels: u.chart.series.map(s => s.label), n: u.chart.data[0].length}))"""
    )
    live = [p for p in plots if p["title"].startswith(f"run {record.run_id}: ") and "per stage vs PEM" in p["title"]]
    stages = [f"stage {k}" for k in range(1, cfg.n_stages + 1)]
    assert live and live[0]["labels"] == ["gap (m)", "PEM", "pretrained", *stages]
    assert live[0]["n"] == record.curve_grid_m.size

    # the list is sorted least robust first, by the run's metric, across all stages
    rho = [t.robustness for t in record.trajectories]
    assert rho == sorted(rho)
    least = record.trajectories[0]
    batch_min = min(
        float(np.min(e.robustness)) for e in record.events if type(e).__name__ == "RolloutsSampled"
    )
    assert least.robustness == batch_min

    page.get_by_role("tab", name="Rollouts").click()
    page.get_by_label("rollout", exact=True).click()
    first = page.get_by_role("option").nth(1)
    assert first.inner_text().startswith(f"stage {least.stage} rollout {least.index} · rho ")
    first.click()
    wait_until(lambda: app.shown is least and app.shown_step > 3, what="playback to start")
    page.get_by_role("button", name="Pause").click()
    wait_until(lambda: not app.playing, what="pause")
    time.sleep(0.3)

    # the scene shows that rollout at the shown step, in the browser's own scene graph
    step = app.shown_step
    ego_x, _ = scene_positions(least, app.params)
    def shown_in_browser() -> bool:
        s = scene_in_browser(page)
        return s["label"].startswith(least.key) and abs(s["x"] - ego_x[step]) < 1e-3

    wait_until(shown_in_browser, what="the browser's scene to show the rollout")
    s = scene_in_browser(page)
    assert tuple(s["color"]) == (DETECTED_RGB if least.detected[step] else MISSED_RGB)
    assert f"Scene: {least.key}" in page.inner_text("body")

    # a second tab sees the same run and the same scene
    other = open_panel(browser, app)
    try:
        other.get_by_text("Final estimate", exact=True).wait_for(timeout=30_000)
        wait_until(lambda: scene_in_browser(other)["label"].startswith(least.key), what="the second tab's scene")
        assert abs(scene_in_browser(other)["x"] - ego_x[step]) < 1e-3
    finally:
        other.close()

    # screenshot for the README: a step where the detector missed inside 10 m, if the rollout has one
    missed = np.flatnonzero(~least.detected & (least.gap_m < 10.0))
    app.step_slider.value = int(missed[len(missed) // 2]) if missed.size else 40
    time.sleep(1.0)
    SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
    tmp = SCREENSHOT.with_name(".viser_panel.tmp.png")
    page.screenshot(path=str(tmp))
    os.replace(tmp, SCREENSHOT)
    assert SCREENSHOT.stat().st_size > 20_000


def test_invalid_values_are_rejected_in_the_panel_with_a_visible_message(app, page):
    page.get_by_role("tab", name="Experiment").click()
    runs_before = len(app.runs), app.current
    for label, bad, good, message in (
        ("alpha", "0", "0.2", "alpha must be in (0, 1]"),
        ("sigma", "1", "0.9", "sigma must be in [0.5, 1)"),
        ("N", "1", "100", "N must be an integer >= 2"),
    ):
        type_number(page, label, bad)
        sync_api.expect(page.get_by_text(message).first).to_be_visible(timeout=5_000)
        page.get_by_role("button", name="Run", exact=True).click()
        sync_api.expect(page.get_by_text("Run refused").first).to_be_visible(timeout=5_000)
        assert (len(app.runs), app.current) == runs_before and not app.running
        type_number(page, label, good)
        sync_api.expect(page.get_by_text(message)).to_have_count(0, timeout=5_000)


def test_changing_controls_mid_run_is_harmless_and_stop_ends_the_run_within_2_s(app, page):
    page.get_by_role("tab", name="Experiment").click()
    type_number(page, "K", "40")
    wait_until(lambda: app.read_config().n_stages == 40, what="K to reach the server")
    page.get_by_role("button", name="Run", exact=True).click()
    wait_until(lambda: app.running and len(app.current.stages) >= 2, timeout=60, what="two finished stages")
    record = app.current

    choose(page, "metric", "smooth-cumulative")
    type_number(page, "alpha", "0.5")
    type_number(page, "seed", "7")
    wait_until(lambda: app.read_config().seed == 7, what="the changes to reach the server")
    assert app.running and record.config.metric == "agm" and record.config.smoothing == 0.2  # the run keeps its config
    n_done = len(record.stages)
    wait_until(lambda: len(record.stages) > n_done, timeout=30, what="one more stage after the changes")

    page.get_by_role("button", name="Stop", exact=True).click()
    wait_until(lambda: not app.running, timeout=10, what="the worker to end")
    assert record.status == "cancelled"
    assert app.last_stop_latency_s is not None and app.last_stop_latency_s < 2.0, app.last_stop_latency_s
    assert len(record.stages) < record.n_stage_events
    sync_api.expect(page.get_by_text(re.compile(r"stopped after \d+ stages")).first).to_be_visible(timeout=5_000)
    sync_api.expect(page.get_by_role("button", name="Run", exact=True)).to_be_enabled()
    type_number(page, "K", "8")


def test_export_name_from_the_browser_cannot_escape_recordings(app, page):
    recordings = Path(app.recordings_dir).resolve()
    page.get_by_role("tab", name="Runs").click()
    # viser's text input has no id for its label: find the input beside the label
    box = page.locator("xpath=//label[normalize-space()='export name']/ancestor::div[.//input][1]//input")
    box.fill("../x")
    box.press("Tab")
    wait_until(lambda: app.export_name.value == "../x", what="the name to reach the server")
    page.get_by_role("button", name="Export current run").click()
    sync_api.expect(page.get_by_text("Saved").first).to_be_visible(timeout=30_000)
    written = recordings / "x.rrd"
    assert written.is_file() and written.stat().st_size > 1000
    assert app.last_export == written
    assert not (recordings.parent / "x.rrd").exists() and not (recordings.parent / "x").exists()
    assert sorted(p.name for p in recordings.iterdir()) == ["x.rrd"]  # no temp or .partial files left
    # the browser got a link to the file (viser's download notification)
    sync_api.expect(page.locator("a[download]").first).to_be_attached(timeout=10_000)
