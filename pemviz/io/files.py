"""Writing files safely: never a half-written file, and bad output paths refused before any work; built on the
atomic write and tagged checkpoints of :mod:`pemviz.core.files`."""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from types import FrameType
from typing import Any

from pemviz.core.files import OutputExists, _commit, atomic_write, default_file_mode

TEMP_NAME_EXTRA = 14
"""Characters a temporary name adds to the target's name: ``.NAME.`` + 8 random characters + ``.tmp``."""

MAGIC = {".rrd": b"RRF", ".parquet": b"PAR1", ".pt": b"PK\x03\x04"}
"""Leading bytes of the files pemviz writes, by suffix: a file without them was not written by pemviz and is
never replaced (rerun recording, Parquet table, ``torch.save`` zip archive)."""

SIGNATURES = {
    ".html": b"<title>pemviz report",
    ".md": b"# pemviz report",
    ".xml": b'<testsuites><testsuite name="pemviz"',
}
"""Text the text files pemviz writes under a name the user picks carry in their first 4 KiB, by suffix: the
safety-case report (``--report``, ``pemviz report``), its Markdown twin and the JUnit test case (``--junit``). A file
without it (a user's page, notes, a build's XML) is never replaced, ``--overwrite`` or not."""


def commit_files(pairs: list[tuple[str, Path]], *, overwrite: bool) -> None:
    """Move finished temporary files onto their targets, in order (the last one is the unit's commit point:
    a reader checks the others against it). Without ``overwrite``, targets already moved are removed again
    when a later one exists, so a refused unit leaves nothing.

    Raises:
        OutputExists: ``overwrite`` is False and a target exists."""
    done: list[Path] = []
    with deferred_signals():  # Ctrl-C / SIGTERM wait the few renames out: the unit is never half moved
        try:
            for tmp, target in pairs:
                os.chmod(tmp, default_file_mode())
                _commit(tmp, target, overwrite)
                done.append(target)
        except OutputExists:
            for target in done:
                target.unlink(missing_ok=True)
            raise


@contextlib.contextmanager
def deferred_signals() -> Iterator[None]:
    """SIGINT and SIGTERM received inside the block are acted on when it ends (main thread only; elsewhere
    a no-op). For short steps that must not be cut in two, such as moving the files of a unit into place."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list[int] = []
    names = [signal.SIGINT, signal.SIGTERM]
    previous: dict[int, Callable[[int, FrameType | None], Any] | int | None] = {
        sig: signal.signal(sig, lambda signum, frame: received.append(signum)) for sig in names
    }
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        for signum in received[:1]:
            handler = previous[signum]
            if callable(handler):
                handler(signum, None)
            elif handler == signal.SIG_DFL:
                signal.raise_signal(signum)


def write_text_atomic(path: str | os.PathLike[str], text: str, *, overwrite: bool = True) -> Path:
    """Write UTF-8 ``text`` to ``path`` through :func:`atomic_write`."""

    def write(tmp: str) -> None:
        Path(tmp).write_text(text, encoding="utf-8")

    return atomic_write(path, write, overwrite=overwrite)


def write_rrd(
    path: str | os.PathLike[str], log: Callable[[Any], None], *, app_id: str = "pemviz", overwrite: bool = True
) -> Path:
    """A rerun recording: ``log(stream)`` into a :class:`rerun.RecordingStream` encoded in memory, then written
    through :func:`atomic_write` (rerun's own file sink stalls its writer thread on a write error).

    Raises:
        OSError: the file could not be written (nothing is left); OutputExists: see :func:`atomic_write`."""
    import rerun as rr  # ~1.3 s to import: pemviz.io.data imports this module and needs neither rerun nor torch

    stream = rr.RecordingStream(app_id)
    # rerun's class attribute ``binary_stream = binary_stream`` (a module function) reads to mypy as unbound
    binary = stream.binary_stream()  # type: ignore[misc]
    try:
        stream.set_log_time_enabled(False)
        stream.set_log_tick_enabled(False)
        log(stream)
        stream.flush()
        encoded = binary.read(flush=True) or b""
    finally:
        stream.disconnect()

    def write(tmp: str) -> None:
        Path(tmp).write_bytes(encoded)

    return atomic_write(path, write, overwrite=overwrite)


def written_by_pemviz(path: Path) -> bool:
    """Whether an existing file looks like one pemviz writes for its suffix (:data:`MAGIC`, :data:`SIGNATURES`; a
    ``.json`` must be a pemviz rollout sidecar or result document). Other suffixes (CSV, LaTeX tables) cannot be told
    and count as True."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    if path.suffix in MAGIC:
        return head.startswith(MAGIC[path.suffix])
    if path.suffix in SIGNATURES:
        return SIGNATURES[path.suffix] in head
    if path.suffix == ".json":  # a rollout sidecar, a run's result (pemviz run --json) or an estimate's
        return any(b'"%s"' % tag in head for tag in (b"pemviz-rollouts", b"pemviz-result", b"pemviz-estimate"))
    return True


def check_output_path(
    path: str | os.PathLike[str], suffix: str, what: str = "output", *, overwrite: bool = False
) -> Path:
    """Refuse a path that cannot be written, before any work starts (nothing is created).

    Args:
        path: the file to be written.
        suffix: the extension it must have (``.rrd``, ``.parquet`` ...).
        what: how the message names the path (a flag such as ``--save``).
        overwrite: an existing file may be replaced (only a regular file pemviz wrote, :func:`written_by_pemviz`).
    Raises:
        ValueError: wrong extension, a directory, a missing folder, a name too long, a folder where no file can be
            created (tested by creating one), or an existing file (:class:`OutputExists` without ``overwrite``; with
            it, one pemviz did not write)."""
    p = Path(path)
    if p.suffix != suffix:
        raise ValueError(f"{what} {p}: the file name must end in {suffix}")
    if p.is_dir():
        raise ValueError(f"{what} {p}: is a directory, give a file name ending in {suffix}")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise ValueError(f"{what} {p}: folder {parent} does not exist")
    try:
        name_max = os.pathconf(parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    n_bytes = len(os.fsencode(p.name)) + TEMP_NAME_EXTRA
    if n_bytes > name_max:
        raise ValueError(
            f"{what} {p}: file name too long ({len(os.fsencode(p.name))} bytes; at most "
            f"{name_max - TEMP_NAME_EXTRA} here)"
        )
    _check_writable(parent, f"{what} {p}")
    check_free_name(p, what, overwrite=overwrite, kind=f"{suffix} file")
    return p


def _check_writable(folder: Path, where: str) -> None:
    """Create and remove a probe file in ``folder`` (root ignores permission bits, not read-only mounts)."""
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".pemviz-probe-"):
            pass
    except OSError as exc:  # errno's own words can contradict the message (/proc: "No such file or directory")
        why = "read-only" if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOENT) else exc.strerror
        raise ValueError(f"{where}: folder {folder} is not writable ({why})") from None


def check_output_folder(folder: str | os.PathLike[str], names: tuple[str, ...], what: str = "--out") -> Path:
    """Refuse an output folder where ``names`` cannot be written, before any work starts (nothing is created); the
    folder may be missing, and files of those names are replaced (never a folder or special file).

    Raises:
        ValueError: not a folder, no parent folder, not writable, a name too long, or a name taken by a folder."""
    out = Path(folder)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{what} {out}: exists and is not a folder")
    probe_dir = out.absolute()
    while not probe_dir.is_dir():  # the nearest existing folder: missing ones are created when the files are written
        if os.path.lexists(probe_dir) or probe_dir.parent == probe_dir:
            raise ValueError(f"{what} {out}: {probe_dir} exists and is not a folder")
        probe_dir = probe_dir.parent
    _check_writable(probe_dir, f"{what} {out}")
    for name in names:
        target = out / name
        if len(os.fsencode(name)) + TEMP_NAME_EXTRA > 255:
            raise ValueError(f"{what} {target}: file name too long")
        if os.path.lexists(target) and (target.is_symlink() or not target.is_file()):
            raise ValueError(f"{what} {target}: exists and is not a regular file; not replacing it")
    return out


def check_free_name(path: Path, what: str, *, overwrite: bool = False, kind: str = "file") -> None:
    """Refuse a companion file (a sidecar, a checkpoint) that exists and may not be replaced.

    Raises:
        OutputExists / ValueError: as :func:`check_output_path` for an existing file."""
    if not os.path.lexists(path):
        return
    if path.is_symlink() or not path.is_file():
        raise ValueError(f"{what} {path}: exists and is not a regular file; not replacing it")
    if not overwrite:
        raise OutputExists(f"{what} {path}: exists; give --overwrite to replace it")
    if not written_by_pemviz(path):
        raise ValueError(f"{what} {path}: exists and is not a {kind} pemviz wrote; not replacing it")


def free_default_path(folder: Path, stem: str, suffix: str = ".rrd") -> Path:
    """``folder/stem.rrd``, or ``stem-2.rrd``, ``stem-3.rrd`` ... when taken: default names never replace a file."""
    path, k = folder / f"{stem}{suffix}", 2
    while path.exists():
        path, k = folder / f"{stem}-{k}{suffix}", k + 1
    return path
