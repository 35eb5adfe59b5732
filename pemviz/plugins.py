"""What the scenario and method registries share: a reference to an object by its import path, resolved when first
used (as Gymnasium's ``entry_point``), and plugins loaded from modules an environment variable names and from entry
points, each failure one line naming the plugin."""

from __future__ import annotations

import functools
import importlib
import os
import sys
from collections.abc import Callable
from typing import Any

Ref = Any
"""An object, or the text ``"package.module:name"`` that names it (imported when first used)."""


def resolve(ref: Ref) -> Any:
    """The object ``ref`` names: ``ref`` itself, or for the text ``"package.module:attr.attr"`` that attribute of
    that module (imported now).

    Raises:
        ValueError: a text that is not ``module:name``.
        ImportError, AttributeError: no such module or name."""
    if not isinstance(ref, str):
        return ref
    module, sep, attr = ref.partition(":")
    if not sep or not module or not attr:
        raise ValueError(f"{ref!r} is not 'package.module:name'")
    obj: Any = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


def load_plugins(
    variable: str, group: str, register_object: Callable[[object], None], error: type[ValueError], kind: str
) -> None:
    """Import the modules named (comma-separated) by the environment variable ``variable`` (each registers at import;
    found as ``python -m`` finds them, the current folder included: :func:`import_here`) and register each object of
    the entry-point group ``group`` with ``register_object``.

    Raises:
        ``error``: one line, ``{kind} plugin <which>: <exception type>: <message>``, for the first plugin that cannot
            be imported or that raised while registering; for a module named by ``variable`` that is nowhere to
            import from (:func:`import_here`), what to set instead of the exception."""

    def load(what: str, action: Callable[[], object]) -> None:
        try:
            action()
        except error:
            raise
        except Exception as exc:  # a plugin's own failure: one line naming it
            detail = str(exc) if isinstance(exc, PluginNotFound) else f"{type(exc).__name__}: {exc}"
            raise error(f"{kind} plugin {what}: {detail}") from None

    for module in (m.strip() for m in os.environ.get(variable, "").split(",")):
        if module:
            load(f"{variable} module {module}", functools.partial(import_here, module, variable))
    from importlib.metadata import EntryPoint, entry_points

    def register_entry_point(ep: EntryPoint) -> None:
        register_object(ep.load())

    for ep in entry_points(group=group):
        load(f"entry point {ep.name} ({ep.value}) of group {group}", functools.partial(register_entry_point, ep))


def check_record(kind: str, name: object, description: object) -> None:
    """A registry record's name and description (``kind``: ``Method``, ``Scenario``).

    Raises:
        ValueError: an empty name, a name with spaces around it, or a description of several lines."""
    if not isinstance(name, str) or not name.strip() or name != name.strip():
        raise ValueError(f"{kind}: name must be a non-empty text without surrounding spaces, got {name!r}")
    if not isinstance(description, str) or "\n" in description:
        raise ValueError(f"{kind} {name}: description must be one line of text")


class PluginNotFound(LookupError):
    """A module an environment variable names that is neither in the current folder nor on the Python path."""


def import_here(module: str, variable: str) -> None:
    """Import ``module`` as ``python -m`` finds it: from the Python path, else from the current folder (added to the
    end of ``sys.path`` then, so that a module there shadows nothing installed and its own sibling modules import).

    Raises:
        ModuleNotFoundError: a module ``module`` imports is missing (its own message).
        PluginNotFound: ``module`` itself is neither in the current folder nor on the Python path; the message says what
            to set."""
    try:
        importlib.import_module(module)
        return
    except ModuleNotFoundError as exc:
        if not _names_it(exc, module):  # the module was found: one of its own imports is missing
            raise
    here = os.getcwd()
    if here not in sys.path and "" not in sys.path:
        sys.path.append(here)
        importlib.invalidate_caches()
        try:
            importlib.import_module(module)
            return
        except ModuleNotFoundError as exc:
            if not _names_it(exc, module):
                raise
    top = module.split(".")[0]
    holder = f"{top}.py" if top == module else f"the package {top}/"
    raise PluginNotFound(
        f"no module {module} in the current folder ({here}) nor on the Python path: run pemviz in the folder of "
        f"{holder}, or set PYTHONPATH to that folder"
    ) from None


def _names_it(exc: ModuleNotFoundError, module: str) -> bool:
    """Whether ``exc`` says that ``module`` itself (or a package above it) is missing, not one of its imports."""
    return exc.name is not None and (module == exc.name or module.startswith(exc.name + "."))


class Plugins:
    """A registry's plugins, loaded once per process (:meth:`load`; after a failure the next call tries again).

    Args:
        variable, group, kind, error: as :func:`load_plugins` takes them.
        record: the registry's record type (an entry point may give one, or a callable that registers some).
        registry: name -> record, the registry itself (a record already there is not registered again).
        register: registers one record."""

    def __init__(
        self,
        variable: str,
        group: str,
        kind: str,
        error: type[ValueError],
        record: type,
        registry: dict[str, Any],
        register: Callable[[Any], Any],
    ) -> None:
        self.variable, self.group, self.kind, self.error = variable, group, kind, error
        self.record, self.registry, self.register = record, registry, register
        self.loaded = False

    def load(self) -> None:
        """Load them, once (raises ``error``: one line naming the plugin)."""
        if self.loaded:
            return
        self.loaded = True
        try:
            load_plugins(self.variable, self.group, self.register_object, self.error, self.kind)
        except self.error:
            self.loaded = False
            raise

    def register_object(self, obj: object) -> None:
        """An entry point's object: a record (registered unless one of its name is) or a callable that registers."""
        if isinstance(obj, self.record):
            if obj.name not in self.registry:  # type: ignore[attr-defined]
                self.register(obj)
        elif callable(obj):
            obj()
        else:
            raise TypeError(
                f"expected a {self.record.__name__} or a callable that registers {self.kind}s, got "
                f"{type(obj).__name__}"
            )

    def get(self, name: str) -> Any:
        """The record registered as ``name``, plugins loaded first.

        Raises:
            KeyError: no record of that name (the message lists the registered ones); ``error``: a plugin that cannot
                be loaded."""
        self.load()
        if name not in self.registry:
            raise KeyError(f"no {self.kind} named {name!r}; registered: {', '.join(self.registry)}")
        return self.registry[name]
