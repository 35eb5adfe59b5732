"""``pemviz serve`` end to end in headless Chromium, what the panel shows of a run: the scene and the strip charts
follow the newest run, the final estimate with its interval and verdict, the scene's colours and framing at a failure,
and *Live*, *Explain* and *Rollouts* after a default run. Uses the browser, server and tab helpers of
``tests/app/test_app.py`` (the form, the runs and Stop are tested there); every wait is on a condition.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
from pemviz.scenarios.braking.panel import explain
from pemviz.sinks import colours

from .test_app import TINY, Tab, app, browser, expect, open_tab, shown_at, tab, wait_until  # noqa: F401  (fixtures)


class Crashed:
    """A tab at 1400 x 900 (``tab``), the scene it drew before any run (``idle``: :meth:`Tab.scene`), and its finished
    run of three stages (``record``) whose most likely failure is shown: tests that only read them, or move the step
    slider, share one run."""

    def __init__(self, tab: Tab) -> None:  # noqa: F811
        self.tab = tab
        self.idle = tab.scene()
        self.record = tab.run({**TINY, "K": "3"})


@pytest.fixture(scope="module")
def crashed(browser, app):  # noqa: F811
    for t in open_tab(browser, app, {"width": 1400, "height": 900}):
        yield Crashed(t)


# 2 ------------------------------------------------------------------------------------------------
def test_the_scene_and_strip_chart_follow_the_newest_run_and_name_it(tab, app):  # noqa: F811
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


# 6 ------------------------------------------------------------------------------------------------
def test_the_final_estimate_comes_with_its_interval_verdict_and_a_hint_when_nothing_failed(crashed, tab):  # noqa: F811
    record = crashed.record
    e = record.final.estimate
    text = crashed.tab.page.inner_text("body")
    assert f"failures {e.n_failures}/{e.n}" in text and "ESS" in text and "k-hat" in text
    if hasattr(e, "log_ci"):
        assert "95 % interval" in text and e.verdict in text and e.reason in text
    if record.exact_log_p is not None:
        assert "exact answer" in text
    # the stages backed no interval and ran once more (a retry): two final batches, each named once in Live's legend
    finals = [st.stage for st in record.stages if st.kind == "final"]
    assert len(finals) == 2, f"K 3 of the tiny run is retried: final batches at stages {finals}"
    for title in ("mean q(detect) vs the PEM", "log q(miss)/q(detect)"):
        names = crashed.tab.plot(title)["labels"]
        assert len(set(names)) == len(names), names
        assert {f"final batch (stage {k})" for k in finals} <= set(names), names
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
def test_scene_colours_are_the_recordings_idle_ego_is_grey_and_the_cars_never_overlap(crashed, app):  # noqa: F811
    from pemviz.sinks import rerun_views as recording  # the recording's colours

    tab, record = crashed.tab, crashed.record  # noqa: F811
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


# 10 -----------------------------------------------------------------------------------------------
def test_live_shows_what_the_sampler_did_and_explain_says_why_and_how_bad(tab, app):  # noqa: F811
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


# 12 -----------------------------------------------------------------------------------------------
def test_the_scene_frames_both_cars_and_shows_the_gap_the_breach_and_the_detections_so_far(crashed, app):  # noqa: F811
    """At 1400 x 900, at the step a failure crosses the 2 m line: the canvas lies between the panels and both cars
    project inside it; the ruler spans the gap and says it in metres; a red gate stands where the ego's camera crossed
    the line; the trail holds one square per step so far, green where detected and orange where missed; every label
    beside the road lies outside both cars on screen, on the side its text runs to."""
    tab, record = crashed.tab, crashed.record  # noqa: F811
    tab.draw_scene()  # the canvas' place on the page is checked
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
