"""torch, imported where a computation first needs it, with the thread count a run asked for:
:func:`pemviz.engine.resources.torch_threads` leaves the number here when torch is not imported yet
(:func:`want_threads`), and :func:`torch_module` applies it on the import."""

from __future__ import annotations

import sys
from typing import Any

_wanted: int | None = None
"""Threads asked for while torch was not imported (None: none asked for)."""
_default: int | None = None
"""torch's own thread count, read when :func:`torch_module` imported it under a :func:`want_threads` request."""


def torch_module() -> Any:
    """The ``torch`` module, imported now if it was not; a pending :func:`want_threads` request is applied once."""
    global _wanted, _default
    import torch

    if _wanted is not None:
        _default = torch.get_num_threads()
        torch.set_num_threads(_wanted)
        _wanted = None
    return torch


def want_threads(n: int | None) -> None:
    """Ask for ``n`` torch threads once torch is imported by :func:`torch_module` (None: withdraw the request)."""
    global _wanted, _default
    _wanted, _default = n, None


def imported() -> bool:
    """Whether torch has been imported in this process."""
    return "torch" in sys.modules


def settle() -> int | None:
    """End a :func:`want_threads` request: the thread count torch had before it was applied (to restore), or None when
    torch was not imported under it."""
    global _wanted, _default
    before, _wanted, _default = _default, None, None
    return before
