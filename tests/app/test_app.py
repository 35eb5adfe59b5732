"""``pemviz serve`` end to end in headless Chromium: one test per defect a safety engineer hit in the panel.

One panel server (in-process, 127.0.0.1, a free port) and one browser for the module; each test opens its
own tab, which gets its own session (form, runs, Stop, scene). The browser types and clicks the way a user
does; the session's state, the browser's scene graph (``window.__viserMutable`` / ``__viserSceneTree``)
and its uPlot charts (``window.__viserTestpoints``) are what the tests compare. Every wait is on a
condition. Chromium is Debian's (``apt-get install chromium``; ``.ci/run`` installs it).
"""

from __future__ import annotations

import math
import os
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

sync_api = pytest.importorskip("playwright.sync_api", reason="the Python playwright package is not installed")
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
if not os.path.exists(CHROMIUM):
    pytest.skip("Debian's chromium is not installed (apt-get install chromium)", allow_module_level=True)

from pemviz.app.form import FIELDS_BY_KEY, parse_number  # noqa: E402
from pemviz.app.panel import PanelApp  # noqa: E402
from pemviz.app.session import Session  # noqa: E402
from pemviz.settings import SETTINGS  # noqa: E402
from pemviz.scenarios.braking.panel import explain  # noqa: E402
from pemviz.sinks import colours  # noqa: E402

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


class Tab:
    """A browser tab and its server-side session."""

    def __init__(self, browser, app: PanelApp, viewport: dict | None = None) -> None:
        known = set(app.sessions)
        self.page = browser.new_page(viewport=viewport or VIEWPORT)
        self.page.set_default_timeout(90_000)  # a click waits for a renderer a loaded machine starves
        self.page.goto(app.url)
        self.session: Session = app.wait_for_session(known)
        hide_notifications(self.page)
        self.field("alpha").wait_for(timeout=60_000)

    def close(self) -> None:
        self.page.close()

    def field(self, label: str):
        """The text input labelled ``label`` (viser's text inputs are not tied to their label by id)."""
        return self.page.locator(f"xpath=//label[normalize-space()='{label}']/ancestor::div[.//input][1]//input").first

    def type(self, label: str, value: str, wait: bool = True) -> None:
        """Type into a field; with ``wait``, until the server has the value.

        viser's browser client sends input updates through one 50 ms throttle shared by every input and
        button (only the last message of a window goes out): a script typing into several fields at once
        must let each value arrive, as a person's typing speed does.
        """
        box = self.field(label)
        box.fill(value)
        box.press("Tab")
        if wait:
            handle = self.inputs()[label]
            wait_until(lambda: handle.value == value, what=f"{label} = {value!r} to reach the server")

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


def open_tab(browser, app, viewport: dict | None = None):
    """A fixture's body: a :class:`Tab` (``viewport``: its size), its run stopped and the tab closed afterwards."""
    t = Tab(browser, app, viewport)
    yield t
    t.session.stop_run()
    t.session.wait_for_run(10.0)
    t.close()


@pytest.fixture
def tab(browser, app):
    yield from open_tab(browser, app)


class Crashed:
    """A tab at 1400 x 900 (``tab``), the scene it drew before any run (``idle``: :meth:`Tab.scene`), and its finished
    run of three stages (``record``) whose most likely failure is shown: tests that only read them, or move the step
    slider, share one run."""

    def __init__(self, tab: Tab) -> None:
        self.tab = tab
        self.idle = tab.scene()
        self.record = tab.run({**TINY, "K": "3"})


@pytest.fixture(scope="module")
def crashed(browser, app):
    for t in open_tab(browser, app, {"width": 1400, "height": 900}):
        yield Crashed(t)


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


# 2 ------------------------------------------------------------------------------------------------
def test_the_scene_and_strip_chart_follow_the_newest_run_and_name_it(tab, app):
    first = tab.run()
    wait_until(lambda: tab.session.shown is not None and tab.session.shown_record is first, what="run 1 shown")
    second = tab.run({"seed": "3"})
    # run 2's most likely failure (or least-robust rollout) is shown, named by its run, in the browser
    wait_until(lambda: tab.session.shown_record is second, what="the scene to switch to run 2")
    shown = tab.session.shown
    assert shown is second.most_likely_failure or second.most_likely_failure is None
    ego_x, _ = app.drawing.lane_positions(shown.batch, 0)[:2]
    wait_until(
        lambda: tab.scene()["label"].startswith(f"{second.short_label} {shown.name} t=0.00s"),
        what="the browser's scene label to name run 2",
    )
    assert abs(tab.scene()["x"] - ego_x[0]) < 1e-3

    # the explanation: strip chart of that rollout, its decisive misses as the counterfactual finds them
    ex = explain(shown.signal("gap_m"), shown.detected, shown.log_p, shown.log_q, app.drawing.params)
    tab.page.get_by_role("tab", name="Explain").click()
    expect(tab.page.get_by_text("Counterfactual", exact=False)).to_be_visible(timeout=10_000)
    gap = tab.plot("gap and speeds")
    assert (
        gap["title"] == "gap and speeds"
        and gap["caption"] == f"{second.short_label} stage {shown.stage} rollout {shown.index}"
    )
    assert np.allclose(gap["data"][1], shown.signal("gap_m"))
    assert set(gap["labels"]) >= {"crash gap 2 m", "braking distance 10 m", "gap (m)"}
    detect = tab.plot("p(detect) and q(detect)")
    decisive = shown_at(detect["data"][detect["labels"].index("decisive miss")])
    assert decisive == ex.decisive.tolist()

    # playback moves the scene and the strip chart's marker together
    tab.session.step_slider.value = 30
    wait_until(lambda: abs(tab.scene()["x"] - ego_x[30]) < 1e-3, what="the scene at step 30")
    now = tab.plot("p(detect) and q(detect)")["data"][-1]
    assert shown_at(now) == [30]


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
    tab.fill_form({"K": "1000", "N": "1000"})
    sims = 1000 * 1000 + int(TINY["pretrain rollouts"]) + int(TINY["N_e"])
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


# 6 ------------------------------------------------------------------------------------------------
def test_the_final_estimate_comes_with_its_interval_verdict_and_a_hint_when_nothing_failed(crashed, tab):
    record = crashed.record
    e = record.final.estimate
    text = crashed.tab.page.inner_text("body")
    assert f"failures {e.n_failures}/{e.n}" in text and "ESS" in text and "k-hat" in text
    if hasattr(e, "log_ci"):
        assert "95 % interval" in text and e.verdict in text and e.reason in text
    if record.exact_log_p is not None:
        assert "exact answer" in text
    tab.open_advanced()
    tab.choose("method", "mc")
    tab.run({"N": "20"})
    expect(tab.page.get_by_text("no failure among 20 rollouts, so mu_hat = 0", exact=False)).to_be_visible()
    # the advice speaks of what plain Monte Carlo does, not of stages or a proposal it does not have
    expect(
        tab.page.get_by_text("plain Monte Carlo draws every rollout from the PEM itself", exact=False)
    ).to_be_visible()
    assert (
        "More stages (K)" not in tab.session.result_html.content and "proposal" not in tab.session.result_html.content
    )


# 7 ------------------------------------------------------------------------------------------------
def test_scene_colours_are_the_recordings_idle_ego_is_grey_and_the_cars_never_overlap(crashed, app):
    from pemviz.sinks import rerun_views as recording  # the recording's colours

    tab, record = crashed.tab, crashed.record
    before = crashed.idle  # the scene before any run
    assert tuple(before["color"]) == colours.IDLE  # not green ("detected") before any rollout
    assert before["lead_label"] == "lead" and "within 10 m" in before["zones"] and "2 m crash" in before["zones"]
    assert recording.MISSED_RGBA == (245, 130, 30, 255) and recording.DETECTED_RGBA == (40, 170, 80, 255)
    assert (colours.MISSED, colours.DETECTED) == ((245, 130, 30), (40, 170, 80))  # the panel's: orange and green
    shown = tab.session.shown
    assert shown is not None and shown.crashed, "the quick preset finds a crash"
    t_crash = int(np.argmax(shown.signal("gap_m") < app.drawing.params.crash_gap_m))
    tab.session.step_slider.value = t_crash
    wait_until(
        lambda: tab.scene()["label"].startswith(f"{record.short_label} {shown.name} t={t_crash * 0.05:.2f}s"),
        what="the crash step",
    )
    s = tab.scene()
    assert tuple(s["color"]) == (colours.DETECTED if shown.detected[t_crash] else colours.MISSED)
    p = app.drawing.params
    assert s["lead_x"] - p.lead_length_m / 2 >= s["x"] + p.ego_length_m / 2 - 1e-6  # lead rear ahead of ego front


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


# 10 -----------------------------------------------------------------------------------------------
def test_live_shows_what_the_sampler_did_and_explain_says_why_and_how_bad(tab, app):
    """A default run (state-ce): the sampler's q(detect) over the visited states inside the 10 m window sits below
    the PEM's; the mu_hat chart shows the interval and the exact answer; Explain gives the severity, the controller,
    and for a failure that no single miss decides, its minimal miss set."""
    from pemviz.scenarios.braking.failures import severity

    s = tab.session
    tab.choose("preset", "state-ce")
    record = tab.run({"seed": "0", "K": "4", "N_e": "300"}, timeout=300)  # state-ce, fewer stages and final rollouts
    live = tab.plot("mean q(detect) vs the PEM")
    x = np.array(live["data"][0])
    pem = np.array(live["data"][live["labels"].index("PEM")], dtype=float)
    final = np.array(live["data"][live["labels"].index("final batch")], dtype=float)
    inside = (x > 3.0) & (x < 9.0) & np.isfinite(pem) & np.isfinite(final)
    assert inside.sum() >= 8 and np.all(final[inside] < pem[inside])
    assert np.mean(pem[inside] - final[inside]) > 0.2  # the sampler misses far more often than the PEM there
    assert "median log q(miss)/q(detect)" in tab.plot("log q(miss)/q(detect)")["title"]
    mu = tab.plot("log10 mu_hat per stage")
    assert "band: its 95 % interval" in mu["caption"] and "black: the exact answer" in mu["caption"]
    assert f"{record.short_label} 95 % low" in mu["labels"] and any(lab.startswith("exact") for lab in mu["labels"])

    # Explain: the most likely failure with its severity in words, what happened, and the controller
    wait_until(lambda: s.shown is record.most_likely_failure, what="the most likely failure shown")
    tab.page.get_by_role("tab", name="Explain").click()
    words = severity(s.shown.signal("gap_m"), app.drawing.params).short
    expect(tab.page.get_by_text(words, exact=False).first).to_be_visible(timeout=10_000)
    expect(tab.page.get_by_text("What happened", exact=False)).to_be_visible()
    applied = np.flatnonzero(s.explanation.controller.brake_applied).tolist()

    def shown_series(title: str, label: str) -> list[int]:
        p = tab.plot(title)
        return shown_at(p["data"][p["labels"].index(label)]) if label in p["labels"] else []

    assert applied
    wait_until(lambda: shown_series("controller", "brake applied") == applied, what="the brake in the controller chart")

    # a failing rollout that no single miss decides (among the least robust): its minimal miss set, shown and marked
    tab.tab("Rollouts")
    tab.choose("sort by", "robustness")

    def undecided() -> list[str]:  # the panel refills its rollout list after the sort: wait for one, never sleep
        return [
            lab
            for lab, t in list(s._rollout_labels.items())
            if t.crashed
            and t is not record.most_likely_failure
            and app.drawing.lane_explanation(t.batch, 0).decisive.size == 0
        ]

    wait_until(lambda: bool(undecided()), what="a failing rollout no single miss decides, listed after the sort")
    label = undecided()[0]
    tab.tab("Rollouts")
    tab.choose("rollout", label)
    wait_until(lambda: s.shown is s._rollout_labels[label], what="the rollout shown")
    cf = s.explanation.counterfactual
    assert cf.minimal_set.size >= 2 and s.explanation.decisive.size == 0
    tab.page.get_by_role("tab", name="Explain").click()
    expect(tab.page.get_by_text(f"{cf.minimal_set.size} misses at", exact=False)).to_be_visible(timeout=10_000)
    expect(tab.page.get_by_text("none: no single detection saves it", exact=False)).to_be_visible()
    wait_until(
        lambda: shown_series("p(detect) and q(detect)", "minimal miss set") == cf.minimal_set.tolist(),
        what="the minimal miss set marked in the strip chart",
    )

    # the Rollouts table lists every failure of the final estimate, the largest importance weight first, and groups
    # them by their last saving detection, the groups' shares adding up to 1
    tab.tab("Rollouts")
    tab.choose("sort by", "importance weight")
    pop, final = record.population, record.final
    n = final.estimate.n_failures
    expect(
        tab.page.get_by_text(f"Every failure of the final estimate of {record.short_label}: {n:,}", exact=False)
    ).to_be_visible(timeout=10_000)
    expect(tab.page.get_by_text("by importance weight", exact=False)).to_be_visible(timeout=10_000)
    assert pop.shares.n == n and sum(t is not None for t in pop.rollouts) == n
    first = tab.page.evaluate("""() => {
        const t = [...document.querySelectorAll('table.pemviz-table')].find(x => x.textContent.includes('share of p')
                                                                          && x.textContent.includes('outcome'));
        return [...t.querySelectorAll('tr')[1].querySelectorAll('td')].map(td => td.textContent);}""")
    best = int(np.argmax(pop.shares.log_weight))  # the estimate's own weights: w lambda_k N / n_k
    assert best == 0 and first[1:3] == [str(pop.shares.stage[0]), str(pop.shares.index[0])], first
    from scipy.special import logsumexp

    assert math.isclose(
        float(logsumexp(pop.shares.log_weight)) - math.log(final.estimate.n), final.estimate.log_mu_hat, rel_tol=1e-12
    )
    assert math.isclose(sum(g.share for g in pop.groups), 1.0, rel_tol=1e-12) and len(pop.groups) >= 2
    expect(tab.page.get_by_text(pop.groups[0].label, exact=False).first).to_be_visible()
    if os.environ.get("PEMVIZ_SCREENSHOTS") == "1":  # the Rollouts tab as the user guide shows it
        shot = Path(__file__).resolve().parents[2] / "assets" / "screenshots" / "panel_rollouts.png"
        tab.page.get_by_text("share of p", exact=True).last.scroll_into_view_if_needed()
        tab.page.screenshot(path=str(shot.with_name(shot.name + ".partial.png")))
        os.replace(shot.with_name(shot.name + ".partial.png"), shot)

    # sorted by severity (the fastest contact first), then filtered to failures
    tab.choose("sort by", "severity")
    expect(tab.page.get_by_text("by severity", exact=False)).to_be_visible(timeout=10_000)
    listed = s.rollouts_tab.ordered_rollouts(record)
    speeds = [
        severity(t.signal("gap_m"), app.drawing.params).contact_speed_mps for t in [*pop.rollouts, *record.trajectories]
    ]
    assert severity(listed[0].signal("gap_m"), app.drawing.params).contact_speed_mps == np.nanmax(speeds)
    tab.page.get_by_label("failures only").check()
    wait_until(lambda: all(t.crashed for t in s.rollouts_tab.ordered_rollouts(record)), what="only failures listed")
    expect(tab.page.get_by_text("least robust rollouts outside it, by severity", exact=False)).to_be_visible()


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


# 12 -----------------------------------------------------------------------------------------------
def test_the_scene_frames_both_cars_and_shows_the_gap_the_breach_and_the_detections_so_far(crashed, app):
    """At 1400 x 900, at the step a failure crosses the 2 m line: the canvas lies between the panels and both cars
    project inside it; the ruler spans the gap and says it in metres; a red gate stands where the ego's camera crossed
    the line; the trail holds one square per step so far, green where detected and orange where missed; every label
    beside the road lies outside both cars on screen, on the side its text runs to."""
    tab, record = crashed.tab, crashed.record
    s, p = tab.session, app.drawing.params
    shown = s.shown
    assert shown is not None and shown.crashed, "the quick preset finds a crash"
    b = s.explanation.severity.breach_step
    assert b == int(np.argmax(shown.signal("gap_m") < p.crash_gap_m))
    s.step_slider.value = b
    wait_until(
        lambda: tab.scene()["label"].startswith(f"{record.short_label} {shown.name} t={b * p.dt_s:.2f}s"),
        what="the breach step",
    )
    ego_x, lead_x = app.drawing.lane_positions(shown.batch, 0)[:2]
    cam, rear = ego_x[b] + p.camera_offset_m, lead_x[b] - p.lead_length_m / 2
    h = 1.5  # the boxes' height (metres)
    grid = np.linspace(-0.5, 0.5, 5)
    boxes = [
        [x + fx * length, fy * p.vehicle_width_m, (fz + 0.5) * h]
        for x, length in ((ego_x[b], p.ego_length_m), (lead_x[b], p.lead_length_m))
        for fx in grid
        for fy in grid
        for fz in grid
    ]
    labels = {
        "/ego/label": "right",
        "/gap_ruler/label": "right",
        "/ego/brake_zone_10m/label": "right",
        "/breach/label": "left",
    }  # the labels beside the road and the side their text runs to

    def read():
        return tab.page.evaluate(SCENE_JS, [boxes, list(labels)])

    # the camera follows the cars (it may arrive after the scene's step): both cars inside the canvas
    wait_until(lambda: np.all(np.abs(np.array(read()["boxes"])) < 1.0), what="both cars inside the canvas")
    got = read()
    # the canvas is the space between the panels
    assert got["left_panel"] <= got["canvas"][0] and got["canvas"][1] <= got["run_left"]
    # the gap ruler: from the ego's camera to the lead's rear, its label the gap in metres
    ruler = np.array(got["ruler"]).reshape(3, 2, 3)
    np.testing.assert_allclose(ruler[0, :, 0], [cam, rear], atol=1e-4)
    gap_b = shown.signal("gap_m")[b]
    assert got["gap_text"] == f"gap {gap_b:.2f} m" and gap_b < p.crash_gap_m
    # the breach gate where the camera crossed the 2 m line, with its time
    assert got["breach_visible"] and abs(got["breach_x"] - cam) < 1e-4
    assert got["breach_text"] == f"{p.crash_gap_m:g} m line crossed\nat {b * p.dt_s:.2f} s"
    # the trail: a square per step 0..b behind where the ego was, coloured by the detection
    trail = np.array(got["trail"]).reshape(-1, 3)
    assert got["trail_visible"] and trail.shape[0] == b + 1
    np.testing.assert_allclose(trail[:, 0], ego_x[: b + 1] - p.ego_length_m / 2 - 0.35, atol=1e-4)
    drawn = np.array(got["trail_colours"]).reshape(-1, 3)
    want = np.where(shown.detected[: b + 1, None], colours.DETECTED, colours.MISSED)
    np.testing.assert_array_equal(drawn, want)
    assert not shown.detected[: b + 1].all() and shown.detected[: b + 1].any()  # both colours are drawn
    # labels beside the road: the rectangle of each one's text (7 px a character, 17 px a line, generously)
    # holds no point of either car on screen
    width_px, height_px = got["canvas"][2], got["canvas"][3]
    cars = np.array(got["boxes"])
    for (name, side), (ax, ay), text in zip(labels.items(), got["anchors"], got["texts"], strict=False):
        lines = text.split("\n")
        w, hh = 7 * max(map(len, lines)) / (width_px / 2), 17 * len(lines) / (height_px / 2)
        x0, x1 = (ax, ax + w) if side == "right" else (ax - w, ax)
        inside = (cars[:, 0] > x0) & (cars[:, 0] < x1) & (np.abs(cars[:, 1] - ay) < hh / 2)
        assert not inside.any(), f"{name} ({text!r}) covers a car"


SCENE_JS = """([boxes, names]) => {
    const m = window.__viserMutable, tree = window.__viserSceneTree.getState();
    const ego = m.nodeRefFromName['/ego'], V = ego.position.constructor, root = ego.parent;
    root.updateMatrixWorld(true);  // the scene's frame (+z up) in three.js' world
    const project = (v, frame) => { v.applyMatrix4(frame.matrixWorld).project(m.camera); return [v.x, v.y]; };
    const ndc = ps => ps.map(([x, y, z]) => project(new V(x, y, z), root));
    const parent = n => m.nodeRefFromName[n.slice(0, n.lastIndexOf('/'))];
    const anchor = n => project(new V(...m.nodePoseData[n].position), parent(n));
    const rect = e => { const r = e.getBoundingClientRect(); return [r.left, r.right, r.width, r.height]; };
    const canvas = Array.from(document.querySelectorAll('canvas')).filter(c => c.width > 300)
      .map(rect).sort((a, b) => b[2] - a[2])[0];
    const charts = Array.from(document.querySelectorAll('.u-wrap')).map(rect);
    const run = rect(Array.from(document.querySelectorAll('button')).find(b => b.innerText.trim() === 'Run'));
    const props = n => tree[n]?.message?.props ?? {};
    return {boxes: ndc(boxes), anchors: names.map(anchor), canvas, left_panel: Math.max(...charts.map(r => r[1])),
            run_left: run[0], texts: names.map(n => props(n).text), ruler: Array.from(props('/gap_ruler').points),
            gap_text: props('/gap_ruler/label').text, breach_text: props('/breach/label').text,
            breach_x: m.nodeRefFromName['/breach'].position.x, breach_visible: tree['/breach'].visibility,
            trail: Array.from(props('/trail').points), trail_colours: Array.from(props('/trail').colors),
            trail_visible: tree['/trail'].visibility};
}"""
"""What the browser's scene holds: the given world points (the cars) and the named labels' anchors projected by its
camera to the canvas ([-1, 1] inside), the canvas' and the panels' edges (pixels), the labels' texts, the ruler's
points, the breach gate, the trail's points and colours."""
