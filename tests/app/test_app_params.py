"""The panel's scenario parameters: the form's parsing (:func:`pemviz.app.form.parse_params` through
:func:`pemviz.app.form.parse_form`: a changed field goes into the run's ``scenario_params``, a bad one gives that
field's error, unchanged ones give none), the run's label, and in headless Chromium the folder *scenario
parameters* of the *Experiment* tab (rebuilt with the scenario, a changed value in the run's config, a bad one on its
field with Run disabled).

The browser test uses the browser, server and tab helpers of ``tests/app/test_app.py``; with ``PEMVIZ_SCREENSHOTS=1`` it
also writes ``assets/screenshots/panel_params.png``.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from types import SimpleNamespace

import pytest
from pemviz.app.form import format_param, param_key, parse_form, parse_params, run_label
from pemviz.app.params_form import ScenarioParamsForm, label
from pemviz.config import ExperimentConfig
from pemviz.scenarios.registry import get

CUT_IN = {"scenario": "cut-in", "sim": "batched"}
"""The dropdowns of a cut-in run."""


def default_texts(scenario: str) -> dict[str, str]:
    """The texts the folder shows at first for ``scenario``: every parameter at its default."""
    return {p.name: format_param(p, p.default) for p in get(scenario).parameters()}


def test_a_changed_parameter_goes_into_the_runs_scenario_params_and_its_label():
    form = parse_form({}, CUT_IN, params={**default_texts("cut-in"), "cut_in_gap_m": " 19.5 "})
    assert form.ok and form.errors == {}
    assert form.config.scenario_params == (("cut_in_gap_m", 19.5),)
    assert run_label(3, form.config) == "run 3 · classic, scenario cut-in, cut_in_gap_m=19.5"
    # an int and a bool by their kinds, in the order of the fields
    both = parse_form(
        {}, {"scenario": "braking"}, params={**default_texts("braking"), "n_steps": "80", "latched_brake": "yes"}
    )
    assert both.config.scenario_params == (("n_steps", 80), ("latched_brake", True))
    assert run_label(1, both.config).endswith("n_steps=80, latched_brake=true")


@pytest.mark.parametrize(
    "text, message",
    [
        ("abc", "cut_in_gap_m='abc' is not a number: cut_in_gap_m takes a number in m (default 20.0)"),
        ("-5", "the cut-in scenario: cut_in_gap_m must be finite and >= 0, got -5.0"),
        ("", "cut_in_gap_m='' is not a number: cut_in_gap_m takes a number in m (default 20.0)"),
    ],
    ids=["not-a-number", "out-of-range", "empty"],
)
def test_a_bad_value_is_an_error_of_its_field_only(text, message):
    form = parse_form({"n_stages": "0"}, CUT_IN, params={**default_texts("cut-in"), "cut_in_gap_m": text})
    assert not form.ok
    assert form.errors[param_key("cut_in_gap_m")] == message
    assert set(form.errors) == {param_key("cut_in_gap_m"), "n_stages"}  # every error at once, one per field
    assert "\n" not in message


def test_the_plain_monte_carlo_fallback_is_a_field_of_its_own():
    # default 500; 0 turns it off; a negative number is that field's error alone
    assert parse_form({}, {"scenario": "crowd"}).config.fallback.plain_fallback == 500
    off = parse_form({"plain_fallback": "0"}, {"scenario": "crowd"})
    assert off.config.fallback.plain_fallback == 0
    assert run_label(1, off.config) == "run 1 · classic, scenario crowd, plain fallback 0"
    bad = parse_form({"plain_fallback": "-3"}, {"scenario": "crowd"})
    assert list(bad.errors) == ["plain_fallback"] and "the plain Monte Carlo fallback" in bad.errors["plain_fallback"]
    # the retry before it: default 4, 0 off, a fraction that field's error alone
    assert parse_form({}, {"scenario": "crowd"}).config.fallback.retry_factor == 4
    assert parse_form({"retry_factor": "0"}, {"scenario": "crowd"}).config.fallback.retry_factor == 0
    bad = parse_form({"retry_factor": "2.5"}, {"scenario": "crowd"})
    assert list(bad.errors) == ["retry_factor"] and "the retry's factor on N" in bad.errors["retry_factor"]


def test_unchanged_fields_give_the_same_config_as_a_form_without_parameters():
    for scenario in ("braking", "cut-in", "cut-in-rare"):
        choices = {"scenario": scenario, "sim": "batched"}
        texts = default_texts(scenario)
        assert texts and parse_params(scenario, texts) == ((), {})
        assert parse_params(scenario, {**texts, "dt_s": f"{get(scenario).parameters()[0].default:.3e}"}) == ((), {})
        with_params = parse_form({}, choices, params=texts)
        assert with_params.config == parse_form({}, choices).config
        assert with_params.config.scenario_params == ()
    assert parse_form({}, {}, params={}).config == ExperimentConfig.of()


def test_the_fields_replace_the_starting_configs_parameters_and_only_the_panel_passes_them():
    base = ExperimentConfig.of(**CUT_IN, scenario_params=(("cut_in_gap_m", 19.5),))
    assert parse_form({}, {}, base).config.scenario_params == base.scenario_params  # no fields: the base's are kept
    assert parse_form({}, {}, base, params=default_texts("cut-in")).config.scenario_params == ()
    # another scenario chosen: its own (unchanged) parameters, not the base's
    assert parse_form({}, {"scenario": "braking"}, base, params=default_texts("braking")).config.scenario_params == ()


def test_a_field_is_labelled_with_its_name_and_unit_and_shows_its_value_by_kind():
    p = {q.name: q for q in get("braking").parameters()}
    assert [label(p[n]) for n in ("gap0_m", "kp", "n_steps")] == ["gap0_m (m)", "kp", "n_steps (steps)"]
    assert [format_param(p[n], p[n].default) for n in ("gap0_m", "n_steps", "latched_brake")] == [
        "12.2932",
        "100",
        "false",
    ]
    assert parse_params("no-such-scenario", {"x": "1"}) == ((), {})
    assert parse_params("braking", {"nope": "1"})[1] == {
        param_key("nope"): "'nope' is not a parameter of the " "braking scenario"
    }


class FakeHandle(SimpleNamespace):
    """A GUI handle as the folder uses it: a label, a value, removal and an update callback."""

    removed = False

    def remove(self) -> None:
        assert not self.removed
        self.removed = True

    def on_update(self, callback) -> None:
        self.callback = callback

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        pass


class FakeGui:
    """The part of viser's ``client.gui`` the folder calls, keeping every handle made."""

    def __init__(self) -> None:
        self.made: list[FakeHandle] = []

    def _make(self, **kw) -> FakeHandle:
        self.made.append(FakeHandle(**kw))
        return self.made[-1]

    def add_folder(self, label, expand_by_default=True):
        return self._make(label=label, expanded=expand_by_default)

    def add_text(self, label, initial_value, hint=None):
        return self._make(label=label, value=initial_value, hint=hint)

    def add_html(self, content):
        return self._make(content=content)

    def add_markdown(self, content):
        return self._make(content=content)


def test_the_folder_starts_collapsed_at_the_starting_configs_values_and_rebuilds_with_the_scenario():
    gui = FakeGui()
    client = SimpleNamespace(gui=gui, atomic=contextlib.nullcontext)
    config0 = ExperimentConfig.of(**CUT_IN, scenario_params=(("cut_in_gap_m", 19.5),))
    changes = []
    form = ScenarioParamsForm(client, config0)
    form.build("cut-in", lambda: changes.append(1))
    assert (form.folder.label, form.folder.expanded) == ("scenario parameters", False)
    first = dict(form.fields)
    assert form.texts("cut-in") == {**default_texts("cut-in"), "cut_in_gap_m": "19.5"}
    assert first["cut_in_gap_m"].label == "cut_in_gap_m (m)" and "default 20.0" in first["cut_in_gap_m"].hint
    first["n_objects"].callback(None)
    assert changes == [1]
    assert form.texts("braking") == {}  # another scenario's fields are not read as its own
    form.show("cut-in-rare")  # the same names, the other scenario's defaults: the starting config is a cut-in's
    assert all(h.removed for h in first.values()) and form.texts("cut-in-rare") == default_texts("cut-in-rare")
    form.show_errors({param_key("n_objects"): "n_objects: bad"})
    assert "n_objects: bad" in form.field_errors["n_objects"].content and form.field_errors["dt_s"].content == ""
    form.show("toy")
    assert set(form.fields) == {p.name for p in get("toy").parameters()}


# -- in the browser ---------------------------------------------------------------------------------
try:  # the browser test needs playwright and chromium (test_app skips without them); the tests above do not
    from .test_app import app, browser, expect, open_tab, wait_until  # noqa: F401  (app, browser: fixtures)

    NO_BROWSER = ""
except pytest.skip.Exception as exc:
    NO_BROWSER = str(exc) or "no browser"

SHOT = Path(
    os.environ.get(
        "PEMVIZ_PARAMS_SHOT", Path(__file__).resolve().parents[2] / "assets" / "screenshots" / "panel_params.png"
    )
)


@pytest.fixture
def tab(browser, app):  # noqa: F811  (pytest's fixtures, imported above)
    yield from open_tab(browser, app, {"width": 1400, "height": 1300})


@pytest.mark.skipif(bool(NO_BROWSER), reason=NO_BROWSER)
def test_the_folder_sets_the_chosen_scenarios_parameters_for_the_next_run(tab):
    s, page = tab.session, tab.page
    params = s.form.params
    assert params.scenario == "braking" and "gap0_m" in params.fields
    tab.choose("scenario", "cut-in")
    wait_until(lambda: params.scenario == "cut-in", what="the cut-in's parameter fields")
    gap = tab.open_folder("scenario parameters", "cut_in_gap_m (m)")
    assert gap.input_value() == "20.0" and "gap0_m" not in params.fields

    for bad, message in (("abc", "is not a number"), ("-5", "must be finite and >= 0")):
        gap.fill(bad)
        gap.press("Tab")
        expect(page.get_by_text(message)).to_be_visible(timeout=10_000)
        expect(tab.button("Run")).to_be_disabled()
    gap.fill("19.5")
    gap.press("Tab")
    wait_until(
        lambda: params.fields["cut_in_gap_m"].value == "19.5" and s.form.parsed.ok, what="19.5 to reach the server"
    )
    expect(tab.button("Run")).to_be_enabled()
    if os.environ.get("PEMVIZ_SCREENSHOTS") == "1" or "PEMVIZ_PARAMS_SHOT" in os.environ:
        page.wait_for_function("() => document.fonts.ready.then(() => true)")
        SHOT.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SHOT))
    tab.button("Run").click()
    wait_until(lambda: s.record is not None, what="the run to start")
    s.stop_run()  # its config is what this test checks, not its estimate
    assert s.record.config.scenario_params == (("cut_in_gap_m", 19.5),)
    assert "cut_in_gap_m=19.5" in s.record.label
