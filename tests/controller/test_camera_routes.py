"""Camera switching (issue 18 item 4, docs/cameras.md): the user I/F box's switches and the
console's CAMERA ROUTE request -> Data Acquisition, the one writer of
``commands.matrix_route`` -> the service's strobe handshake -> the fake matrix switcher.
The whole system in simulated time (SystemSimulator); the box is driven on the simulated
rack (FakeWorld.set_user_inputs)."""

from __future__ import annotations

import pytest

from controller.layers import Request, Response
from controller.routes import (
    ALL_ROUTES, encode_matrix_route, BOX_IDLE, box_selections, parse_route_request, route_request_arg, route_text, set_monitor,
    switch_word,
)

PIO_FRAMES = 24  # three of the service's 40 Hz PIO periods at 320 Hz: read, route, write


def _switcher(sim):
    return sim.world.bus["pio_video"].switcher


def _press(sim, monitor: int, camera: int, frames: int = PIO_FRAMES) -> None:
    sim.world.set_user_inputs(switch_word(monitor, camera))
    sim.step(frames)


def _release(sim) -> None:
    sim.world.set_user_inputs(BOX_IDLE)
    sim.step(PIO_FRAMES)


def _service_messages(sim, code: int) -> list[str]:
    return [m.text for m in sim.client.messages(0, "service") if int(m.code) == code]


# --- the table ------------------------------------------------------------------------------
def test_switch_table_active_low_one_switch_per_selection():
    assert box_selections(BOX_IDLE) == (None, None)  # an unplugged box selects nothing
    assert box_selections(switch_word(1, 3)) == (3, None)
    assert box_selections(switch_word(2, 0)) == (None, 0)  # blank monitor 2
    both = switch_word(1, 1) & switch_word(1, 2)  # two cameras for monitor 1 at once: none
    assert box_selections(both) == (None, None)
    assert box_selections(switch_word(1, 2) & switch_word(2, 1)) == (2, 1)
    assert box_selections(0xFF00 | 0xFF) == (None, None) and box_selections(0x00FF) == (None, None)
    with pytest.raises(ValueError, match="no user I/F box switch for camera 4 on monitor 1"):
        switch_word(1, 4)


def test_routes_in_words_and_the_request_argument():
    assert len(ALL_ROUTES) == 16 and len(set(ALL_ROUTES)) == 16
    assert route_text(encode_matrix_route(2, 3)) == "monitor 1: camera 2, monitor 2: camera 3"
    assert route_text(0) == "monitor 1: blank, monitor 2: blank"
    assert route_text(0x55) == "monitor 1: camera 1, monitor 2: camera 1 (bits 0x50 outside the route table)"
    assert set_monitor(encode_matrix_route(1, 2), 2, 0) == encode_matrix_route(1, 0)
    assert parse_route_request(route_request_arg(2, 3)) == (2, 3)
    for bad in (0x13 + 1, 0x30, 0x04, -1):
        with pytest.raises(ValueError, match="is not monitor\\*16 \\+ camera"):
            parse_route_request(bad)


# --- the box on the simulated rack ----------------------------------------------------------
def test_a_box_switch_changes_the_switchers_route(sim):
    sw = _switcher(sim)
    sim.step(PIO_FRAMES)
    assert sw.route == 0  # both monitors blank until someone chooses
    _press(sim, 1, 2)
    assert sw.monitors == (2, 0)
    assert int(sim.client.read_inputs().matrix_route) == encode_matrix_route(2, 0)  # published, applied
    assert int(sim.rt.wm.get("daq.camera_route")) == encode_matrix_route(2, 0)
    assert int(sim.rt.wm.get("daq.camera_route_applied")) == encode_matrix_route(2, 0)
    _release(sim)
    assert sw.monitors == (2, 0)  # a push-button: releasing it keeps the route
    _press(sim, 2, 3)
    assert sw.monitors == (2, 3)
    _press(sim, 2, 0)
    assert sw.monitors == (2, 0)  # blanked
    assert "camera route monitor 1: camera 2, monitor 2: blank (user I/F box)" in [
        m.text for m in sim.rt.messages.recent(500, "daq")]


def test_two_switches_for_one_monitor_or_an_idle_box_change_nothing(sim):
    sw = _switcher(sim)
    _press(sim, 1, 1)
    strobes = sw.strobes
    sim.world.set_user_inputs(switch_word(1, 2) & switch_word(1, 3))
    sim.step(PIO_FRAMES)
    _release(sim)
    assert sw.monitors == (1, 0) and sw.strobes == strobes


def test_the_console_route_stands_until_a_box_switch_moves(sim):
    sw = _switcher(sim)
    _press(sim, 1, 1)  # held down
    code, text = sim.request(Request.ROUTE, route_request_arg(1, 3))
    assert code == Response.COMPLETE, text
    assert text == "CAMERA ROUTE: applied by the service: monitor 1: camera 3, monitor 2: blank"
    sim.step(4 * PIO_FRAMES)
    assert sw.monitors == (3, 0)  # the held switch does not take it back
    _press(sim, 1, 2)
    assert sw.monitors == (2, 0)


def test_console_routes_in_every_system_state(powered):
    sim = powered
    code, text = sim.request(Request.ROUTE, route_request_arg(2, 1))
    assert code == Response.COMPLETE, text
    assert _switcher(sim).monitors == (0, 1)
    code, text = sim.request(Request.ROUTE, 0x35)
    assert code == Response.REFUSED and "camera route argument 53 is not monitor*16 + camera" in text
    assert _switcher(sim).monitors == (0, 1)


def test_a_box_switch_while_halted_is_applied_by_a_single_step(powered):
    sim = powered
    code, text = sim.request(Request.HALT)
    assert code == Response.COMPLETE, text
    _press(sim, 1, 3)
    assert _switcher(sim).monitors == (0, 0)  # a halted controller runs no frames
    code, text = sim.request(Request.STEP, 1)
    assert code == Response.COMPLETE, text
    sim.step(PIO_FRAMES)
    assert _switcher(sim).monitors == (3, 0)  # the step's halted write carried the route


def test_a_switcher_that_does_not_answer_one_message_no_retry_every_frame(sim):
    sw = _switcher(sim)
    sim.step(PIO_FRAMES)
    sim.world.bus["pio_video"].inject("switcher_silent")
    code, text = sim.request(Request.ROUTE, route_request_arg(1, 2))
    assert code == Response.FAILED
    assert text == ("CAMERA ROUTE: monitor 1 <- camera 2 not applied by the service within 0.25 s "
                    "(its messages say why)")
    strobes = sw.strobes
    sim.step(320)  # one second: the service does not strobe again every frame
    assert sw.strobes == strobes
    assert len(_service_messages(sim, 141)) == 1
    assert int(sim.client.read_inputs().matrix_route) == 0  # the applied route is still the old one
    # the switcher answers again: the next route goes through
    sim.world.bus["pio_video"].clear("switcher_silent")
    code, text = sim.request(Request.ROUTE, route_request_arg(1, 3))
    assert code == Response.COMPLETE, text
    assert sw.monitors == (3, 0)


def test_the_applied_route_is_recorded_in_the_pio_topic(sim):
    from tools.recording.topics import _Topics  # the recorder's message builder (pfma record)
    _press(sim, 1, 3)
    _press(sim, 2, 1)
    topics = _Topics(sim.rig.layout)
    snap = sim.client.read_inputs()
    msg = topics.pio(snap.record, {"t_s": 0.0, "frame": 0})
    assert (msg["matrix_route"], msg["monitor_1_camera"], msg["monitor_2_camera"]) == (
        encode_matrix_route(3, 1), 3, 1)
    assert msg["user_inputs"] == switch_word(2, 1)
    props = topics.schemas()["/pfma/pio"]["properties"]
    assert {"matrix_route", "monitor_1_camera", "monitor_2_camera"} <= set(props)
