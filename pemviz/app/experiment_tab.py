"""The *Experiment* tab of a :class:`pemviz.app.session.Session`: the next run's form, each field with its own error
line; a preset or scenario sets its fields, and the folders *scenario parameters* and *method settings*
(:mod:`pemviz.app.params_form`) hold the chosen scenario's parameters and method's settings."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import viser

from pemviz.app._viser_compat import resend_value, set_value
from pemviz.app.form import FIELDS_BY_KEY, NUMBERS, PANEL_ROWS, FormResult, format_number, panel_rows, parse_form
from pemviz.app.host import PanelHost
from pemviz.app.html import field_error
from pemviz.app.params_form import MethodSettingsForm, ScenarioParamsForm
from pemviz.config import ExperimentConfig, scene_defaults
from pemviz.methods import method_names
from pemviz.pem import shipped_pems
from pemviz.pem.recipes import DEFAULT_PEM_NAME
from pemviz.presets import PRESETS, preset_help
from pemviz.scenarios.registry import registered, scenario_hint
from pemviz.settings import SETTINGS, SIMULATORS


class ExperimentTab:
    """The *Experiment* tab: owns the form's fields (:attr:`fields`: text, :attr:`choices`: dropdowns, :attr:`preset`)
    and their error lines, the scenario's parameters (:attr:`params`) and the form as last checked (:attr:`parsed`);
    whoever builds it is told of each change."""

    def __init__(self, client: viser.ClientHandle, app: PanelHost) -> None:
        self.client, self.app = client, app
        self.parsed = FormResult(None, {})
        """The form as last checked (:meth:`show_errors`)."""
        self._on_change: Callable[[], None] = lambda: None
        self._on_scenario: Callable[[str], None] = lambda _: None
        self.params = ScenarioParamsForm(client, app.config0)
        """The folder of the chosen scenario's parameters."""
        self.own = MethodSettingsForm(client, app.config0)
        """The folder of the chosen method's own settings (hidden for a method without)."""

    def build(self, on_change: Callable[[], None], on_scenario: Callable[[str], None] | None = None) -> None:
        """Add the form to the tab open in ``client.gui``; ``on_change`` is called after every change to it,
        ``on_scenario`` (if given) with the scenario's name after each choice of a scenario."""
        self._on_change = on_change
        self._on_scenario = on_scenario or (lambda _: None)
        gui = self.client.gui
        c0 = self.app.config0
        simulators = SIMULATORS
        shipped = shipped_pems() or [DEFAULT_PEM_NAME]
        self._default_pem = DEFAULT_PEM_NAME if DEFAULT_PEM_NAME in shipped else shipped[0]
        pem_options = list(shipped) + (
            [c0.perception.pem] if c0.perception.pem and c0.perception.pem not in shipped else []
        )

        self.preset = gui.add_dropdown(
            "preset",
            tuple(PRESETS),
            initial_value=self.app.preset_name,
            hint=f"sampler settings: {preset_help(PRESETS)}",
        )
        self.choices: dict[str, Any] = {}
        self.fields: dict[str, viser.GuiTextHandle] = {}
        self.field_errors: dict[str, viser.GuiHtmlHandle] = {}

        def number(key: str) -> None:  # label, range and hint from the setting (pemviz.settings.SETTINGS)
            f = FIELDS_BY_KEY[key]
            self.fields[key] = gui.add_text(f.label, format_number(f, c0.value(key)), hint=f.hint)
            self.field_errors[key] = gui.add_html("")

        def dropdown(key: str, options: tuple[str, ...] | None = None, value: str | None = None, **kw: Any) -> None:
            s = SETTINGS[key]
            kw.setdefault("hint", s.hint)
            self.choices[key] = gui.add_dropdown(
                s.label, options or s.choices, initial_value=value or c0.value(key), **kw
            )

        def place(where: str) -> None:  # the rows that say they are shown here (pemviz.settings.Setting.panel)
            for row in panel_rows(SETTINGS.values(), where):
                if row.kind in NUMBERS:
                    number(row.name)
                else:
                    dropdown(row.name)

        dropdown("scenario", registered(), hint=scenario_hint())  # every registered scenario, plugins included
        dropdown("metric")
        place("main")
        dropdown("pem", tuple(pem_options), c0.perception.pem or self._default_pem)
        dropdown("sim", simulators, c0.sim if c0.sim in simulators else simulators[0], disabled=len(simulators) < 2)
        self.params.build(self.choices["scenario"].value, lambda: self._on_change())
        with gui.add_folder("advanced", expand_by_default=False):
            dropdown("method", method_names())  # every registered method, plugins included
            self.own.build(self.choices["method"].value, lambda: self._on_change())
            place("advanced")
        gui.add_markdown("Changes apply to the next run.")
        for handle in (*self.fields.values(), *self.choices.values()):
            handle.on_update(lambda _: self._on_change())
        self.preset.on_update(lambda _: self._apply_preset(self.preset.value))
        self.choices["scenario"].on_update(lambda _: self._apply_scene(self.choices["scenario"].value))
        self.choices["method"].on_update(lambda _: self._apply_method(self.choices["method"].value))

    def field_texts(self) -> dict[str, str]:
        return {key: handle.value for key, handle in self.fields.items()}

    def choice_values(self) -> dict[str, Any]:
        values = {key: handle.value for key, handle in self.choices.items()}
        if values.get("pem") == self._default_pem:
            values["pem"] = self.app.config0.perception.pem
        return values

    def read_form(self) -> FormResult:
        """Parse what the form holds now (every field, every error)."""
        name = self.preset.value
        base = self.app.config0 if name == self.app.preset_name else ExperimentConfig.of(**PRESETS[name])
        choices = self.choice_values()
        params, own = self.params.texts(choices["scenario"]), self.own.texts(choices["method"])
        return parse_form(self.field_texts(), choices, base, params, own)

    def show_errors(self, form: FormResult) -> None:
        """Keep ``form`` as :attr:`parsed` and show each field's error under it (none: an empty line)."""
        self.parsed = form
        for key, handle in self.field_errors.items():
            handle.content = field_error(form.errors.get(key, ""))
        self.params.show_errors(form.errors)
        self.own.show_errors(form.errors)

    def echo(self) -> None:
        """Send every field's value as the server has it back to the browser, so the form shows what runs (viser's
        client throttles GUI updates at 50 ms and can drop a value typed just before Run)."""
        with self.client.atomic():
            for handle in (
                *self.fields.values(),
                *self.choices.values(),
                self.preset,
                *self.params.handles(),
                *self.own.handles(),
            ):
                resend_value(handle)

    def _apply_scene(self, scenario: str) -> None:
        """Set the method and N to ``scenario``'s own defaults (:func:`pemviz.config.scene_defaults`) where it has
        them, and back to the preset's where it has none; show its parameters; tell whoever built the tab."""
        fields = scene_defaults(scenario)
        if not fields:
            preset = ExperimentConfig.of(**PRESETS.get(self.preset.value, {}))
            fields = {"method": preset.method, "n_per_stage": preset.n_per_stage}
        with self.client.atomic():
            self.choices["method"].value = fields["method"]
            set_value(self.fields["n_per_stage"], format_number(FIELDS_BY_KEY["n_per_stage"], fields["n_per_stage"]))
        self.params.show(scenario)
        self._on_change()
        self._on_scenario(scenario)

    def _apply_method(self, method: str) -> None:
        """Show ``method``'s own settings (none: the folder hidden)."""
        self.own.show(method)
        self._on_change()

    def _apply_preset(self, name: str) -> None:
        """Set the fields to ``name``'s settings (metric, seed, PEM, simulator and method stay)."""
        cfg = ExperimentConfig.of(**PRESETS.get(name, {}))
        with self.client.atomic():
            for f in PANEL_ROWS:
                if f.kind not in NUMBERS:
                    self.choices[f.name].value = cfg.value(f.name)
                elif f.name != "seed":
                    set_value(self.fields[f.name], format_number(f, cfg.value(f.name)))
        self._on_change()
