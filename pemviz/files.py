"""Writing files safely: never a half-written file, and bad output paths refused before any work."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Callable


def default_file_mode() -> int:
    """0o666 minus the process umask (what ``open()`` gives; ``mkstemp`` gives 0o600)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def atomic_write(path: str | os.PathLike[str], write: Callable[[str], None]) -> Path:
    """``write(tmp)`` into a temporary file beside ``path``, then ``os.replace`` it onto ``path``.

    The temporary file is removed whatever happens, so an exception (or Ctrl-C) inside ``write`` leaves
    neither a partial ``path`` nor a stray file. Returns ``path``.

    Raises:
        OSError: the folder is missing or not writable; whatever ``write`` raises.
    """
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, default_file_mode())
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


def write_text_atomic(path: str | os.PathLike[str], text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` through :func:`atomic_write`."""
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


def check_output_path(path: str | os.PathLike[str], suffix: str, what: str = "output") -> Path:
    """Refuse a path that cannot be written, before any work starts (nothing is created).

    Args:
        path: the file to be written.
        suffix: the extension it must have (``.rrd``, ``.parquet`` ...).
        what: how the message names the path (a flag such as ``--save``).
    Raises:
        ValueError: wrong extension, a directory, a missing folder, or a folder where no file can be
            created (tested by creating and removing one: root ignores permission bits, not read-only mounts).
    """
    p = Path(path)
    if p.suffix != suffix:
        raise ValueError(f"{what} {p}: the file name must end in {suffix}")
    if p.is_dir():
        raise ValueError(f"{what} {p}: is a directory, give a file name ending in {suffix}")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise ValueError(f"{what} {p}: folder {parent} does not exist")
    try:
        with tempfile.NamedTemporaryFile(dir=parent, prefix=".pemviz-probe-"):
            pass
    except OSError as exc:
        raise ValueError(f"{what} {p}: folder {parent} is not writable ({exc.strerror})") from None
    if p.exists() and not os.access(p, os.W_OK):
        raise ValueError(f"{what} {p}: not writable")
    return p


def load_tagged(path: Path, tag: str, version: int, what: str, error: type[Exception]) -> dict:
    """``torch.load(path, weights_only=True)`` of a pemviz payload dict, checked for its format tag and version.

    Args:
        path: an existing file.
        tag, version: the expected ``payload["format"]`` and ``payload["version"]``.
        what: how messages name the file (``PEM``, ``proposal checkpoint``).
        error: the exception type raised for an unreadable or foreign file.
    Raises:
        ``error``: damaged file, missing tag, or another format version.
    """
    import torch

    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for damaged files
        raise error(f"{path}: not a readable {what} file ({exc})") from None
    if not isinstance(payload, dict) or payload.get("format") != tag:
        raise error(f"{path}: not a pemviz {what} file (missing format tag {tag!r})")
    if payload.get("version") != version:
        raise error(f"{path}: {what} format version {payload.get('version')}, this pemviz reads {version}")
    return payload
