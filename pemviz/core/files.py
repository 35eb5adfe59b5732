"""The files the lower layers write and read themselves: :func:`atomic_write` (never a half-written file) and
:func:`load_tagged` (format tag and version checked), for proposal checkpoints and PEMs; output-path checks before a
run are :mod:`pemviz.io.files`'s."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path


def default_file_mode() -> int:
    """0o666 minus the process umask (what ``open()`` gives; ``mkstemp`` gives 0o600)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


class OutputExists(ValueError):
    """The output file exists (or appeared while the work ran) and replacing it was not asked for."""


def _commit(tmp: str, target: Path, overwrite: bool) -> None:
    """Move the finished ``tmp`` onto ``target``: ``os.replace`` with ``overwrite``, else a hard link that fails
    when ``target`` exists (atomic create-if-absent, so a concurrent writer is never silently replaced)."""
    if overwrite:
        os.replace(tmp, target)
        return
    try:
        os.link(tmp, target)
    except FileExistsError:
        raise OutputExists(
            f"{target}: appeared while this run worked (another writer?); not replaced, "
            "give --overwrite to replace it"
        ) from None
    except OSError:  # a file system without hard links: check, then replace
        if target.exists():
            raise OutputExists(f"{target}: exists; give --overwrite to replace it") from None
        os.replace(tmp, target)


def atomic_write(path: str | os.PathLike[str], write: Callable[[str], None], *, overwrite: bool = True) -> Path:
    """``write(tmp)`` into a temporary file of a unique name beside ``path``, then move it onto ``path``; the temporary
    file is removed whatever happens, so a failure leaves no partial file and an existing ``path`` untouched.
    Returns ``path``.

    Args:
        path: the file written.
        write: writes the whole file at the path it is given.
        overwrite: replace an existing ``path``; when False, :class:`OutputExists` if one exists at the end.
    Raises:
        OSError: the folder is missing or not writable, the disk is full, the file is too large; whatever ``write``
            raises.
        OutputExists: ``overwrite`` is False and ``path`` exists."""
    target = Path(path)
    with temp_file(target) as tmp:
        write(tmp)
        os.chmod(tmp, default_file_mode())
        _commit(tmp, target, overwrite)
    return target


@contextlib.contextmanager
def temp_file(path: str | os.PathLike[str]) -> Iterator[str]:
    """A temporary file of a unique name beside ``path`` (created empty), removed on every exit path.

    Write it, then commit it (:func:`atomic_write`, :func:`pemviz.io.files.commit_files`); whatever was not committed
    is gone when the block ends (an exception, Ctrl-C, SIGTERM)."""
    target = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    try:
        yield tmp
    finally:
        if os.path.lexists(tmp):
            os.unlink(tmp)


def file_kind(path: Path) -> str:
    """What the file at ``path`` is, in words, from its first bytes (for a message that refuses it): ``it is empty``,
    ``it is a text file whose first line is 'hello'``, ``it is a zip archive torch cannot read (...)``, ``it is
    binary data not written by torch.save``."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError as exc:
        return f"it cannot be read: {exc.strerror or exc}"
    if not head:
        return "it is empty"
    if head.startswith(b"PK\x03\x04"):
        return "it is a zip archive torch cannot read (damaged, or not written by torch.save)"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        return "it is binary data not written by torch.save"
    if "\x00" in text:
        return "it is binary data not written by torch.save"
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    return f"it is a text file whose first line is {first[:40]!r}" if first else "it is a text file of blank lines"


def load_tagged(
    path: Path,
    tag: str,
    version: int,
    what: str,
    error: type[Exception],
    *,
    as_numpy: bool = False,
    allowed: str | None = None,
) -> dict:
    """A pemviz payload dict written by ``torch.save``, checked for its format tag and version.

    Args:
        path: an existing file.
        tag: the expected ``payload["format"]``.
        version: the expected ``payload["version"]``.
        what: how messages name the file (``PEM``, ``proposal checkpoint``).
        error: the exception type raised for an unreadable or foreign file.
        as_numpy: tensors as numpy arrays, read without torch where possible
            (:func:`pemviz.core.torch_payload.load_payload`); else ``torch.load(path, weights_only=True)``'s
            tensors.
        allowed: what a file that cannot be read is told to give instead.
    Raises:
        ``error``: damaged file, missing tag, or another format version."""
    try:
        if as_numpy:
            from pemviz.core.torch_payload import load_payload

            payload = load_payload(path)
        else:
            import torch  # ~1 s to import: only when a checkpoint is read (see pemviz.io.files.write_rrd's rerun)

            payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # torch raises several types for damaged files, their messages no help to a user
        allowed = allowed or f"a {what} file is the torch.save archive pemviz writes"
        raise error(f"{path}: not a readable {what} file ({file_kind(path)}): {allowed}") from None
    if not isinstance(payload, dict) or payload.get("format") != tag:
        raise error(f"{path}: not a pemviz {what} file (missing format tag {tag!r})")
    if payload.get("version") != version:
        raise error(f"{path}: {what} format version {payload.get('version')}, this pemviz reads {version}")
    return payload


def repo_root() -> Path:
    """The folder holding the ``pemviz`` package folder (the repository root in a checkout)."""
    return Path(__file__).resolve().parents[2]  # pemviz/core/files.py -> the repository
