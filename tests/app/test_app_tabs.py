"""Every tab of the panel after a run, in headless Chromium, for the braking scenario and the cut-in: every uPlot chart
shown has data (at least one finite point beside its x values), and a cut-in's *Live* and *Explain* are at the braking
scenario's level: q(detect) of the cut-in car per bin of its gap ahead beside the PEM's, what happened in words, the
severity, the tracker's estimate of the cut-in car against the truth and the ACC's acceleration; the same run's most
likely failure shows every car of the cut-in and the errors that decided it.

Uses the browser, server and tab helpers of ``tests/app/test_app.py``. With ``PEMVIZ_SCREENSHOTS=1`` the tests also
write ``assets/screenshots/panel_<scene>_<tab>.png`` (braking and cut_in; live, explain, compare, rollouts, runs,
experiment) at 1400 x 1300.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
from pemviz.app import charts
from pemviz.app.captions import MAX_TITLE
from pemviz.scenarios.cut_in.panel import GAP_BINS_M as OBJECT_GAP_BINS_M
from pemviz.scenarios.cut_in.panel import VIEW_OBJECT
from pemviz.sinks import colours
from scipy.special import expit

from .test_app import TINY, Tab, app, browser, expect, open_tab, wait_until  # noqa: F401  (app, browser: fixtures)

SCREENSHOTS = Path(__file__).resolve().parents[2] / "assets" / "screenshots"
VIEWPORT = {"width": 1400, "height": 1300}
TABS = ("Live", "Explain", "Compare", "Rollouts", "Runs", "Experiment")
"""The plot panel's tabs (left: Live, Explain, Compare) and the control panel's (right); the left panel keeps its tab
while the right one changes, so every chart shown is checked under each."""
CHARTS_PER_TAB = {"braking": {"Live": 6, "Explain": 4, "Compare": 2}, "cut_in": {"Live": 6, "Explain": 3, "Compare": 2}}
"""Charts each left tab shows after one run: Live the two q(detect) charts and the four per-stage charts; Explain the
braking scenario's four strip charts or the cut-in's three (tracker gap, tracker lateral offset, ACC); Compare the
estimates and the run's reference-state curve."""

CHARTS_JS = """() => Object.entries(window.__viserTestpoints?.uplots ?? {}).map(([k, u]) => ({
    title: u.chart.root.querySelector('.u-title')?.textContent ?? '',
    caption: document.querySelector(`.pemviz-caption[data-chart="${k}"]`)?.textContent ?? '',
    visible: u.chart.root.checkVisibility(),
    labels: u.chart.series.map(s => s.label),
    finite: u.chart.data.slice(1).map(d => Array.from(d ?? []).filter(v => v != null && Number.isFinite(v)).length),
    data: u.chart.data.map(d => Array.from(d ?? []).map(v => v ?? null))}))"""
"""Every uPlot chart of the page: its title, its caption (the text below it), whether it is shown, its series' labels,
each y series' count of finite values and its data."""


OBJECTS_JS = """(n) => {
    const m = window.__viserMutable, tree = window.__viserSceneTree.getState();
    const cells = Array.from(document.querySelectorAll('svg.pemviz-raster rect[height="10"]'))
        .map(r => r.getAttribute('fill'));
    const cars = [...Array(n).keys()].map(j => {
        const name = '/objects/car' + j;
        return {position: m.nodePoseData[name]?.position, color: tree[name]?.message?.props?.color,
                visible: tree[name]?.visibility, label: tree[name + '/label']?.message?.props?.text};
    });
    const above = Array.from(document.querySelectorAll('div')).map(d => d.textContent)
        .filter(t => t.startsWith('From above at step')).at(-1) ?? '';
    const tracks = document.querySelectorAll('svg.pemviz-birds-eye rect.pemviz-track').length;
    const detect = Array.from(document.querySelectorAll('svg.pemviz-detect polyline'))
        .map(p => p.getAttribute('points'));
    return {cells, cars, above, tracks, detect, braking_lead: tree['/lead']?.visibility};
}"""
"""The Explain raster's cells (fill colours, object by object, step by step), each car of the scene (position,
colour, visibility, label), the bird's-eye view's heading, the proposal bands' polylines (each object's p then q) and
the braking scene's lead's visibility."""


def shown_charts(tab: Tab) -> list[dict]:
    return [c for c in tab.page.evaluate(CHARTS_JS) if c["visible"]]


def empty(chart: dict) -> bool:
    """No y series of the chart has a finite value."""
    return sum(chart["finite"]) == 0


def check_every_tab(tab: Tab, scene: str) -> dict[str, list[dict]]:
    """Open each tab; every chart shown has a finite point and each left tab shows its charts; with
    ``PEMVIZ_SCREENSHOTS=1`` the tab is written to ``panel_<scene>_<tab>.png``. The charts shown per tab."""
    seen = {}
    for name in TABS:
        tab.tab(name)
        n = CHARTS_PER_TAB[scene].get(name, 1)
        wait_until(
            lambda: (
                len(shown_charts(tab)) >= n  # noqa: B023 (called within the iteration)
                and not any(empty(c) for c in shown_charts(tab))
            ),
            what=f"{scene} {name}: {n} charts shown, each with data",
        )
        shown = shown_charts(tab)
        assert not [c["title"] for c in shown if empty(c)], f"{scene} {name}: empty charts shown"
        long = [c["title"] for c in tab.page.evaluate(CHARTS_JS) if len(c["title"]) > MAX_TITLE]
        assert (
            not long
        ), f"{scene} {name}: chart titles over {MAX_TITLE} characters (the caption is for the rest): {long}"
        text = tab.page.inner_text("body")
        assert not re.search(r"\bs\d+r\d+\b", text), f"{scene} {name}: a rollout named by its key, not in words"
        seen[name] = shown
        if os.environ.get("PEMVIZ_SCREENSHOTS") == "1":
            tab.page.wait_for_function("() => document.fonts.ready.then(() => true)")
            path = SCREENSHOTS / f"panel_{scene}_{name.lower()}.png"
            partial = path.with_name(path.stem + ".partial.png")
            tab.page.screenshot(path=str(partial))
            os.replace(partial, path)
    for name, n in CHARTS_PER_TAB[scene].items():
        assert len(seen[name]) == n, (name, [c["title"] for c in seen[name]])
    return seen


def chart(charts_shown: list[dict], title_part: str) -> dict:
    found = [c for c in charts_shown if title_part in c["title"]]
    assert found, f"no chart titled *{title_part}* in {[c['title'] for c in charts_shown]}"
    return found[0]


def series(c: dict, label: str) -> np.ndarray:
    assert label in c["labels"], f"no series {label!r} in {c['labels']}"
    return np.array([math.nan if v is None else v for v in c["data"][c["labels"].index(label)]], dtype=np.float64)


@pytest.fixture
def wide_tab(browser, app):  # noqa: F811  (pytest's fixtures, imported above)
    yield from open_tab(browser, app, VIEWPORT)


def test_every_braking_tab_shows_only_charts_with_data(wide_tab):
    tab = wide_tab
    record = tab.run()
    wait_until(
        lambda: tab.session.shown_record is record and tab.session.explanation is not None,
        timeout=30,
        what="the run's rollout explained",
    )
    seen = check_every_tab(tab, "braking")
    live = chart(seen["Live"], "mean q(detect) vs the PEM")
    assert "mean q(detect) over the visited states" in live["caption"]
    assert "PEM" in live["labels"] and np.isfinite(series(live, "PEM")).any()
    assert chart(seen["Explain"], "controller")["finite"][0] > 0
    weight = chart(seen["Explain"], "log w")
    assert weight["caption"].startswith("log w: the rollout's importance log-weight")  # what log w is, below it
    # the Compare tab shows one reference-state chart per kept run, no empty slot
    assert not any(c["title"].startswith("slot ") for c in seen["Compare"])


def test_a_cut_in_run_fills_live_and_explain_and_shows_every_car_and_the_errors_that_decided_its_failure(wide_tab):
    """The scenario choice runs the cut-in (five cars, missed and mislocated), one run for both halves. Live and
    Explain are at the braking scenario's level: q(detect) of the cut-in car per bin of its gap ahead beside the PEM's,
    what happened in words, the severity, the tracker against the truth and the ACC. Explain's most likely failure:
    the errors that decided it, each car's events step by step as the rollout holds them, and every car in the 3D
    scene where the rollout has it, coloured by whether it was detected; the playback moves both."""
    from pemviz.app import objects_view as OV

    tab = wide_tab
    s = tab.session
    tab.choose("scenario", "cut-in")
    # the scene's own default is its tilted proposal (its adaptive estimates are not right): N and method follow
    wait_until(
        lambda: s.choices["method"].value == "tilt" and s.fields["n_per_stage"].value == "7280",
        what="the cut-in's default method and N",
    )
    s.choices["method"].value = "adaptive"  # a few stages of 60 rollouts find failures in a few seconds
    # the stages alone (no retry, no plain Monte Carlo after them): their failures are what Live and Explain show
    record = tab.run({**TINY, "K": "3", "N": "60", "N_e": "60", "seed": "1", "plain fallback": "0"}, timeout=300)
    assert record.config.method == "adaptive" and record.config.scenario == "cut-in"
    assert record.most_likely_failure is not None
    # no exact answer: the final estimate stands beside the scenario's plain Monte Carlo reference
    assert record.exact_log_p is None and record.reference is not None
    wait_until(
        lambda: f"reference {record.reference.text()}: " in tab.page.inner_text("body"),
        what="the final estimate beside the Monte Carlo reference",
    )
    wait_until(
        lambda: s.objects_ex is not None and s.shown is record.most_likely_failure,
        timeout=60,
        what="the most likely failure explained",
    )
    ox = s.objects_ex
    st = ox.story
    assert st is not None and st.severity.failed
    # the story's failure step is the safety formula's first violation, as the counterfactuals replay it
    assert st.severity.failure_step == ox.counterfactuals.failure_step

    seen = check_every_tab(tab, "cut_in")

    # Live: q(detect) and p(detect) of the cut-in car per 1 m bin of its gap ahead, every stage drawn by a proposal
    live = chart(seen["Live"], "mean q(detect) vs the PEM")
    assert "mean q(detect) of car 0 (the cut-in car) over the visited states" in live["caption"]
    assert {"PEM", "stage 1", "final batch"} <= set(live["labels"]) and "pretraining" not in live["labels"]
    x = np.array(live["data"][0])
    np.testing.assert_allclose(x, (OBJECT_GAP_BINS_M[:-1] + OBJECT_GAP_BINS_M[1:]) / 2)
    pem, final = series(live, "PEM"), series(live, "final batch")
    assert np.isfinite(pem).sum() >= 10 and np.isfinite(final).sum() >= 10
    # the PEM's line is the mean p(detect) of car 0 over the final batch's states where the camera sees it
    stage = max(record.sampled)
    batch = record.sampled[stage].batch
    names = batch.object_names
    rows = batch.objects[:, :, VIEW_OBJECT, :]
    visible = rows[..., names.index("visible")] > 0.5
    p = expit(record.problem.target.detect_logit(rows[visible]))
    b = np.searchsorted(OBJECT_GAP_BINS_M, rows[visible][:, names.index("gap_m")], side="right") - 1
    full = [k for k in range(x.size) if np.sum(b == k) >= charts.MIN_BIN_STATES]
    assert len(full) >= 10
    np.testing.assert_allclose(pem[full], [p[b == k].mean() for k in full], rtol=1e-9)
    odds = chart(seen["Live"], "median log q(miss)/q(detect)")
    assert odds["finite"][0] > 0 and "of car 0" in odds["caption"]

    # Explain: what happened in words, the severity, the tracker against the truth, the ACC
    page = tab.page
    tab.tab("Explain")
    expect(page.get_by_text("What happened", exact=False)).to_be_visible(timeout=10_000)
    expect(page.get_by_text(st.severity.short, exact=False).first).to_be_visible()
    expect(page.get_by_text("minimum clearance", exact=False).first).to_be_visible()
    expect(page.get_by_text(st.sentences[1], exact=False).first).to_be_visible()  # the lane entry, in words
    explain = seen["Explain"]
    gap = chart(explain, "car 0's gap ahead")
    truth, track = series(gap, "truth"), series(gap, "tracker (confirmed track)")
    lo, hi = min(v for v in truth if np.isfinite(v)), max(v for v in truth if np.isfinite(v))
    inside = np.isfinite(ox.gap_ahead[:, 0]) & (ox.gap_ahead[:, 0] >= lo) & (ox.gap_ahead[:, 0] <= hi)
    np.testing.assert_allclose(truth[inside], ox.gap_ahead[inside, 0])
    assert np.isfinite(track).sum() > 10 and np.isfinite(series(gap, "measured (detected)")).any()
    lateral = chart(explain, "car 0's lateral offset from the ego's lane centre")
    np.testing.assert_allclose(series(lateral, "truth"), ox.lateral_m[:, 0], atol=1e-9)
    assert np.isfinite(series(lateral, "tracker (confirmed track)")).sum() > 10
    acc = chart(explain, "ACC acceleration")
    a = series(acc, "acceleration (m/s^2)")
    np.testing.assert_allclose(a, np.clip(st.acc.accel_mps2, np.nanmin(a), np.nanmax(a)))
    assert np.isfinite(series(acc, "follows car 0")).any()  # the ACC followed the cut-in car at some step
    assert a.min() < 0.0  # and braked
    # the braking scenario's strip charts are hidden, never shown empty
    assert not any("gap and speeds" in c["title"] or "log w" in c["title"] for c in explain)
    # the objects' view: the raster, the 3D scene's cars, the proposal bands, from above
    shown = s.shown
    t_steps, m = ox.detected.shape
    assert m == 5 and shown.crashed and shown.batch.detected.shape == (1, t_steps, m)
    cf = ox.counterfactuals
    assert cf is not None and cf.decisive and all(i.robustness >= 0.0 for i in cf.decisive)
    first = cf.decisive[0]
    tab.page.get_by_role("tab", name="Explain").click()
    expect(tab.page.get_by_text("Which errors decided it", exact=False)).to_be_visible(timeout=10_000)
    expect(tab.page.get_by_text(cf.summary(ox.names), exact=False)).to_be_visible()
    wait_until(
        lambda: tab.page.evaluate(OBJECTS_JS, m)["above"].startswith(f"From above at step {first.step}"),
        what="Explain at the first decisive error",
    )
    got = tab.page.evaluate(OBJECTS_JS, m)
    # the raster: one cell per car and step, green detected, orange missed, grey unseen, as the rollout has them
    want = np.where(ox.detected, OV.GREEN, np.where(ox.seen, OV.ORANGE, OV.UNSEEN))
    assert got["cells"] == want.T.reshape(-1).tolist()
    assert ox.detected.any() and (~ox.detected & ox.seen).any()  # both colours are drawn

    def check_cars(t: int, cars: list) -> None:
        decisive = {obj for obj, _ in ox.decisive_at(t)}
        for j, car in enumerate(cars):
            assert car["visible"], f"car {j} hidden at step {t}"
            np.testing.assert_allclose(car["position"][:2], [ox.ahead_m[t, j], -ox.lateral_m[t, j]], atol=1e-4)
            det, seen = bool(ox.detected[t, j]), bool(ox.seen[t, j])
            assert car["color"] == list(colours.DETECTED if det else colours.MISSED if seen else colours.IDLE)
            state = "detected" if det else ("missed" if seen else "unseen")
            assert car["label"] == f"car {j}: {state}" + (" (decisive)" if j in decisive else "")

    check_cars(first.step, got["cars"])
    # each object's proposal band: p(detect) of the PEM, recomputed here at the rollout's rows, and q(detect) of the
    # sampler as the trajectory kept it, drawn 0 at the band's foot and 1 at 17 px above it
    rows = shown.batch.objects[0]
    p_want = expit(record.problem.target.detect_logit(rows.reshape(-1, rows.shape[-1]))).reshape(t_steps, m)
    np.testing.assert_allclose(shown.object_p, p_want, atol=1e-12)
    assert shown.object_q.shape == (t_steps, m) and np.all((shown.object_q >= 0) & (shown.object_q <= 1))
    assert len(got["detect"]) == 2 * m
    for j in range(m):
        foot = 2 + (j + 1) * 22 - 3
        for k, values in enumerate((shown.object_p[:, j], shown.object_q[:, j])):
            ys = np.array([float(pt.split(",")[1]) for pt in got["detect"][2 * j + k].split()])
            np.testing.assert_allclose(ys, foot - 17 * values, atol=0.051)
    assert got["braking_lead"] is False  # the braking scene's lead is hidden
    # from above, a dashed box where the tracker places each tracked car drawn (in the view)
    t = first.step
    drawn = (
        (ox.ahead_m[t] >= OV.AHEAD_M[0]) & (ox.ahead_m[t] <= OV.AHEAD_M[1]) & (np.abs(ox.lateral_m[t]) <= OV.LATERAL_M)
    )
    assert got["tracks"] == int((np.isfinite(ox.tracked[t, :, 0]) & drawn).sum()) > 0
    # the playback moves the scene and the view from above to the failure
    s.step_slider.value = cf.failure_step
    wait_until(
        lambda: tab.page.evaluate(OBJECTS_JS, m)["above"].startswith(f"From above at step {cf.failure_step}"),
        what="Explain at the failure step",
    )
    wait_until(
        lambda: tab.page.evaluate(OBJECTS_JS, m)["cars"][0]["position"][0]
        == pytest.approx(ox.ahead_m[cf.failure_step, 0], abs=1e-4),
        what="the scene at the failure step",
    )
    check_cars(cf.failure_step, tab.page.evaluate(OBJECTS_JS, m)["cars"])


def test_the_cut_in_story_tells_a_hand_made_rollout_step_by_step():
    """Six steps of 0.1 s by hand: car 0 moves across from step 1, enters the ego's lane at step 2 (missed there, its
    track 2.5 m off laterally, outside the lane), the ACC follows it and brakes from the decision at step 3, contact
    at step 4 at 3.0 m/s closing speed (the row before: car 0 3.0 m/s slower than the ego)."""
    from pemviz.scenarios.cut_in.scenario import OBJECT_NAMES, OBSERVATION_NAMES
    from pemviz.scenarios.cut_in.story import cut_in_story

    t = 6
    obs = np.zeros((t, len(OBSERVATION_NAMES)))
    rows = np.zeros((t, 2, len(OBJECT_NAMES)))

    def o(name, values):
        obs[:, OBSERVATION_NAMES.index(name)] = values

    def r(name, values):
        rows[:, 0, OBJECT_NAMES.index(name)] = values

    o("safe_margin_m", 200.0)
    o("cut_in_recent", [0, 0, 1, 1, 1, 1])
    o("clearance_m", [200, 200, 5, 1, -0.5, -0.3])
    o("front_index", [-1, -1, 0, 0, 0, 0])
    o("followed_index", [-1, -1, -1, -1, 0, 0])  # the decision of the step before
    o("ego_accel_mps2", [0, 0, 0, 0, -6, -6])
    r("lateral_speed_mps", [0, -1, -1, -1, 0, 0])
    r("in_ego_lane", [0, 0, 1, 1, 1, 1])
    r("gap_m", [20, 15, 10, 5, -0.5, -0.3])
    r("rel_speed_mps", [-7.6, -7.6, -7.6, -3.0, -2.0, -1.0])
    r("tracked", [0, 1, 1, 1, 1, 1])
    r("loc_x", [4, 4, 1.5, 0.5, 0, 0])
    r("track_err_y_m", [0, 0, 2.5, 0, 0, 0])
    detected = np.ones((t, 2), bool)
    detected[2, 0] = False
    st = cut_in_story(obs, OBSERVATION_NAMES, rows, OBJECT_NAMES, detected, 0.1)
    sev = st.severity
    assert (sev.failure_step, sev.contact_step, sev.collision, sev.min_clearance_step) == (4, 4, True, 4)
    assert sev.closing_speed_mps == pytest.approx(3.0) and sev.min_clearance_m == -0.5
    assert (st.lane_change_step, st.lane_entry_step, st.first_detected_step, st.track_step) == (1, 2, 0, 1)
    assert (st.follow_step, st.brake_step, st.misses_after_entry, st.steps_after_entry) == (3, 3, 1, 1)
    assert st.outside_steps == 1 and st.worst_track_error_m == 2.5
    assert sev.short == (
        "contact at 3.0 m/s closing speed at 0.40 s · minimum clearance -0.50 m at 0.40 s (the " "boxes overlap)"
    )
    assert st.acc.accel_mps2.tolist() == [0, 0, 0, -6, -6] and st.acc.followed.tolist() == [-1, -1, -1, 0, 0]
    assert "Its box entered the ego's lane at 0.20 s (step 2), 10.0 m ahead." in st.text
    assert "it was missed at 1 of them" in st.text and "lateral error up to 2.50 m" in st.text
    assert "The ACC first followed it at 0.30 s, 0.10 s after it entered the lane." in st.text
    assert "Contact at 0.40 s (step 4) at a closing speed of 3.0 m/s" in st.text
