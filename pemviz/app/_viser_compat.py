"""The one place pemviz reaches into viser's private API (viser 1.1, pinned): :func:`resend_value` sends a GUI
input's unchanged value to the browser again with viser's own update message (``tests/app/test_app.py`` finds out
when viser changes)."""

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
        AttributeError: a viser whose handles no longer carry ``_impl.gui_api._websock_interface`` (not 1.1)."""
    impl = handle._impl
    impl.gui_api._websock_interface.queue_message(GuiUpdateMessage(impl.uuid, {"value": impl.value}))


def set_value(handle: _GuiInputHandle[T], value: T) -> None:
    """``handle.value = value``: set a GUI input's value (viser sends it and runs its callbacks), typed once here
    because mypy takes viser 1.1's property for read-only."""
    handle.value = value  # type: ignore[misc]  # viser 1.1: setter not adjacent to the getter, mypy sees read-only
