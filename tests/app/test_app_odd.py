"""The panel over an operating design domain: a scenario parameter given a distribution in the *scenario parameters*
folder (:func:`pemviz.app.form.parse_params`), and the *ODD* tab (:mod:`pemviz.app.odd_tab`) after such a run, in
headless Chromium: the chart of log10 p(failure | bin) per parameter with its interval's ends, the table of bins and
the region that carries most of p_ODD, against the run's own map and the toy's closed form.

Uses the browser, server and tab helpers of ``tests/app/test_app.py``. With ``PEMVIZ_SCREENSHOTS=1`` the test also
writes ``assets/screenshots/panel_odd.png`` (the ODD tab after a toy run over ``braking~choice(5, 6, 7)``).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
from pemviz.app.form import param_key, parse_params
from pemviz.app.odd_tab import bin_points, odd_table_html
from pemviz.core.estimate import estimate
from pemviz.core.odd import ODD, MapBin, OddMap, parse_distribution

SCREENSHOT = Path(__file__).resolve().parents[2] / "assets" / "screenshots" / "panel_odd.png"
TOY_EXACT = {5: 1e-3, 6: 1e-4, 7: 1e-5}
"""The toy's closed form at total 10, safe 3 and each braking distance: p = 0.1 ** (braking - safe - 1)."""


def test_a_distribution_typed_into_a_parameter_field_draws_it_per_rollout():
    pairs, errors = parse_params("cut-in", {"cut_in_gap_m": " ~uniform(19.5, 21.5) "})
    assert (pairs, errors) == ((("cut_in_gap_m", "~uniform(19.5, 21.5)"),), {})
    _, errors = parse_params("cut-in", {"cut_in_speed_mps": "~uniform(15, 17)"})
    assert (
        "cannot draw cut_in_speed_mps per rollout (its parameters that can be drawn: cut_in_gap_m)"
        in (errors[param_key("cut_in_speed_mps")])
    )
    _, errors = parse_params("cut-in", {"cut_in_gap_m": "~uniform(-3, 2)"})
    assert "its value -3 is out of the parameter's range" in errors[param_key("cut_in_gap_m")]
    _, errors = parse_params("cut-in", {"cut_in_gap_m": "~gamma(2, 3)"})
    assert "gamma" in errors[param_key("cut_in_gap_m")] and "\n" not in errors[param_key("cut_in_gap_m")]


def _hand_map() -> OddMap:
    """Two bins of one parameter: 3 failures of 100 rollouts in the first (weights 1 / P(bin) = 2), none in the
    second: p(failure | bin 1) = 2 * 3 / 100 = 0.06."""
    odd = ODD((("gap", parse_distribution("uniform(10, 12)")),))
    failed = np.zeros(100, bool)
    failed[:3] = True
    lw = np.where(np.arange(100) < 50, math.log(2.0), -np.inf)
    first = estimate(lw, failed, np.zeros(100))
    second = estimate(np.where(np.arange(100) >= 50, math.log(2.0), -np.inf), np.zeros(100, bool), np.zeros(100))
    return OddMap(odd, 100, (MapBin("gap", 10, 11, 0.5, first, 1.0), MapBin("gap", 11, 12, 0.5, second, 0.0)))


def test_the_chart_points_and_table_are_the_maps_own_numbers():
    m = _hand_map()
    x, p, lo, hi = bin_points(list(m.bins))
    assert x.tolist() == [10.5, 11.5]
    assert p[0] == pytest.approx(math.log10(0.06)) and math.isnan(p[1])  # no failure: no point
    assert lo[0] == pytest.approx(m.bins[0].estimate.shown_log_ci[0] / math.log(10))
    text = odd_table_html(m)
    assert "Most of p_ODD: <b>gap in [10, 11)</b> (100 % of it, P(bin) 0.50)" in text
    assert "6.000e-02" in text and "no failure" in text


# -- in the browser ---------------------------------------------------------------------------------
try:  # the browser test needs playwright and chromium (test_app skips without them); the tests above do not
    from .test_app import app, browser, expect, open_tab, wait_until  # noqa: F401  (app, browser: fixtures)

    NO_BROWSER = ""
except pytest.skip.Exception as exc:
    NO_BROWSER = str(exc) or "no browser"


@pytest.fixture
def tab(browser, app):  # noqa: F811  (pytest's fixtures, imported above)
    yield from open_tab(browser, app, {"width": 1400, "height": 1000})


@pytest.mark.skipif(bool(NO_BROWSER), reason=NO_BROWSER)
def test_the_odd_tab_maps_a_run_over_a_distribution_chosen_in_the_form(tab):
    s, page = tab.session, tab.page
    tab.tab("ODD")
    expect(page.get_by_text("No operating design domain in this run.")).to_be_visible(timeout=10_000)
    tab.tab("Experiment")
    tab.choose("scenario", "toy")
    wait_until(lambda: s.form.params.scenario == "toy", what="the toy's parameter fields")
    tab.open_folder("scenario parameters", "total")
    for name, value in (("total", "10"), ("safe", "3"), ("braking", "~choice(5, 6, 7)")):
        box = tab.field(name)
        box.wait_for()
        box.fill(value)
        box.press("Tab")
        wait_until(lambda n=name, v=value: s.form.params.fields[n].value == v, what=f"{name} = {value!r}")
    record = tab.run({"N": "2000"}, timeout=120)
    assert dict(record.config.scenario_params)["braking"] == "~choice(5, 6, 7)"
    m = record.final.odd_map
    assert m is not None and [b.label for b in m.bins] == ["braking = 5", "braking = 6", "braking = 7"]
    tab.tab("ODD")
    title = "log10 p(failure | braking bin)"
    wait_until(lambda: any(title in p["title"] for p in tab.uplots()), what="the ODD chart")
    chart = tab.plot(title)
    assert chart["x"] == [5.0, 6.0, 7.0]
    shown = chart["data"][chart["labels"].index("p")]
    for k, b in enumerate(m.bins):  # the run's own bins, and each within a factor 3 of the closed form
        assert shown[k] == pytest.approx(b.estimate.log_mu_hat / math.log(10), abs=1e-9)
        assert abs(shown[k] - math.log10(TOY_EXACT[k + 5])) < math.log10(3)
    expect(page.get_by_text("Most of p_ODD:")).to_be_visible(timeout=10_000)
    expect(page.get_by_role("cell", name="braking = 5", exact=True)).to_be_visible()
    if os.environ.get("PEMVIZ_SCREENSHOTS") == "1":
        page.wait_for_function("() => document.fonts.ready.then(() => true)")
        SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SCREENSHOT))


def test_the_heat_map_of_a_pair_shows_each_cell_shaded_by_its_p_and_names_the_largest_share():
    from pemviz.app.odd_tab import pair_html
    from pemviz.core.odd_pair import pair_map

    odd = ODD((("gap", parse_distribution("choice(10, 11)")), ("speed", parse_distribution("choice(8, 9)"))))
    values = np.array([[10, 8], [10, 9], [11, 8], [11, 9]] * 10, dtype=np.float64)
    failed = np.zeros(40, bool)
    failed[[0, 4, 8, 1]] = True  # cell (gap 10, speed 8): 3 of 10; (gap 10, speed 9): 1 of 10; the others none
    pair = pair_map(odd, values, np.zeros(40), failed, np.zeros(40))
    assert pair is not None
    page = pair_html(pair)
    assert "rows speed, columns gap" in page and "3.0e-01" in page and "1.0e-01" in page and page.count(">-<") == 2
    assert "Most of p_ODD in the pair: <b>gap in [9.5, 10.5) and speed in [7.5, 8.5)</b> (75 % of it)" in page
    assert "rgba(214, 64, 43, 1)" in page and "rgba(214, 64, 43, 0.15)" in page  # largest dark, least light
