"""``pemviz serve`` end to end in headless Chromium: one test per defect a safety engineer hit in the panel.

One panel server (in-process, 127.0.0.1, a free port) and one browser for the module; each test opens its
own tab, which gets its own session (form, runs, Stop, scene). The browser types and clicks the way a user
does; the session's state, the browser's scene graph (``window.__viserMutable`` / ``__viserSceneTree``)
and its uPlot charts (``window.__viserTestpoints``) are what the tests compare. Every wait is on a
condition. Chromium is Debian's (``apt-get install chromium``; ``.ci/run`` installs it). The form, the runs, Stop
and the hints are tested here; what the panel shows of a run (scene, *Live*, *Explain*) in ``test_app_explain.py``.
"""

from __future__ import annotations

import os
import re
import shutil
import time
from pathlib import Path

import pytest

sync_api = pytest.importorskip("playwright.sync_api", reason="the Python playwright package is not installed")
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
if not os.path.exists(CHROMIUM):
    pytest.skip("Debian's chromium is not installed (apt-get install chromium)", allow_module_level=True)

from pemviz.app.form import FIELDS_BY_KEY, parse_number  # noqa: E402
from pemviz.app.panel import PanelApp  # noqa: E402
from pemviz.app.session import Session  # noqa: E402
from pemviz.settings import SETTINGS  # noqa: E402

CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
VIEWPORT = {"width": 1600, "height": 1000}
TINY = {"K": "2", "N": "40", "N_e": "60", "CE epochs": "40", "pretrain rollouts": "30", "pretrain epochs": "40"}
"""A run of about a second: the quick preset with fewer stages, rollouts and epochs."""
expect = sync_api.expect


@pytest.fixture(scope="module")
def app(tmp_path_factory):
    recordings = tmp_path_factory.mktemp("serve") / "recordings"
    panel = PanelApp("127.0.0.1", 0, recordings_dir=recordings, preset="quick")
    yield panel
    panel.close()


@pytest.fixture(scope="module")
def browser():
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


SCREENSHOTS = (
    os.environ.get("PEMVIZ_SCREENSHOTS") == "1"
    or bool(os.environ.get("PEMVIZ_IDLE_SHOTS"))
    or "PEMVIZ_PARAMS_SHOT" in os.environ
)
"""The tests write screenshots of the panel (the variables test_app_*.py read): every tab draws its 3D scene."""
PARK_SCENE = """(() => {
    const park = () => {
        const gl = window.__viserMutable?.canvas;
        if (!gl?.isConnected) return false;
        let box = gl;  // the canvas' wrappers (three at most) that hold no control of the panel
        const bare = (e) => e && !e.querySelector('input, button, [role=tab]');
        for (let i = 0; i < 3 && bare(box.parentElement); i++) box = box.parentElement;
        box.style.transform = 'translateX(-100000px)';
        return true;
    };
    const timer = setInterval(() => { if (park()) clearInterval(timer); }, 100);
})();"""
"""Moves the 3D scene's canvas (viser's ``__viserMutable.canvas``) and its wrappers out of the window (a transform: no
layout changes): viser stops drawing a canvas out of view (its three.js scene graph, camera and labels go on
updating, and the tests read those), and the software WebGL of headless Chromium otherwise draws the scene about once
a second, a quarter of a core per open tab."""


class Tab:
    """A browser tab and its server-side session; ``draw_scene``: the 3D canvas is drawn and in the window (a test
    that reads its pixels' place on the page, or writes screenshots), else moved out of view (:data:`PARK_SCENE`)."""

    def __init__(self, browser, app: PanelApp, viewport: dict | None = None, draw_scene: bool = False) -> None:
        known = set(app.sessions)
        self.page = browser.new_page(viewport=viewport or VIEWPORT)
        if not (draw_scene or SCREENSHOTS):
            self.page.add_init_script(PARK_SCENE)
        self.page.set_default_timeout(90_000)  # a click waits for a renderer a loaded machine starves
        self.page.goto(app.url)
        self.session: Session = app.wait_for_session(known)
        hide_notifications(self.page)
        self.field("alpha").wait_for(timeout=60_000)

    def close(self) -> None:
        self.page.close()

    def draw_scene(self) -> None:
        """Bring the 3D canvas that :data:`PARK_SCENE` moved out of view back into the window; viser draws it again."""
        self.page.evaluate("""() => { const c = window.__viserMutable.canvas;
            for (let e = c; e; e = e.parentElement) if (e.style.transform) e.style.transform = ''; }""")

    def field(self, label: str):
        """The text input labelled ``label`` (viser's text inputs are not tied to their label by id)."""
        return self.page.locator(f"xpath=//label[normalize-space()='{label}']/ancestor::div[.//input][1]//input").first

    def type(self, label: str, value: str, wait: bool = True) -> None:
        """Type into a field; with ``wait``, until the server has the value.

        viser's browser client sends input updates through one 50 ms throttle shared by every input and
        button (only the last message of a window goes out): a script typing into several fields at once
        must let each value arrive, as a person's typing speed does. A value the server overwrites while it arrives
        (a preset chosen just before, applied late on a loaded machine) is typed again, up to three times.
        """
        for attempt in range(3):
            box = self.field(label)
            box.fill(value)
            box.press("Tab")
            if not wait:
                return
            handle = self.inputs()[label]
            try:
                wait_until(lambda h=handle: h.value == value, what=f"{label} = {value!r} to reach the server")
                return
            except AssertionError:
                if attempt == 2:
                    raise

    def inputs(self) -> dict:
        """Label -> the session's handle of each text field and dropdown of the form."""
        s = self.session
        out = {FIELDS_BY_KEY[k].label: h for k, h in s.fields.items()}
        lists = (s.preset, s.run_choice, s.rollout_dropdown, s.rollout_order)
        out.update({h.label: h for h in (*s.choices.values(), *lists)})
        out.update({h.label: h for h in s.form.own.handles()})  # the chosen method's own settings, if any
        return out

    def fill_form(self, values: dict[str, str]) -> None:
        if any(k in values for k in ("CE epochs", "pretrain rollouts", "pretrain epochs")):
            self.open_advanced()
        for label, value in values.items():
            self.type(label, value)

    def open_advanced(self) -> None:
        self.open_folder("advanced", "CE epochs")

    def choose(self, label: str, option: str) -> None:
        self.page.get_by_label(label, exact=True).click()
        self.page.get_by_role("option", name=option, exact=True).click()
        handle = self.inputs()[label]
        wait_until(lambda: handle.value == option, what=f"{label} = {option!r} to reach the server")

    def button(self, name: str):
        return self.page.get_by_role("button", name=name, exact=True)

    def open_folder(self, label: str, field_label: str):
        """Expand the folder ``label`` until its field ``field_label`` shows (a click that lands while the folder is
        being rebuilt, e.g. right after a scenario change, is made again); the field's input."""
        field = self.field(field_label)
        for _ in range(3):
            if field.is_visible():
                return field
            try:  # a click that a loaded browser cannot land in 10 s (the panel still moving) is made again
                self.page.get_by_text(label, exact=True).click(timeout=10_000)
                field.wait_for(state="visible", timeout=5_000)
            except sync_api.TimeoutError:
                continue
        field.wait_for(state="visible")
        return field

    def tab(self, name: str) -> None:
        self.page.get_by_role("tab", name=name, exact=True).click()

    def run(self, values: dict[str, str] | None = None, timeout: float = 90.0):
        """Fill the form, press Run, wait for the final estimate; the finished run's record."""
        self.tab("Experiment")
        self.fill_form(values or TINY)
        previous = self.session.record
        self.button("Run").click()
        wait_until(lambda: self.session.record is not previous, what="the run to start")
        record = self.session.record
        wait_until(lambda: record.done and not self.session.running, timeout=timeout, what="the run to finish")
        assert record.status == "finished", record.message
        expect(self.page.get_by_text(f"Final estimate of {record.short_label}")).to_be_visible(timeout=10_000)
        return record

    def uplots(self) -> list[dict]:
        """Every uPlot chart in the page: title, caption (the text below it), series labels, x data and x / y scale
        ranges."""
        return self.page.evaluate(
            """() => Object.entries(window.__viserTestpoints?.uplots ?? {}).map(([k, u]) => ({
                   title: u.chart.root.querySelector('.u-title')?.textContent ?? '',
                   caption: document.querySelector(`.pemviz-caption[data-chart="${k}"]`)?.textContent ?? '',
                   legend: u.chart.root.querySelector('.u-legend')?.textContent ?? '',
                   labels: u.chart.series.map(s => s.label),
                   x: Array.from(u.chart.data[0] ?? []),
                   data: u.chart.data.map(d => Array.from(d ?? []).map(v => v ?? null)),
                   xmin: u.chart.scales.x.min, xmax: u.chart.scales.x.max,
                   ymin: u.chart.scales.y?.min, ymax: u.chart.scales.y?.max,
                   axes: u.chart.axes.map(a => a.label ?? '')}))"""
        )

    def plot(self, title_part: str) -> dict:
        found = [p for p in self.uplots() if title_part in p["title"]]
        assert found, f"no plot titled *{title_part}* in {[p['title'] for p in self.uplots()]}"
        return found[0]

    def scene(self) -> dict:
        """The ego and lead in this tab's three.js scene: positions, colours, label texts."""
        return self.page.evaluate(
            """() => {
                const m = window.__viserMutable.nodeRefFromName;
                const tree = window.__viserSceneTree.getState();
                const prop = (n, k) => tree[n]?.message?.props?.[k];
                return {x: m['/ego'].position.x, lead_x: m['/lead'].position.x,
                        color: prop('/ego', 'color'), label: prop('/ego/label', 'text'),
                        lead_label: prop('/lead/label', 'text'),
                        zones: prop('/ego/brake_zone_10m/label', 'text'),
                        miss_zone_colors: [prop('/ego/brake_zone_10m', 'color'), prop('/ego/crash_zone_2m', 'color')]};
            }"""
        )


def hide_notifications(page) -> None:
    """Headless Chromium renders WebGL on the CPU and viser says so in a notification over the scene:
    hide notifications (none of the tests reads one)."""
    page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")


def shown_at(values: list) -> list[int]:
    """Indices of the values a chart draws (not null / NaN)."""
    return [i for i, v in enumerate(values) if v is not None and v == v]


def wait_until(predicate, timeout: float = 15.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def open_tab(browser, app, viewport: dict | None = None, draw_scene: bool = False):
    """A fixture's body: a :class:`Tab` (``viewport``: its size; ``draw_scene``: as :class:`Tab`), its run stopped
    and the tab closed afterwards."""
    t = Tab(browser, app, viewport, draw_scene)
    yield t
    t.session.stop_run()
    t.session.wait_for_run(10.0)
    t.close()


@pytest.fixture
def tab(browser, app):
    yield from open_tab(browser, app)


# 1 ------------------------------------------------------------------------------------------------
def test_typed_values_run_exactly_as_typed_and_every_error_shows_on_its_field(tab):
    tab.fill_form({"alpha": "abc", "sigma": "1", "K": "", "N": "12.5"})
    page = tab.page
    for message in (
        "alpha: 'abc' is not a number; type a number in (0, 1] (the smoothing alpha)",
        "sigma: 1 is out of range; the quantile level sigma must be a number in [0.5, 1)",
        "K: empty; type a whole number in [1, 1000] (the number of cross-entropy stages K)",
        "N: 12.5 is not a whole number; the rollouts per stage N must be a whole number >= 2",
    ):
        expect(page.get_by_text(message, exact=True)).to_be_visible(timeout=10_000)
    expect(page.get_by_text("4 settings to fix before Run.", exact=False)).to_be_visible()
    expect(tab.button("Run")).to_be_disabled()
    assert tab.field("N").input_value() == "12.5"  # the form keeps what was typed, nothing rounded
    assert tab.session.runs == []

    # valid values; the last one typed and Run pressed at once: the run uses what the server holds, and
    # the form shows exactly that (viser may drop a value typed within 50 ms of the click on its way)
    tab.fill_form({**TINY, "alpha": "1e-3", "sigma": "0.9", "N": "41"})
    tab.type("seed", "12", wait=False)
    tab.button("Run").click()
    wait_until(lambda: tab.session.record is not None, what="the run to start")
    cfg = tab.session.record.config
    assert (
        cfg.adaptive.smoothing,
        cfg.adaptive.quantile_level,
        cfg.adaptive.n_stages,
        cfg.n_per_stage,
        cfg.adaptive.n_final,
    ) == (0.001, 0.9, 2, 41, 60)
    assert cfg.seed in (0, 12)
    for key in ("smoothing", "quantile_level", "n_stages", "n_per_stage", "n_final", "seed"):
        f = FIELDS_BY_KEY[key]
        shown = tab.field(f.label)
        expect(shown).to_have_value(re.compile("^(" + re.escape(tab.session.fields[key].value) + ")$"))
        assert parse(f, shown.input_value()) == cfg.value(key)
    assert tab.field("alpha").input_value() == "1e-3"  # as typed, not reformatted
    expect(page.get_by_text("settings to fix")).to_have_count(0)


def test_every_field_and_dropdown_has_a_hint_each_setting_the_one_its_flag_gives(tab):
    s = tab.session
    from pemviz.scenarios.registry import scenario_hint

    for key, handle in {**s.fields, **s.choices}.items():
        hint = scenario_hint() if key == "scenario" else SETTINGS[key].hint  # every registered scenario, as --help
        assert (handle.label, handle.hint) == (SETTINGS[key].label, hint), key
    # not the weight of a new fit in an update: that is another method
    assert s.fields["smoothing"].hint == (
        "smoothing alpha, a number in (0, 1]: the power on the importance weights " "in the CE loss"
    )
    metric = s.choices["metric"].hint
    assert "\n" not in metric and all(f"; {m}: " in metric for m in ("classic", "agm", "smooth-cumulative"))
    assert all(h.hint for h in (s.preset, s.run_choice, s.rollout_dropdown))


def parse(field, text: str):
    value, error = parse_number(field, text)
    assert not error, error
    return value


# 3 ------------------------------------------------------------------------------------------------
def test_finished_runs_survive_stopped_ones_pinned_runs_stay_and_any_kept_run_exports(tab, app):
    s = tab.session
    first = tab.run({**TINY, "K": "1"})
    second = tab.run({**TINY, "K": "2", "N": "30"})
    assert first.label != second.label and "K 1" in first.label and "K 2, N 30" in second.label
    # pin run 1 from the Runs tab
    tab.tab("Runs")
    tab.choose("kept run", first.label)
    tab.button("Pin").click()
    wait_until(lambda: first.pinned, what="run 1 pinned")
    expect(tab.button("Unpin")).to_be_visible()
    # the run chosen under Runs is the one the Rollouts tab lists and Explain explains
    wait_until(lambda: s.listed is first and s.shown_record is first, what="Rollouts and Explain to follow run 1")
    tab.tab("Rollouts")
    expect(
        tab.page.get_by_text(f"Every failure of the final estimate of {first.short_label}", exact=False)
    ).to_be_visible()
    # three stopped runs: the first is dropped to make room, never the finished run 2 or the pinned run 1
    stopped = []
    for _ in range(3):
        tab.tab("Experiment")
        tab.fill_form({"K": "200"})  # long enough to be stopped under load
        tab.button("Run").click()
        wait_until(lambda: s.running and s.record not in (first, second, *stopped), what="a run to start")
        stopped.append(s.record)
        tab.button("Stop").click()
        wait_until(lambda: not s.running, what="the run to stop")
        # no view describes a stopped run as going
        wait_until(lambda: "is going" not in s.explain_html.content + s.scene_html.content, what="'is going' gone")
        expect(tab.page.get_by_text("is going", exact=False)).to_have_count(0)
    assert s.runs == [first, second, *stopped[1:]]  # the oldest stopped run made room
    # the compare table shows every setting of every kept run
    tab.page.get_by_role("tab", name="Compare").click()
    expect(tab.page.get_by_text("Reference-state curves", exact=False)).to_be_visible()
    compare = tab.page.locator("table.pemviz-table").last
    for setting in ("seed", "K", "N", "N_e", "simulator", "PEM", "alpha", "sigma", "metric"):
        expect(compare.locator("th", has_text=re.compile(f"^{re.escape(setting)}$"))).to_have_count(1)
    # export the pinned run 1 (not the newest)
    tab.tab("Runs")
    tab.choose("kept run", first.label)
    tab.button("Export chosen run").click()
    expect(tab.page.get_by_text(f"Saved {first.short_label} to", exact=False)).to_be_visible(timeout=30_000)
    path = Path(app.recordings_dir) / f"run{first.run_id}-{first.config.metric}.rrd"
    assert s.last_export == path.resolve() and path.stat().st_size > 1000


# 4, 5 ---------------------------------------------------------------------------------------------
def test_one_stage_numbering_and_plot_axes_follow_the_stages_that_ran(tab):
    tab.fill_form({**TINY, "K": "100000"})
    expect(tab.page.get_by_text("K: 100000 is out of range", exact=False)).to_be_visible(timeout=10_000)
    expect(tab.button("Run")).to_be_disabled()
    tab.fill_form({"K": "1000", "N": "510"})  # 510,000 simulations: above the 500,000 that need a confirmation
    sims = 1000 * 510 + int(TINY["pretrain rollouts"]) + int(TINY["N_e"])
    expect(tab.page.get_by_text(f"Cost: {sims:,} simulations", exact=False)).to_be_visible(timeout=10_000)
    tab.button("Run").click()
    expect(tab.button("Run anyway")).to_be_visible(timeout=10_000)  # a large run asks first
    assert tab.session.record is None
    tab.button("Run anyway").click()
    # the status names the stage as the console does: "CE stage k/K"
    expect(tab.page.get_by_text(re.compile(r"CE stage [3-9]/1000: "))).to_be_visible(timeout=60_000)
    tab.button("Stop").click()
    record = tab.session.record
    wait_until(lambda: not tab.session.running, what="the run to stop")
    last = record.stages[-1].stage
    wait_until(lambda: tab.plot("failures / N per stage")["xmax"] < last + 1, what="the x axes to fit the stages")
    for title in ("failures / N per stage", "log10 mu_hat per stage", "gamma per stage, classic (m)"):
        # each plot gets the last stage's point on its own update, after the status has said it stopped
        wait_until(
            lambda: tab.plot(title)["x"] == list(range(last + 1)),  # noqa: B023 (called within the iteration)
            what=f"{title}: a point per stage that ran",
        )
        p = tab.plot(title)
        assert p["x"] == list(range(last + 1)), title  # stage numbers as the engine counts them
        assert p["xmax"] == pytest.approx(last + 0.5) and p["axes"][0].startswith("stage (0 pretraining")
        assert p["axes"][1] and "--" not in p["legend"]
    assert tab.plot("log10 mu_hat per stage")["ymax"] > max(v for v in record.stage_series("log10_mu_hat").values())
    curve = tab.plot("mean q(detect) vs the PEM")
    assert curve["caption"].startswith(f"{record.short_label}: mean q(detect) over the visited states")
    assert "PEM" in curve["labels"] and "stage 1" in curve["labels"] and "pretraining" not in curve["labels"]
    assert curve["ymax"] > 1.0  # the top tick "1" is inside the plot


# 5 (units) ------------------------------------------------------------------------------------------
def test_gamma_of_runs_with_other_metrics_is_not_drawn_on_the_same_axis(tab):
    classic = tab.run({**TINY, "K": "1"})  # one stage each: a gamma per run is all the chart needs
    tab.choose("metric", "agm")
    agm = tab.run({**TINY, "K": "1"})
    p = tab.plot("gamma per stage, agm (unitless)")
    assert p["caption"].endswith("; 1 run of another metric not shown")
    assert p["labels"] == ["stage", agm.short_label]
    assert classic.short_label not in p["labels"]


# 8 ------------------------------------------------------------------------------------------------
def test_two_tabs_have_their_own_form_runs_and_stop(tab, browser, app):
    other = Tab(browser, app)
    try:
        tab.fill_form({"K": "100", "alpha": "0.3"})  # long enough to outlast tab B's run
        expect(other.field("alpha")).to_have_value("0.1")
        tab.button("Run").click()
        wait_until(lambda: tab.session.running, what="tab A's run")
        expect(other.button("Stop")).to_be_disabled()
        expect(other.button("Run")).to_be_enabled()
        assert other.session.runs == [] and other.session.record is None
        # B runs its own experiment while A's goes on; B's Stop stops only B's
        other.button("Run").click()
        wait_until(lambda: other.session.running, what="tab B's run")
        other.button("Stop").click()
        wait_until(lambda: not other.session.running, what="tab B's run to stop")
        assert other.session.record.status == "cancelled" and tab.session.running
        assert (
            other.session.record.config.adaptive.smoothing == 0.1
            and tab.session.record.config.adaptive.smoothing == 0.3
        )
    finally:
        other.close()


# 9 ------------------------------------------------------------------------------------------------
def test_progress_shows_elapsed_and_expected_time(tab):
    tab.fill_form({**TINY, "K": "40", "CE epochs": "150"})
    tab.button("Run").click()
    status = re.compile(
        r"CE stage \d+/40: cross-entropy update \(at most 150 epochs\) · stage \d+\.\d s(, about \d+\.\d s left in "
        r"it|, nearly done) · run \d+\.\d s, ~[0-9.]+ (s|min) left in all(, up to ~[0-9.]+ (s|min))?"
    )
    expect(tab.page.get_by_text(status)).to_be_visible(timeout=60_000)
    tab.button("Stop").click()
    expect(
        tab.page.get_by_text(re.compile(r"stopped after \d+ stages \(\d\.\d\d s after Stop\), \d+\.\d s in all"))
    ).to_be_visible(timeout=10_000)
    assert tab.session.last_stop_latency_s < 2.0


# 11 -----------------------------------------------------------------------------------------------
def test_every_dropdown_shows_its_hint_in_the_browser(tab):
    """Hovering any dropdown of any tab of the control panel shows a non-empty hint, the one its handle holds."""
    page = tab.page
    s = tab.session
    expected = {
        h.label: h.hint for h in (*s.choices.values(), s.preset, s.run_choice, s.rollout_dropdown, s.rollout_order)
    }
    seen = {}
    for name in ("Experiment", "Rollouts", "Runs"):
        tab.tab(name)
        if name == "Experiment":
            tab.open_advanced()
        selects = page.locator("input[aria-haspopup='listbox']:visible")
        expect(selects.first).to_be_visible()
        for i in range(selects.count()):
            select = selects.nth(i)
            label = select.locator("xpath=ancestor::div[.//label][1]//label").first.inner_text().strip()
            select.hover()
            tip = page.get_by_role("tooltip")
            expect(tip).to_be_visible(timeout=10_000)
            seen[label] = tip.inner_text().strip()
            page.mouse.move(1, 1)
            expect(tip).to_have_count(0, timeout=10_000)
    assert set(seen) == set(expected), (set(seen), set(expected))  # every dropdown, no other
    for label, hint in seen.items():
        assert hint and hint == expected[label].strip(), label
    assert all(f"{m}: " in seen["metric"] for m in ("classic", "agm", "smooth-cumulative"))  # what each rewards
    assert all(f"{p}: " in seen["preset"] for p in ("state-ce", "paper", "quick"))
