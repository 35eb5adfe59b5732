"""The one place pemviz reaches into viser's private API (viser 1.1, pinned in pyproject.toml).

viser has no public way to send a GUI input's value to the browser again when it has not changed on the server;
:func:`resend_value` does it with viser's own update message. When viser changes these internals, this module is
the one to adapt (``tests/app/test_app.py`` drives the panel in a browser and finds out).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, TypeVar

from viser._messages import GuiUpdateMessage

if TYPE_CHECKING:
    from viser._gui_handles import _GuiInputHandle

T = TypeVar("T")


def resend_value(handle: Any) -> None:
    """Queue a message that sets the browser's copy of a GUI input to the value the server holds.

    Args:
        handle: a viser GUI input handle (``GuiInputHandle``: a number, text, dropdown or button-group input).
    Raises:
        AttributeError: a viser whose handles no longer carry ``_impl.gui_api._websock_interface`` (not 1.1).
    """
    impl = handle._impl
    impl.gui_api._websock_interface.queue_message(GuiUpdateMessage(impl.uuid, {"value": impl.value}))


def set_value(handle: _GuiInputHandle[T], value: T) -> None:
    """``handle.value = value``: set a GUI input's value (viser sends it to the browser and runs its callbacks).

    viser 1.1 defines the ``value`` setter apart from its getter, so mypy takes the property for read-only; the
    assignment is typed here once, against the handle's value type.
    """
    handle.value = value  # type: ignore[misc]  # viser 1.1: setter not adjacent to the getter, mypy sees read-only
