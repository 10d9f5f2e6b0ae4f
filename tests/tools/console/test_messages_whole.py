"""Messages from every layer reach the buffer whole (issue 18 item 3): a 600-byte message
of a controller layer and of the service goes through the Bit3 message queues (11 entries
each, joined by the reader: ``Message.first_seq``) to the console, whose Messages screen
shows it uncut. The bound (MESSAGE_MAX_BYTES) is stated once, in bit3/layout.py and the
generated docs/bit3-layout.md."""

from __future__ import annotations

from bit3.layout import MESSAGE_MAX_BYTES, MESSAGE_TEXT_BYTES, Severity
from controller.messages import Level
from tools.console.app import MessagesScreen
from tests.tools.console._pilot import frames, run_app


def _text(who: str, n: int = 600) -> str:
    """``n`` bytes of ASCII that say where each part came from (a cut would show)."""
    words = "".join(f"{who} part {k:02d} of a long diagnostic; " for k in range(40))
    return words[:n - 3] + "END"


def test_a_600_byte_message_of_a_layer_and_of_the_service_reach_the_console_whole(sim, console):
    layer_text = _text("servo")
    service_text = _text("service")
    assert len(layer_text.encode()) == len(service_text.encode()) == 600 < MESSAGE_MAX_BYTES

    async def body(pilot):
        frames(sim, console, 2)
        sim.rt.post("servo", Level.ERROR, layer_text)  # forwarded as "servo: <text>" (607 bytes)
        sim.svc.post(Severity.ERROR, 199, service_text)
        frames(sim, console, 2)
        # the Bit3 queues: one message each, whole, over 11 entries
        ctl = [m for m in sim.client.messages(0, "controller") if m.text.startswith("servo: servo part 00")]
        svc = [m for m in sim.client.messages(0, "service") if m.code == 199]
        assert [m.text for m in ctl] == ["servo: " + layer_text] and [m.text for m in svc] == [service_text]
        assert ctl[0].seq - ctl[0].first_seq + 1 == -(-607 // MESSAGE_TEXT_BYTES) == 11
        assert svc[0].seq - svc[0].first_seq + 1 == -(-600 // MESSAGE_TEXT_BYTES) == 11
        assert ctl[0].severity is Severity.ERROR and svc[0].severity is Severity.ERROR
        # the console: its sources joined them, the Messages screen shows them uncut
        got = {(m.source, m.text) for m in console.sources.messages}
        assert ("servo", layer_text) in got and ("service", service_text) in got
        await pilot.press("m")
        await pilot.pause()
        assert isinstance(console.screen, MessagesScreen)
        shown = str(console.screen.query_one("#all-messages").render())
        assert layer_text in shown and service_text in shown and "~" not in shown
    run_app(console, body)
