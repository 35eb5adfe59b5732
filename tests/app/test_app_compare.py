"""The panel's *Compare* tab in headless Chromium: the chart of every kept run's final estimate (log10 scale, 95 %
interval, exact answer) and the table of only the settings that differ.

Uses the browser, server and tab helpers of ``tests/app/test_app.py``. With ``PEMVIZ_SCREENSHOTS=1`` the test also
writes ``assets/screenshots/panel_compare.png`` (the Compare tab after the two runs, 1400 x 900).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import pytest
from pemviz.app import compare
from pemviz.settings import SETTINGS

from .test_app import TINY, Tab, app, browser, expect, open_tab, wait_until  # noqa: F401  (app, browser: fixtures)

SCREENSHOT = Path(__file__).resolve().parents[2] / "assets" / "screenshots" / "panel_compare.png"
EXACT_P = 1.984e-15
"""The braking scenario's exact failure probability under the default PEM, to the digits the docs print."""


def drawn(values: list) -> list[tuple[int, float]]:
    """(index, value) of the points a uPlot series draws (not null / NaN)."""
    return [(i, v) for i, v in enumerate(values) if v is not None and v == v]


@pytest.fixture
def wide_tab(browser, app):  # noqa: F811  (pytest's fixtures, imported above)
    yield from open_tab(browser, app, {"width": 1400, "height": 900})


def test_compare_charts_each_runs_estimate_interval_and_exact_answer_and_lists_only_differing_settings(wide_tab):
    tab = wide_tab
    first = tab.run({**TINY, "alpha": "0.2"})
    second = tab.run({"alpha": "0.5"})
    runs = [first, second]
    for r in runs:
        assert r.final.estimate.n_failures > 0, f"{r.short_label} drew no failure: the chart has no estimate to draw"
    tab.tab("Compare")
    labels = [f"{r.short_label} mu_hat" for r in runs]
    wait_until(
        lambda: all(lab in tab.plot("log10 mu_hat of each kept run")["labels"] for lab in labels),
        what="both runs' estimates on the Compare chart",
    )
    chart = tab.plot("log10 mu_hat of each kept run")
    assert chart["title"] == compare.TITLE
    x = chart["x"]

    def series(label: str) -> list[tuple[int, float]]:
        assert label in chart["labels"], f"no series {label!r} in {chart['labels']}"
        return drawn(chart["data"][chart["labels"].index(label)])

    ln10 = math.log(10.0)
    for position, r in enumerate(runs, start=1):
        e = r.final.estimate
        # one point per run, at the run's own position, log10 of its mu_hat
        (i, value), *more = series(f"{r.short_label} mu_hat")
        assert not more and x[i] == position
        assert value == pytest.approx(math.log10(e.mu_hat), abs=1e-9)
        assert value == pytest.approx(e.log_mu_hat / ln10, abs=1e-9)
        # the 95 % interval: caps at log10 of its low and high ends, a vertical line between them at the run's position;
        # a run whose weights back no interval: its lower bound's cap and a line up to the chart's top
        if not e.interval_backed:
            bound = series(f"{r.short_label} 95 % lower bound")
            assert all(v == pytest.approx(e.log_lower_bound / ln10, abs=1e-9) for _, v in bound)
            up = [v for _, v in series(f"{r.short_label} no upper bound")]
            assert up[0] == pytest.approx(e.log_lower_bound / ln10, abs=1e-9) and up[1] > value
            assert up[1] == pytest.approx(chart["ymax"]) and f"{r.short_label} 95 % high" not in chart["labels"]
        else:
            lo, hi = e.log_ci
            assert math.isfinite(lo) and math.isfinite(hi)
            low, high = series(f"{r.short_label} 95 % low"), series(f"{r.short_label} 95 % high")
            cap = pytest.approx(
                [position - compare.CAP_HALF_WIDTH, position, position, position + compare.CAP_HALF_WIDTH]
            )
            assert [x[j] for j, _ in low] == cap and [x[j] for j, _ in high] == cap
            assert all(v == pytest.approx(lo / ln10, abs=1e-9) for _, v in low)
            assert all(v == pytest.approx(hi / ln10, abs=1e-9) for _, v in high)
            upright = series(f"{r.short_label} 95 % interval")
            assert [x[j] for j, _ in upright] == [position, position]
            assert [v for _, v in upright] == pytest.approx([lo / ln10, hi / ln10], abs=1e-9)
            assert low[0][1] <= value <= high[0][1]
        # the exact answer: a bar across the run's position at log10 of the problem's exact p
        assert r.exact_log_p is not None
        bar = series(f"{r.short_label} {compare.EXACT}")
        assert [x[j] for j, _ in bar] == pytest.approx(position + compare._OFFSETS)
        assert all(v == pytest.approx(r.exact_log_p / ln10, abs=1e-9) for _, v in bar)
        assert bar[0][1] == pytest.approx(math.log10(EXACT_P), abs=math.log10(1.0005))
    assert not any(lab.endswith(compare.REFERENCE) for lab in chart["labels"])  # braking knows its exact answer
    # explicit, finite ranges that hold every point, interval and bar
    assert (chart["xmin"], chart["xmax"]) == (0.5, 2.5)
    values = [v for lab in chart["labels"][1:] for _, v in series(lab)]
    assert chart["ymin"] < min(values) and chart["ymax"] >= max(values)  # a bound's line reaches the top: no upper end
    assert all(math.isfinite(chart[k]) for k in ("xmin", "xmax", "ymin", "ymax"))

    # the table: the result rows and only the settings that differ (alpha), the identical ones counted
    n_settings = len(SETTINGS)
    note = f"{n_settings - 1} identical settings hidden"
    expect(tab.page.get_by_text(note, exact=False)).to_be_visible(timeout=10_000)
    table = tab.page.locator(
        "xpath=//table[contains(@class, 'pemviz-table')]"
        "[following-sibling::div[contains(., 'identical settings hidden')]]"
    )
    expect(table).to_have_count(1)
    for row in ("mu_hat", "95 % interval", "failures", "ESS", "verdict", "alpha"):
        expect(table.locator("th", has_text=re.compile(f"^{re.escape(row)}$"))).to_have_count(1)
    for same in ("sigma", "seed", "K", "N", "metric", "PEM"):
        expect(table.locator("th", has_text=re.compile(f"^{re.escape(same)}$"))).to_have_count(0)
    alpha_row = table.locator("tr", has=tab.page.locator("th", has_text=re.compile("^alpha$")))
    expect(alpha_row.locator("td")).to_have_text(["0.2", "0.5"])
    mu_row = table.locator("tr", has=tab.page.locator("th", has_text=re.compile("^mu_hat$")))
    expect(mu_row.locator("td")).to_have_text([compare.result_cells(r)[0] for r in runs])

    if os.environ.get("PEMVIZ_SCREENSHOTS") == "1":
        tab.page.wait_for_function("() => document.fonts.ready.then(() => true)")
        partial = SCREENSHOT.with_name(SCREENSHOT.name + ".partial.png")
        tab.page.screenshot(path=str(partial))
        os.replace(partial, SCREENSHOT)
