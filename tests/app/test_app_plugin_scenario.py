"""The panel runs a scenario of one's own: the user guide's ``my_car_scenario`` module, imported (so registered)
before a browser tab opens, is in the scenario choice, and a run of it stands beside its exact answer, in headless
Chromium. Uses the browser, server and tab helpers of ``tests/app/test_app.py``."""

from __future__ import annotations

import math
import sys

import pytest

from conftest import PLUGIN_SCENARIO_HEADING as HEADING
from conftest import doc_python_block

from .test_app import TINY, app, browser, expect, open_tab, wait_until  # noqa: F401  (app, browser: fixtures)


@pytest.fixture
def my_car(tmp_path, monkeypatch):
    """The guide's module saved by a user and imported: ``my-car`` registered for this test only."""
    (tmp_path / "my_car_scenario.py").write_text(doc_python_block("own-simulator.md", HEADING))
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("my_car_scenario", None)
    from pemviz.scenarios import registry

    __import__("my_car_scenario")
    yield
    registry.unregister("my-car")
    sys.modules.pop("my_car_scenario", None)


def test_the_panel_lists_and_runs_a_registered_scenario_of_ones_own(my_car, browser, app):  # noqa: F811
    for tab in open_tab(browser, app):
        assert "my-car" in tab.session.choices["scenario"].options
        tab.choose("scenario", "my-car")
        # the stages alone, no retry and no plain Monte Carlo after them: the choice, the run and the exact answer
        # beside its estimate are what this test checks, not the estimate (2.9e-5 is rarely hit in 170 rollouts)
        record = tab.run({**TINY, "plain fallback": "0"}, timeout=120)
        assert record.config.scenario == "my-car" and record.config.fallback.plain_fallback == 0
        assert math.exp(record.exact_log_p) == pytest.approx(2.8576e-5, rel=1e-3)
        wait_until(
            lambda: ("exact answer 2.8576e-05" in tab.page.inner_text("body")),  # noqa: B023 (called within the iteration)
            what="the final estimate beside the scenario's exact answer",
        )
        scene = tab.session.scene
        wait_until(
            lambda: ("the my-car scenario draws no scene" in scene.scene_html.content),  # noqa: B023 (called within the iteration)
            timeout=60,
            what="the 3D view saying the scenario draws no scene (no braking road for it)",
        )
        assert not scene.object_box.visible and not scene.ego_box.visible
        # Explain says so too (it went on saying "run 1 is going: its rollouts appear in the Rollouts tab")
        assert "the my-car scenario draws no scene" in scene.explain.explain_html.content


def test_the_panel_lists_and_runs_a_registered_method_of_ones_own(defensive_mc, browser, app):  # noqa: F811
    for tab in open_tab(browser, app):
        assert "defensive-mc" in tab.session.choices["method"].options
        tab.open_advanced()  # the menu sits in the folded "advanced" folder; the method's settings below it
        tab.choose("method", "defensive-mc")
        expect(tab.field("eps")).to_have_value("0.3")
        expect(tab.field("coin radius m")).to_have_value("")
        record = tab.run({"N": "100", "eps": "0.2"}, timeout=120)
        assert record.config.method == "defensive-mc" and record.config.n_per_stage == 100
        assert record.config.flat()["coin_share"] == 0.2 and "eps 0.2" in record.label  # its own setting, run
        tab.choose("method", "mc")  # another method: the fields go
        expect(tab.field("eps")).to_have_count(0)
        wait_until(
            lambda: f"Final estimate of {record.short_label}" in tab.page.inner_text("body"),  # noqa: B023
            what="the method's final estimate in the panel",
        )
