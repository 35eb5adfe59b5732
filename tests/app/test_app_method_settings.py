"""The panel's folder *method settings*, without a browser: the *Experiment* tab built on a stand-in of viser's GUI
with the guide's method of one's own (``tests/estimators/user_method.py``: ``defensive-mc``, two settings) chosen shows
a field per setting, labelled and hinted by its row, parses a good and a bad value (one error, under its field) and
makes the config its flags make; another method hides the folder. The state method's own settings are its folder's
fields alike. The browser side is ``tests/app/test_app_plugin_scenario.py``."""

from __future__ import annotations

import contextlib
from types import SimpleNamespace

from pemviz.app.experiment_tab import ExperimentTab
from pemviz.app.form import run_label
from pemviz.app.html import field_error
from pemviz.cli import build_parser
from pemviz.commands.run import config_from_args
from pemviz.config import ExperimentConfig

from .test_app_params import FakeGui, FakeHandle


class Handle(FakeHandle):
    """A handle whose update callbacks are all kept (the method menu has two) and run by :meth:`pick`."""

    def on_update(self, callback) -> None:
        self.__dict__.setdefault("callbacks", []).append(callback)

    def pick(self, value) -> None:
        """What a choice in the browser does: the value set, then every callback."""
        self.value = value
        for callback in self.__dict__.get("callbacks", []):
            callback(None)


class Gui(FakeGui):
    """:class:`FakeGui` with dropdowns, each handle a :class:`Handle`."""

    def _make(self, **kw) -> Handle:
        self.made.append(Handle(**kw))
        return self.made[-1]

    def add_dropdown(self, label, options, initial_value=None, hint=None, disabled=False):
        return self._make(label=label, options=tuple(options), value=initial_value, hint=hint)


def test_the_chosen_methods_own_settings_are_fields_of_the_form(defensive_mc):
    client = SimpleNamespace(gui=Gui(), atomic=contextlib.nullcontext)
    tab = ExperimentTab(client, SimpleNamespace(config0=ExperimentConfig.of(), preset_name="default"))
    tab.build(lambda: None)
    own, method = tab.own, tab.choices["method"]
    assert own.folder.label == "method settings" and not own.folder.visible and own.fields == {}  # adaptive: none

    method.pick("defensive-mc")
    assert own.folder.visible and own.method == "defensive-mc"
    share, radius = own.fields["coin_share"], own.fields["coin_radius_m"]
    assert list(own.fields) == ["coin_share", "coin_radius_m"]
    assert (share.label, share.value, radius.label, radius.value) == ("eps", "0.3", "coin radius m", "")
    assert share.hint == "coin's share eps, a number in (0, 1): the share of each detection drawn by a fair coin"
    assert radius.hint.startswith("coin's radius in m, none or a number > 0: the coin mixes in only where")

    share.value, radius.value = " 0.2 ", "4"
    form = tab.read_form()
    assert form.ok, form.errors
    args = build_parser("run", full=False).parse_args(
        ["run", "--method", "defensive-mc", "--coin-share", "0.2", "--coin-radius", "4"]
    )
    assert form.config.method_settings == config_from_args(args).method_settings  # as the flags make it
    assert (form.config.method_settings.coin_share, form.config.method_settings.coin_radius_m) == (0.2, 4.0)
    assert list(form.config.flat().items())[-2:] == [("coin_share", 0.2), ("coin_radius_m", 4.0)]  # recorded keys
    assert run_label(1, form.config).endswith("method defensive-mc, eps 0.2, coin radius m 4")

    share.value = "1"
    bad = tab.read_form()
    tab.show_errors(bad)
    message = "eps: 1 is out of range; the coin's share eps must be a number in (0, 1)"
    assert bad.config is None and bad.errors == {"coin_share": message}  # one error, that field's
    assert own.field_errors["coin_share"].content == field_error(message) != field_error("")
    assert own.field_errors["coin_radius_m"].content == field_error("")

    method.pick("mc")  # another method: the folder hidden, its fields gone, the config without them
    assert not own.folder.visible and own.fields == {} and share.removed and radius.removed
    assert tab.read_form().config.method_settings is None
    method.pick("defensive-mc")  # back: its defaults again
    assert own.texts("defensive-mc") == {"coin_share": "0.3", "coin_radius_m": ""}
    assert tab.read_form().config.method_settings == defensive_mc.CoinSettings()


def test_the_state_methods_settings_are_the_fields_of_its_folder_as_a_plugins_are():
    tab = ExperimentTab(
        SimpleNamespace(gui=Gui(), atomic=contextlib.nullcontext),
        SimpleNamespace(config0=ExperimentConfig.of(), preset_name="default"),
    )
    tab.build(lambda: None)
    tab.choices["method"].pick("state")
    own = tab.own
    assert own.folder.visible and own.texts("state") == {
        "state_share": "0.1",
        "state_model": "glm",
        "state_fit_errors": "false",
    }
    own.fields["state_share"].value = "0.3"
    form = tab.read_form()
    assert form.ok, form.errors
    assert form.config.method_settings.state_share == 0.3 and form.config.flat()["state_share"] == 0.3
    assert run_label(1, form.config).endswith("method state, state share 0.3")


def test_the_fields_start_at_the_starting_configs_settings_of_that_method(defensive_mc):
    config0 = ExperimentConfig.of(method="defensive-mc", coin_share=0.2)  # a config the panel is opened with
    tab = ExperimentTab(SimpleNamespace(gui=Gui(), atomic=contextlib.nullcontext), SimpleNamespace(config0=config0))
    tab.app.preset_name = "default"
    tab.build(lambda: None)
    assert tab.own.folder.visible and tab.own.texts("defensive-mc") == {"coin_share": "0.2", "coin_radius_m": ""}
    assert tab.read_form().config.method_settings == config0.method_settings


def test_the_runs_and_compare_tables_list_a_methods_own_settings(defensive_mc):
    from pemviz.app.compare import compare_html, differing_settings
    from pemviz.app.form import default_settings, settings_of
    from pemviz.app.runs import PanelRun

    own = ExperimentConfig.of(method="defensive-mc", coin_share=0.2)
    other = ExperimentConfig.of(method="defensive-mc", coin_share=0.5, coin_radius_m=3.0)
    plain = ExperimentConfig.of()
    rows = {name: (label, values) for name, label, values in settings_of([own, other, plain])}
    assert rows["coin_share"][0] == "eps" and rows["coin_share"][1][:2] == [0.2, 0.5]
    assert rows["coin_radius_m"][1][:2] == [None, 3.0]
    assert default_settings(own)["coin_share"] == 0.3 and "coin_share" not in default_settings(plain)
    runs = [PanelRun(1, own), PanelRun(2, other), PanelRun(3, plain)]
    differ, same = differing_settings(runs)
    labels = [label for label, _ in differ]
    assert "eps" in labels and "coin radius m" in labels and "method" in labels
    assert same == len(rows) - len(differ)
    page = compare_html(runs)
    eps_row = page[page.index(">eps<") :].split("</tr>")[0]
    assert [cell.split("</td>")[0] for cell in eps_row.split("<td>")[1:]] == ["0.2", "0.5", "-"]
