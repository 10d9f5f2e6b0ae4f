"""SpaceMouse over hidapi: report parsing and unplug/re-plug, on FakeHidDevice + SimClock."""

from __future__ import annotations

import struct

import pytest

from drivers.crl import HidSpaceMouse, parse_report
from drivers.crl.hid import AXIS_MAP
from fakes.hid import FakeHidBus, FakeHidDevice
from pfma.clock import SimClock


def test_parse_report_forms():
    assert parse_report(bytes.fromhex("01 0a00 f6ff 5e01")) == {"translation": (10, -10, 350)}
    assert parse_report([2, 0x01, 0x00, 0xFF, 0x7F, 0x00, 0x80]) == {"rotation": (1, 32767, -32768)}
    assert parse_report(bytes([3, 0x03])) == {"buttons": 3}
    assert parse_report(bytes([3, 0x00, 0x01])) == {"buttons": 0x100}  # Pro models: more bytes
    combined = struct.pack("<B6h", 1, 1, 2, 3, -4, -5, -6)
    assert len(combined) == 13
    assert parse_report(combined) == {"translation": (1, 2, 3), "rotation": (-4, -5, -6)}
    assert parse_report(b"") == {} and parse_report(bytes([4, 1, 2])) == {}
    assert parse_report(bytes([1, 0, 0])) == {}  # truncated


def expected_axes(t, r, fs=350.0):
    dev = list(t) + list(r)
    return tuple(max(-1.0, min(1.0, s * dev[i] / fs)) for i, s in AXIS_MAP)


@pytest.fixture
def clock():
    return SimClock()


@pytest.mark.parametrize("combined", [False, True])
def test_axes_from_split_and_combined_reports(clock, combined):
    fake = FakeHidDevice(combined=combined)
    sm = HidSpaceMouse(opener=fake, clock=clock)
    st = sm.update()
    assert sm.connected and st.valid and st.axes == (0.0,) * 6 and not st.deadman and st.source == "hid"
    fake.set_axes((35, -70, 175), (-350, 700, 0))
    st = sm.update()
    assert st.axes == pytest.approx(expected_axes((35, -70, 175), (-350, 700, 0)))
    # device x right, y toward the user, z down -> forward = -y, left = -x, up = -z
    assert st.axis("x") == pytest.approx(0.2) and st.axis("y") == pytest.approx(-0.1)
    assert st.axis("z") == pytest.approx(-0.5) and st.axis("pitch") == pytest.approx(1.0)
    assert st.axis("roll") == -1.0  # clipped
    assert st.raw == (35, -70, 175, -350, 700, 0)


def test_buttons_and_deadman(clock):
    fake = FakeHidDevice()
    sm = HidSpaceMouse(opener=fake, clock=clock)
    fake.set_buttons(0b10)
    st = sm.update()
    assert st.buttons == 2 and not st.deadman
    fake.set_buttons(0b11)
    assert sm.update().deadman
    always = HidSpaceMouse(opener=FakeHidDevice(), clock=clock, deadman_button=None)
    assert always.update().deadman


def test_full_scale_is_configurable(clock):
    fake = FakeHidDevice(combined=True)
    sm = HidSpaceMouse(opener=fake, clock=clock, full_scale_counts=500)
    fake.set_axes((0, -250, 0), (0, 0, 0))
    assert sm.update().axis("x") == pytest.approx(0.5)
    with pytest.raises(ValueError):
        HidSpaceMouse(opener=fake, full_scale_counts=0)


def test_many_reports_are_drained_and_the_last_wins(clock):
    fake = FakeHidDevice()
    sm = HidSpaceMouse(opener=fake, clock=clock)
    for k in range(10):
        fake.set_axes((k, 0, 0), (0, 0, 0))
    st = sm.update()
    assert st.raw[0] == 9 and not fake.reports and sm.reports == 20


def test_unplug_and_replug_without_restart(clock):
    fake = FakeHidDevice()
    sm = HidSpaceMouse(opener=fake, clock=clock, retry_s=1.0)
    fake.set_axes((100, 0, 0), (0, 0, 0))
    fake.set_buttons(1)
    assert sm.update().active
    fake.unplug()
    st = sm.update()
    assert st.fault and not st.valid and not st.deadman and st.axes == (0.0,) * 6
    assert "unplugged" in st.reason and not sm.connected and sm.disconnects == 1
    opens = fake.opens
    for _ in range(30):  # 3 s unplugged: one attempt per second, all failing
        clock.advance(0.1)
        assert sm.update().fault
    assert fake.opens == opens and "none found" in sm.last_error
    fake.replug()
    clock.advance(0.5)
    sm.update()
    clock.advance(0.5)
    st = sm.update()
    assert sm.connected and sm.connects == 2 and st.valid and not st.fault
    assert not st.deadman and st.axes == (0.0,) * 6  # nothing held over from before the unplug
    fake.set_axes((0, 0, 0), (0, 0, 35))
    fake.set_buttons(1)
    st = sm.update()
    assert st.active and st.axis("yaw") == pytest.approx(-0.1)


def test_not_present_at_start_then_plugged_in(clock):
    fake = FakeHidDevice()
    fake.unplug()
    sm = HidSpaceMouse(opener=fake, clock=clock, retry_s=0.5)
    st = sm.update()
    assert st.fault and "none found" in st.reason and "0x256F" in st.reason
    fake.replug()
    clock.advance(0.25)
    assert not sm.update().valid  # not yet time to retry
    clock.advance(0.25)
    assert sm.update().valid


def test_open_failure_is_reported(clock):
    class NoPermission(FakeHidDevice):
        def device(self):
            h = super().device()
            h.open_path = lambda path: (_ for _ in ()).throw(OSError("open failed"))
            return h

    sm = HidSpaceMouse(opener=NoPermission(), clock=clock)
    st = sm.update()
    assert st.fault and "open failed" in st.reason and "udev" in st.reason


def test_only_spacemice_are_picked(clock):
    mouse = FakeHidDevice(0x046D, 0xC077, path=b"/dev/hidraw-mouse", product_string="USB Optical Mouse")
    nav = FakeHidDevice(0x046D, 0xC626, path=b"/dev/hidraw-nav", product_string="SpaceNavigator")
    sm = HidSpaceMouse(opener=FakeHidBus(mouse, nav), clock=clock)
    assert [d["path"] for d in sm.enumerate()] == [b"/dev/hidraw-nav"]
    sm.update()
    assert sm.device_path == b"/dev/hidraw-nav" and sm.product == "SpaceNavigator"
    only_mouse = HidSpaceMouse(opener=FakeHidBus(mouse), clock=clock)
    assert only_mouse.update().fault


def test_multi_axis_interface_is_preferred(clock):
    kbd_if = FakeHidDevice(path=b"/dev/hidraw-a", usage_page=0x0C, usage=1)
    axis_if = FakeHidDevice(path=b"/dev/hidraw-b")
    sm = HidSpaceMouse(opener=FakeHidBus(kbd_if, axis_if), clock=clock)
    sm.update()
    assert sm.device_path == b"/dev/hidraw-b"


def test_explicit_path(clock):
    fake = FakeHidDevice(path=b"/dev/hidraw7")
    assert HidSpaceMouse(path="/dev/hidraw7", opener=fake, clock=clock).update().valid
    assert HidSpaceMouse(path="/dev/hidraw9", opener=fake, clock=clock).update().fault


def test_fake_handle_behaves_like_hidapi():
    fake = FakeHidDevice()
    h = fake.device()
    with pytest.raises(ValueError, match="not open"):
        h.read(64)
    h.open(0x256F, 0xC635)
    assert h.read(64, 10) == []
    fake.unplug()
    with pytest.raises(OSError, match="read error"):
        h.read(64)
    fake.replug()
    with pytest.raises(OSError):  # the old handle stays dead
        h.read(64)
    with pytest.raises(OSError, match="open failed"):
        fake.device().open(0x256F, 0x0001)


@pytest.mark.lab
def test_real_spacemouse_smoke():
    """Lab: a SpaceMouse on USB with read access to its /dev/hidraw* node (udev rule)."""
    sm = HidSpaceMouse()
    if not sm.enumerate():
        pytest.skip("no SpaceMouse connected")
    st = sm.update()
    assert sm.connected, sm.last_error
    assert st.valid and not st.fault and all(-1.0 <= a <= 1.0 for a in st.axes)
    sm.close()


def test_update_without_connect_leaves_reopening_to_the_caller(clock):
    """The service's frame reads with ``connect=False``; its thread calls ``connect()``."""
    fake = FakeHidDevice()
    sm = HidSpaceMouse(opener=fake, clock=clock, retry_s=1.0)
    st = sm.update(connect=False)
    assert st.fault and not sm.connected and fake.opens == 0 and sm.reconnect_due
    assert sm.connect() and not sm.reconnect_due
    fake.set_buttons(1)
    assert sm.update(connect=False).active
    fake.unplug()
    assert sm.update(connect=False).fault and not sm.reconnect_due  # retry_s not yet passed
    fake.replug()
    clock.advance(5.0)
    assert sm.reconnect_due and sm.update(connect=False).fault and fake.opens == 1  # never here
    assert sm.connect() and sm.update(connect=False).valid and sm.connects == 2


def test_report_rate_over_the_last_second(clock):
    fake = FakeHidDevice(combined=True)
    sm = HidSpaceMouse(opener=fake, clock=clock)
    sm.update()
    assert sm.rate_hz() == 0.0
    for k in range(11):  # one report every 0.1 s
        fake.set_axes((k, 0, 0))
        sm.update()
        clock.advance(0.1)
    assert sm.rate_hz(clock.now() - 0.1) == pytest.approx(10.0)
    clock.advance(2.0)
    assert sm.rate_hz() == 0.0  # a puck at rest reports nothing


def test_default_opener_is_hidapi():
    from drivers.crl.hid import default_opener
    opener = default_opener()  # hidapi is a dependency of the project
    assert callable(opener.enumerate) and callable(opener.device)
