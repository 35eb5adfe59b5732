"""Sub-commands of the ``pemviz`` command line; each module exposes ``register(subparsers)``. This module holds what
they share (:class:`UsageError`, :class:`Terminated`, the output folder check, the argument helpers) and imports no
command; the studies' shared part is :mod:`pemviz.commands.study`."""

from __future__ import annotations

import argparse
import functools
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, cast

from pemviz.config import ConfigError, default_of
from pemviz.io.files import check_output_path
from pemviz.settings import SETTINGS, Setting

AS_PROGRAM = False
"""Whether this process is the ``pemviz`` program (:func:`pemviz.cli.main`, which sets it, called without ``argv``),
not a library user: only then does a command change process-wide state (:mod:`pemviz.sinks.process`)."""

COMMANDS: dict[str, tuple[str, str]] = {
    "run": ("pemviz.commands.run", "estimate a scenario's failure probability and record the run"),
    "data": ("pemviz.commands.data", "fetch or locate the KITTI salient-variable files"),
    "pem": ("pemviz.commands.pem", "train or evaluate the perception error model (PEM)"),
    "serve": ("pemviz.commands.serve", "open the interactive panel in the browser (viser)"),
    "estimate": ("pemviz.commands.estimate", "estimate the failure probability from logged rollouts (Parquet)"),
    "validate": ("pemviz.commands.validate", "judge the sampler and the baselines against exact failure probabilities"),
    "tables": (
        "pemviz.commands.tables",
        "reproduce the paper's Tables II and III with repetitions and the exact answer",
    ),
    "report": (
        "pemviz.commands.report",
        "write a safety-case report (HTML and Markdown) from a run's result document or recording",
    ),
}
"""Each command: (its module, its one-line help). ``pemviz --help`` lists them without importing any command module
(``run``'s with the registered scenarios: :func:`command_help`)."""


def command_help(name: str) -> str:
    """The one-line help of the command ``name`` as ``pemviz --help`` prints it: :data:`COMMANDS`' text, ``run``'s
    followed by every registered scenario, plugins included (:func:`pemviz.scenarios.registry.described`)."""
    text = COMMANDS[name][1]
    if name != "run":
        return text
    from pemviz.scenarios.registry import described

    return f"{text} (scenarios: {', '.join(n for n, _ in described() if n != 'not listed')})"


class UsageError(Exception):
    """A bad command-line value: printed as one line, exit status 2, nothing written."""


def output_folder(path: str | Path, flag: str = "--out") -> Path:
    """Create the output folder ``path`` (and its parents) if needed and check that files can be written there;
    every command's ``--out DIR`` goes through here (an existing folder is reused: ``validate`` and ``tables``
    resume from it).

    Raises:
        UsageError: ``path`` is a file, or the folder cannot be created or written."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{flag} {out}: exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=out, prefix=".pemviz-probe-"):
            pass
    except OSError as exc:
        raise UsageError(f"{flag} {out}: cannot write there ({exc.strerror or exc})") from None
    return out


class Terminated(KeyboardInterrupt):
    """SIGTERM (``timeout``, CI, containers), raised where Python runs, handled like Ctrl-C: the command
    finishes what can be finished (a recording marked interrupted), says so in one line, exit status 143."""


def interrupted(exc: KeyboardInterrupt, done: str) -> KeyboardInterrupt:
    """The same interrupt (Ctrl-C or :class:`Terminated`) carrying what the command finished, for the one line
    the command line prints."""
    return type(exc)(done)


def split_choices(
    text: str, allowed: Iterable[str], flag: str, why_not: Callable[[str], str | None] | None = None
) -> tuple[str, ...]:
    """The comma-separated names of ``--FLAG text``, each one of ``allowed``, in the order given; ``why_not(name)``
    may say why a name outside ``allowed`` is not one (None: the list of those allowed says it).

    Raises:
        UsageError: an empty list or a name outside ``allowed``."""
    items = tuple(x.strip() for x in text.split(",") if x.strip())
    allowed = tuple(allowed)
    for x in items:
        why = why_not(x) if why_not is not None and x not in allowed else None
        if why is not None:
            raise UsageError(f"--{flag} {x!r}: {why}")
    if not items or any(x not in allowed for x in items):
        raise UsageError(f"--{flag} {text!r}: use a comma-separated list of {', '.join(allowed)}")
    return items


SHOWN_DEFAULTS = {
    "pem": "ml-nn",
    "workers": "every usable core",
    "ray_address": "a local one",
    "chunk_rollouts": "8192, and only stages above 20000 rollouts stream",
}
"""What a setting's None stands for, as the flags' help says it (tests keep these equal to
:data:`pemviz.pem.recipes.DEFAULT_PEM_NAME`, :data:`pemviz.core.lockstep.DEFAULT_CHUNK_SIZE` and ``STREAM_ABOVE``)."""


def add_setting(p: argparse.ArgumentParser | argparse._ArgumentGroup, name: str, default: Any = None) -> None:
    """The flag of the :class:`ExperimentConfig` field ``name`` (its flags, type and help from
    :data:`pemviz.settings.SETTINGS`; the help says the default config's value, or what None stands for:
    :data:`SHOWN_DEFAULTS`).

    ``default`` is what the flag gives when absent (None: leave the field to the preset / the default config)."""
    shown = default_of(name)
    add_row(p, SETTINGS[name], SHOWN_DEFAULTS.get(name, shown) if shown is None else shown, default)


def add_row(
    p: argparse.ArgumentParser | argparse._ArgumentGroup, s: Setting, shown: object, default: Any = None, lead: str = ""
) -> None:
    """The flag of the setting ``s`` (its first flag, or ``--`` + its name: :attr:`Setting.flag`; its type and help from
    the row, ``lead`` before the help), its value kept as ``s.name``; the help says ``shown`` as the default."""
    name, flags = s.name, s.flags or (s.flag,)
    text = f"{lead}{s.hint} (default {shown})".replace("%", "%%")  # argparse formats help with %
    if s.kind == "params":  # NAME=VALUE, repeatable: the texts, parsed once the scenario is known
        p.add_argument(
            *flags,
            dest=name,
            action="append",
            metavar="NAME=VALUE",
            default=default,
            help=f"{s.hint} (default none: the scenario's own values)".replace("%", "%%"),
        )
        return
    if s.kind == "scenario":  # every registered scenario, listed by the registry when the help is shown
        action = p.add_argument(*flags, dest=name, type=str, default=default, help=text)
        action.describe = functools.partial(_scenario_help, shown)  # type: ignore[attr-defined]
        return
    if s.kind == "bool":  # a switch: present sets True, absent leaves the config's value
        p.add_argument(*flags, dest=name, action="store_const", const=True, default=default, help=text)
        return
    p.add_argument(*flags, dest=name, type=_number(s) if s.kind in ("int", "real") else str, default=default, help=text)


def _scenario_help(shown: object) -> str:
    """``--scenario``'s help: every registered scenario (:func:`pemviz.scenarios.registry.scenario_hint`)."""
    from pemviz.scenarios.registry import scenario_hint

    return f"{scenario_hint()} (default {shown})".replace("%", "%%")


def _number(s: Setting) -> Callable[[str], int | float | None]:
    """The flag's number, parsed as the panel's field parses it (:meth:`Setting.parse`); its range is checked by
    the config, in one line."""

    def parse(text: str) -> int | float | None:
        try:
            return s.parse(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    return parse


def setting_error(exc: ConfigError) -> UsageError:
    """A config's error as the command line says it: ``--alpha: smoothing (alpha) = 2.0 is invalid: ...``."""
    return UsageError(f"{SETTINGS[exc.field].flag}: {exc}" if exc.field in SETTINGS else str(exc))


def pem_argument(value: str | None, flag: str = "--pem") -> str | None:
    """``--pem VALUE`` checked the same way by every command: a shipped PEM's name (``ml-nn``, ``gbt``) or a PEM
    file, returned as given (None: the shipped default).

    Raises:
        UsageError: neither; the message lists the shipped PEMs (:func:`pemviz.pem.store.resolve_pem`)."""
    from pemviz.pem import resolve_pem  # torch: imported when a command runs, not for --help

    try:
        return cast("str | None", resolve_pem(value))  # a str given, the str returned
    except FileNotFoundError as exc:
        raise UsageError(f"{flag} {exc}") from None


def check_save_path(path: Path, overwrite: bool = False) -> Path:
    """Refuse a recording path that cannot be written, before any work starts (nothing is created)."""
    try:
        return check_output_path(path, ".rrd", "--save", overwrite=overwrite)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def add_command(sub: argparse._SubParsersAction, name: str, description: str, **kw: Any) -> argparse.ArgumentParser:
    """The parser of the command ``name`` (its one-line help :data:`COMMANDS`'), with its ``--help`` description."""
    parser: argparse.ArgumentParser = sub.add_parser(name, help=COMMANDS[name][1], description=description, **kw)
    return parser
