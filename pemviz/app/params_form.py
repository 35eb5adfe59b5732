"""The folders of the *Experiment* tab that change with a choice: *scenario parameters* and *method settings*
(:attr:`pemviz.methods.Method.settings`), each field with its own error line, rebuilt when the choice changes
(:class:`ChoiceFolder`); parsed by :func:`pemviz.app.form.parse_form`."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import viser

from pemviz.app.form import format_number, format_param, own_rows, param_key
from pemviz.app.html import field_error
from pemviz.config import ExperimentConfig
from pemviz.methods import method_or_none
from pemviz.scenarios.odd import is_odd
from pemviz.scenarios.parameters import KINDS, Parameter
from pemviz.scenarios.registry import get

Field = tuple[str, str, str, str]
"""One field of a folder: (name, label, first text, hint)."""


class ChoiceFolder:
    """The fields of one value of a choice inside a folder (:attr:`fields`, their error lines, :attr:`shown`),
    rebuilt by :meth:`show`; a subclass gives :meth:`fields_of`, :meth:`empty` (an empty line hides the folder) and
    :meth:`error_key`."""

    title = ""
    """The folder's label."""
    expanded = False
    """Whether the folder starts open."""

    def __init__(self, client: viser.ClientHandle, config0: ExperimentConfig) -> None:
        self.client, self.config0 = client, config0
        self.shown = ""
        """The value whose fields the folder holds (``""``: none built yet)."""
        self.fields: dict[str, viser.GuiTextHandle] = {}
        self.field_errors: dict[str, viser.GuiHtmlHandle] = {}
        self._extra: list[Any] = []
        self._lock = threading.Lock()
        self._on_change: Callable[[], None] = lambda: None

    def fields_of(self, value: str) -> list[Field]:
        raise NotImplementedError

    def empty(self, value: str) -> str:
        """The line the folder shows for a value without fields (``""``: the folder is hidden)."""
        return ""

    def error_key(self, name: str) -> str:
        """The key of the field ``name``'s error in :attr:`pemviz.app.form.FormResult.errors`."""
        return name

    def build(self, value: str, on_change: Callable[[], None]) -> None:
        """Add the folder to the container open in ``client.gui`` with the fields of ``value``; ``on_change`` is
        called after every edit of a field."""
        self._on_change = on_change
        self.folder = self.client.gui.add_folder(self.title, expand_by_default=self.expanded)
        self.show(value)

    def show(self, value: str) -> None:
        """Replace the fields by those of ``value``; nothing to do when they are already its."""
        with self._lock:
            if value == self.shown:
                return
            for handle in (*self.fields.values(), *self.field_errors.values(), *self._extra):
                handle.remove()
            self.fields, self.field_errors, self._extra = {}, {}, []
            made = self.fields_of(value)
            gui = self.client.gui
            with self.client.atomic(), self.folder:
                if not made and self.empty(value):
                    self._extra.append(gui.add_markdown(self.empty(value)))
                for name, text_label, text, text_hint in made:
                    field = gui.add_text(text_label, text, hint=text_hint)
                    field.on_update(lambda _: self._on_change())
                    self.fields[name] = field
                    self.field_errors[name] = gui.add_html("")
                self.folder.visible = bool(made or self.empty(value))
            self.shown = value

    def texts(self, value: str) -> dict[str, str]:
        """Name -> the text of each field when they are ``value``'s; ``{}`` while they are another's (the choice has
        just changed: its fields are on their way, at their first texts)."""
        with self._lock:
            if value != self.shown:
                return {}
            return {name: handle.value for name, handle in self.fields.items()}

    def show_errors(self, errors: dict[str, str]) -> None:
        """Show each field's error (``errors`` by :meth:`error_key`) under it; none: an empty line."""
        with self._lock:
            for name, handle in self.field_errors.items():
                handle.content = field_error(errors.get(self.error_key(name), ""))

    def handles(self) -> list[viser.GuiTextHandle]:
        """The text fields shown now."""
        with self._lock:
            return list(self.fields.values())


class ScenarioParamsForm(ChoiceFolder):
    """The folder *scenario parameters* (collapsed at first): a field per parameter of the chosen scenario, labelled
    with its name and unit, first showing the starting config's value or the scenario's default; only the fields
    changed from the defaults go into the run (:func:`pemviz.app.form.parse_params`)."""

    title = "scenario parameters"

    @property
    def scenario(self) -> str:
        """The scenario whose parameters the fields are (``""``: none built yet)."""
        return self.shown

    def fields_of(self, value: str) -> list[Field]:
        try:
            params = get(value).parameters()
        except KeyError:
            params = ()
        given = dict(self.config0.scenario_params) if value == self.config0.scenario else {}
        return [(p.name, label(p), text(p, given.get(p.name, p.default)), hint(p, value)) for p in params]

    def empty(self, value: str) -> str:
        return f"The {value} scenario has no parameters."

    def error_key(self, name: str) -> str:
        return param_key(name)


class MethodSettingsForm(ChoiceFolder):
    """The folder *method settings* (hidden for a method without settings): a field per row of the chosen method's
    :attr:`~pemviz.methods.Method.settings` (:func:`pemviz.app.form.own_rows`), labelled as its flag, first showing
    the starting config's value or the row's default; parsed by :func:`pemviz.app.form.parse_own`."""

    title = "method settings"
    expanded = True

    @property
    def method(self) -> str:
        """The method whose settings the fields are (``""``: none built yet)."""
        return self.shown

    def fields_of(self, value: str) -> list[Field]:
        record = method_or_none(value)
        kind = None if record is None else record.settings_class()
        if kind is None:
            return []
        given = self.config0.method_settings  # the starting config's, when they are this method's
        first = given if isinstance(given, kind) else kind()
        return [(s.name, s.label, format_number(s, getattr(first, s.name)), s.hint) for s in own_rows(value)]


def label(p: Parameter) -> str:
    """A field's label: the parameter's name, and its unit in brackets when it has one."""
    return f"{p.name} ({p.unit})" if p.unit else p.name


def text(p: Parameter, value: Any) -> str:
    """A field's first text: the value by the parameter's kind, or a distribution as typed (``~uniform(18, 22)``)."""
    return value if is_odd(value) else format_param(p, value)


def hint(p: Parameter, scenario: str = "") -> str:
    """A field's hint: what its value must be and the scenario's default."""
    unit = f" in {p.unit}" if p.unit else ""
    default = format_param(p, p.default)
    drawn = bool(scenario) and p.name in get(scenario).random_params
    odd = "; or ~uniform(a, b), ~normal(mu, sd), ~choice(a, b): drawn per rollout over an ODD" if drawn else ""
    return f"{p.name}: {KINDS[p.kind]}{unit} (default {default}){odd}; a changed value applies to the next run"
