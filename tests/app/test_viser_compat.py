"""pemviz.app._viser_compat: the one use of viser's private API still matches the pinned viser."""

from __future__ import annotations

from types import SimpleNamespace

import viser
from pemviz.app._viser_compat import resend_value
from viser._messages import GuiUpdateMessage


def test_resend_value_queues_viser_s_update_message_with_the_server_value():
    sent = []
    gui_api = SimpleNamespace(_websock_interface=SimpleNamespace(queue_message=sent.append))
    handle = SimpleNamespace(_impl=SimpleNamespace(uuid="field-7", value=2.5, gui_api=gui_api))
    resend_value(handle)
    assert sent == [GuiUpdateMessage("field-7", {"value": 2.5})]


def test_a_real_viser_input_handle_has_what_the_shim_reaches_for():
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        handle = server.gui.add_number("n", initial_value=3.0)
        impl = handle._impl
        assert impl.value == 3.0 and isinstance(impl.uuid, str)
        assert callable(impl.gui_api._websock_interface.queue_message)
        resend_value(handle)  # no error: the message goes to the (empty) client queue
    finally:
        server.stop()
