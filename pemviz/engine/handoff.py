"""A worker's result handed to the run's process through shared memory instead of the pool's pipe.

The worker pickles the result with protocol 5, writes its out-of-band buffers (every contiguous numpy array) once
into a file of a RAM-backed folder (``/dev/shm``), and the run's process maps that file copy-on-write and unpickles
the arrays in place (PEP 574): the same bits, several times less CPU than the pipe for blocks of tens of megabytes.
Where there is no such folder or writing fails, the result travels through the pipe. A pool's folder goes with the
pool; one left by a killed run is removed when the next is made."""

from __future__ import annotations

import contextlib
import mmap
import os
import pickle
import shutil
import tempfile
from typing import Any

SHARED_ROOT = "/dev/shm"
"""The RAM-backed folder under which a pool's hand-off folder is made (Linux)."""

ALIGN = 64
"""Byte alignment of each array in a hand-off file (a cache line: numpy's own allocations are at least 16-aligned)."""

Packed = tuple[bytes, "str | None", list[tuple[int, int]]]
"""A packed result: (its pickle, the path of the file holding its out-of-band buffers or None, each buffer's
(offset, bytes) in that file)."""


PREFIX = "pemviz-pool-"
"""A hand-off folder's name: this prefix, the pid of the run's process, a dash and a random part."""


def make_folder(root: str = SHARED_ROOT) -> str | None:
    """A new folder under ``root`` for one pool's hand-off files, or None where ``root`` is not a writable folder (the
    results then travel through the pipe). Remove it with :func:`remove_folder`; the folders that runs killed
    before they could (their pid gone) are removed here."""
    with contextlib.suppress(OSError):
        for name in os.listdir(root):
            pid = name[len(PREFIX) :].split("-")[0]
            if name.startswith(PREFIX) and pid.isdigit() and not _alive(int(pid)):
                remove_folder(os.path.join(root, name))
    try:
        return tempfile.mkdtemp(prefix=f"{PREFIX}{os.getpid()}-", dir=root)
    except OSError:
        return None


def _alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (one of another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def remove_folder(folder: str | None) -> None:
    """Remove a hand-off folder and the files left in it (blocks cancelled before the run read them)."""
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)


def pack(obj: Any, folder: str | None) -> Packed:
    """``obj`` pickled by cloudpickle (protocol 5), its contiguous numpy arrays written to a new file in ``folder``
    (None, or a failure to write there: pickled in-band). Undo with :func:`unpack`, once."""
    import cloudpickle

    if folder is None:
        return cloudpickle.dumps(obj, protocol=5), None, []
    buffers: list[pickle.PickleBuffer] = []
    head = cloudpickle.dumps(obj, protocol=5, buffer_callback=buffers.append)
    if not sum(buf.raw().nbytes for buf in buffers):
        return head, None, []
    spans, path = [], None
    try:
        fd, path = tempfile.mkstemp(dir=folder, suffix=".block")
        with open(fd, "wb") as f:
            offset = 0
            for buf in buffers:
                raw = buf.raw()
                pad = -offset % ALIGN
                f.write(b"\0" * pad)
                f.write(raw)
                spans.append((offset + pad, raw.nbytes))
                offset += pad + raw.nbytes
    except OSError:  # e.g. a full /dev/shm, or the pool's folder removed while this block ran: the pipe
        if path is not None:
            with contextlib.suppress(OSError):
                os.unlink(path)
        return cloudpickle.dumps(obj, protocol=5), None, []
    return head, path, spans


def unpack(packed: Packed) -> Any:
    """The object :func:`pack` packed; its arrays are views of the hand-off file mapped copy-on-write (writable, the
    file removed at once: its memory is freed with the last array).

    Raises:
        OSError: the hand-off file is missing (its pool's folder was removed)."""
    head, path, spans = packed
    if path is None:
        return pickle.loads(head)
    try:
        with open(path, "rb") as f:
            shared = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_COPY)
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)
    view = memoryview(shared)
    return pickle.loads(head, buffers=[view[a : a + n] for a, n in spans])
