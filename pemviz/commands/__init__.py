"""Sub-commands of the ``pemviz`` command line; each module exposes ``register(subparsers)``."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Iterable


class UsageError(Exception):
    """A bad command-line value: printed as one line, exit status 2, nothing written."""


def output_folder(path: str | Path, flag: str = "--out") -> Path:
    """Create the output folder ``path`` (and its parents) if needed and check that files can be written there.

    Every command's ``--out DIR`` goes through here, so they all behave alike: a missing folder is created, an
    existing one is reused (``validate`` and ``tables`` resume from it).

    Raises:
        UsageError: ``path`` is a file, or the folder cannot be created or written.
    """
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


def split_choices(text: str, allowed: Iterable[str], flag: str) -> tuple[str, ...]:
    """The comma-separated names of ``--FLAG text``, each one of ``allowed``, in the order given.

    Raises:
        UsageError: an empty list or a name outside ``allowed``.
    """
    items = tuple(x.strip() for x in text.split(",") if x.strip())
    allowed = tuple(allowed)
    if not items or any(x not in allowed for x in items):
        raise UsageError(f"--{flag} {text!r}: use a comma-separated list of {', '.join(allowed)}")
    return items
