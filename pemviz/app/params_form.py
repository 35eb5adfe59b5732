"""The folder *scenario parameters* of the *Experiment* tab: one text field per parameter of the chosen scenario, each
with its own error line, rebuilt when the scenario changes. The texts are parsed by :func:`pemviz.app.form.parse_form`
(:func:`pemviz.app.form.parse_params`); only the fields changed from the scenario's defaults go into the run."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import viser

from pemviz.app.form import format_param, param_key
from pemviz.app.html import field_error
from pemviz.config import ExperimentConfig
from pemviz.scenarios.parameters import KINDS, Parameter
from pemviz.scenarios.odd import is_odd
from pemviz.scenarios.registry import get


class ScenarioParamsForm:
    """The fields of one scenario's parameters inside a folder (collapsed at first): :attr:`fields` (name -> text
    field) and their error lines, for the scenario :attr:`scenario`.

    A field's label is the parameter's name and unit (``cut_in_gap_m (m)``, e.g. a cut-in's); its first text is the
    panel's starting config's value when the config is of that scenario and sets it, else the scenario's default.

    Args:
        client: the viser client the folder draws into.
        config0: the panel's starting config (its ``scenario`` and ``scenario_params``).
    """

    def __init__(self, client: viser.ClientHandle, config0: ExperimentConfig) -> None:
        self.client, self.config0 = client, config0
        self.scenario = ""
        """The scenario whose parameters the fields are (``""``: none built yet)."""
        self.fields: dict[str, viser.GuiTextHandle] = {}
        self.field_errors: dict[str, viser.GuiHtmlHandle] = {}
        self._extra: list[Any] = []
        self._lock = threading.Lock()
        self._on_change: Callable[[], None] = lambda: None

    def build(self, scenario: str, on_change: Callable[[], None]) -> None:
        """Add the folder to the container open in ``client.gui`` with the fields of ``scenario``; ``on_change`` is
        called after every edit of a field."""
        self._on_change = on_change
        self.folder = self.client.gui.add_folder("scenario parameters", expand_by_default=False)
        self.show(scenario)

    def show(self, scenario: str) -> None:
        """Replace the fields by those of ``scenario`` (its defaults, or the starting config's values); nothing to do
        when they are already its. A scenario without parameters shows one line saying so."""
        with self._lock:
            if scenario == self.scenario:
                return
            for handle in (*self.fields.values(), *self.field_errors.values(), *self._extra):
                handle.remove()
            self.fields, self.field_errors, self._extra = {}, {}, []
            try:
                params = get(scenario).parameters()
            except KeyError:
                params = ()
            given = dict(self.config0.scenario_params) if scenario == self.config0.scenario else {}
            gui = self.client.gui
            with self.client.atomic(), self.folder:
                if not params:
                    self._extra.append(gui.add_markdown(f"The {scenario} scenario has no parameters."))
                for p in params:
                    value = given.get(p.name, p.default)
                    text = value if is_odd(value) else format_param(p, value)
                    field = gui.add_text(label(p), text, hint=hint(p, scenario))
                    field.on_update(lambda _: self._on_change())
                    self.fields[p.name] = field
                    self.field_errors[p.name] = gui.add_html("")
            self.scenario = scenario

    def texts(self, scenario: str) -> dict[str, str]:
        """Name -> the text of each field when they are ``scenario``'s; ``{}`` while they are another's (the scenario
        has just changed: its fields are on their way, at their defaults)."""
        with self._lock:
            if scenario != self.scenario:
                return {}
            return {name: handle.value for name, handle in self.fields.items()}

    def show_errors(self, errors: dict[str, str]) -> None:
        """Show each field's error (``errors`` by :func:`pemviz.app.form.param_key`) under it; none: an empty line."""
        with self._lock:
            for name, handle in self.field_errors.items():
                handle.content = field_error(errors.get(param_key(name), ""))

    def handles(self) -> list[viser.GuiTextHandle]:
        """The text fields shown now."""
        with self._lock:
            return list(self.fields.values())


def label(p: Parameter) -> str:
    """A field's label: the parameter's name, and its unit in brackets when it has one."""
    return f"{p.name} ({p.unit})" if p.unit else p.name


def hint(p: Parameter, scenario: str = "") -> str:
    """A field's hint: what its value must be and the scenario's default."""
    unit = f" in {p.unit}" if p.unit else ""
    default = format_param(p, p.default)
    drawn = bool(scenario) and p.name in get(scenario).random_params
    odd = "; or ~uniform(a, b), ~normal(mu, sd), ~choice(a, b): drawn per rollout over an ODD" if drawn else ""
    return f"{p.name}: {KINDS[p.kind]}{unit} (default {default}){odd}; a changed value applies to the next run"
