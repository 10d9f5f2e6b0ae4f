"""Every device reaches the service (issue 17 item 6): the USB HID hand controller in the
buffer's ``hid`` slot (``pfma serve --hid``) and the F/T over CAN (``pfma serve --ft
can://...``), in simulated time on the service rig and end to end through ``pfma serve``."""

from __future__ import annotations

import os
import sys
import threading
import uuid

import can
import pytest

from bit3.buffer import Bit3Buffer
from bit3.client import Client
from bit3.layout import LINK_FAULT, LINK_OPEN, LINK_STALE, LINK_SYNCED, Severity
from drivers.crl import hid as hidmod
from drivers.crl.hid import HidSpaceMouse
from fakes.ft_can import FakeCanFtNode
from fakes.hid import FakeHidBus, FakeHidDevice
from sim.rig import SimRig
from tools.cli import main


def _texts(rig) -> list[str]:
    return [m.text for m in rig.reader.messages()]


def _hid(rig):
    s = rig.reader.read_inputs()
    return s, rig.layout.slot("hc", "hid"), rig.layout.slot("link", "hid_hand_controller")


@pytest.fixture
def hid_rig():
    fake = FakeHidDevice()
    rig = SimRig(prefix="pfma-test-")
    sm = HidSpaceMouse(opener=fake, clock=rig.clock, retry_s=0.5)
    assert rig.svc.hand.wire_hid(sm, "fake SpaceMouse", simulated=True, thread=False)
    yield rig, fake
    rig.svc.hand.close()
    rig.close()


def test_hid_fills_its_slot_goes_invalid_when_unplugged_and_recovers(hid_rig):
    rig, fake = hid_rig
    fake.set_axes((0, -175, 0), (0, 0, 35))  # device -y = forward 0.5; rz 35 -> yaw -0.1
    fake.set_buttons(1)  # left button: the deadman
    rig.run(0.1)
    s, i, link = _hid(rig)
    assert s.hc_valid[i] and s.hc_deadman[i] and not s.hc_fault[i]
    assert s.hc_axes[i][0] == 0.5 and s.hc_axes[i][5] == pytest.approx(-0.1) and s.hc_buttons[i] == 1
    assert s.hc_t_s[i] > 0
    assert s.link_status[link] == LINK_OPEN | LINK_SYNCED and s.link_records[link] == 3
    assert s.link_errors[link] == 0 and s.link_resyncs[link] == 0
    assert rig.svc.publish_stats()["devices"]["hid"]["samples"] == 8  # 80 Hz for 0.1 s
    assert "simulated HID hand controller: fake SpaceMouse" in _texts(rig)
    assert any("SIMULATED" in n for n in rig.svc.notes)

    fake.unplug()
    rig.run(0.05)
    s, i, link = _hid(rig)
    # a stale HID can command nothing: invalid, faulted, deadman released, axes zero
    assert not s.hc_valid[i] and s.hc_fault[i] and not s.hc_deadman[i] and not any(s.hc_axes[i])
    assert s.link_status[link] == LINK_FAULT | LINK_STALE and s.link_errors[link] == 1
    lost = [m for m in rig.reader.messages() if "lost" in m.text]
    assert [(m.text, m.severity) for m in lost] == [("simulated HID hand controller lost: slot invalid",
                                                     Severity.ERROR)]
    opens = fake.opens
    rig.run(0.3)  # unplugged: the retries (every 0.5 s) find nothing and open nothing
    assert fake.opens == opens and not _hid(rig)[0].hc_valid[i]

    fake.replug()
    rig.run(0.5)
    s, i, link = _hid(rig)
    assert s.hc_valid[i] and not s.hc_fault[i] and s.link_status[link] == LINK_OPEN | LINK_SYNCED
    assert not s.hc_deadman[i] and not any(s.hc_axes[i])  # nothing held over from before the unplug
    assert s.link_resyncs[link] == 1 and "simulated HID hand controller reconnected" in _texts(rig)
    fake.set_axes((0, 0, -350), (0, 0, 0))
    fake.set_buttons(1)
    rig.run(0.025)
    s, i, _ = _hid(rig)
    assert s.hc_deadman[i] and s.hc_axes[i][2] == 1.0


@pytest.mark.realtime
def test_the_frame_never_enumerates_or_opens_the_hid_its_thread_does():
    """``thread=True`` (pfma serve): the frame only reads; enumerate and open, which wait on
    udev and the kernel with real hidapi, happen in the reconnect thread."""
    calls: list[tuple[str, int]] = []

    class Spy(FakeHidDevice):
        def enumerate(self, vendor_id=0, product_id=0):
            calls.append(("enumerate", threading.get_ident()))
            return super().enumerate(vendor_id, product_id)

    fake = Spy()
    with SimRig(prefix="pfma-test-") as rig:
        task = rig.svc.hand
        try:
            sm = HidSpaceMouse(opener=fake, clock=rig.clock, retry_s=0.005)
            assert task.wire_hid(sm, "fake SpaceMouse", simulated=True, thread=True)
            main_thread = threading.get_ident()
            calls.clear()
            fake.unplug()
            rig.run(0.05)
            assert not _hid(rig)[0].hc_valid[rig.layout.slot("hc", "hid")]
            fake.replug()
            assert task.hid_reconnected.wait(30), sm.last_error
            rig.run(0.05)
            s, i, link = _hid(rig)
            assert s.hc_valid[i] and s.link_resyncs[link] == 1
            assert calls and all(tid != main_thread for _, tid in calls)
        finally:
            task.close()
        assert task._hid_thread is None and not sm.connected


def test_ft_over_can_virtual_in_simulated_time():
    """The F/T on python-can's virtual interface, fed by the fake CAN node, which answers
    between frames (``pump``): deterministic. The F/T slot carries the node's wrench."""
    channel = f"pfma-ft-{uuid.uuid4().hex}"
    with can.Bus(interface="virtual", channel=channel) as node_bus:
        with SimRig(prefix="pfma-test-", service_kw={"ft_port": f"can://virtual/{channel}?node=3"}) as rig:
            node = FakeCanFtNode(node_bus, node_id=3, clock=rig.clock)
            node.set_load((10.0, -2.0, 3.0), (0.5, 0.1, -0.2))
            rig.on_frame.append(lambda info: node.pump())
            try:
                assert rig.svc.ft.open_error is None and rig.svc.ft.can is not None
                rig.run(0.5)
                s = rig.reader.read_inputs()
                link = rig.layout.slot("link", "ft_sensor")
                assert list(s.ft_force_n) == [10.0, -2.0, 3.0]  # 16 counts per N: exact
                assert list(s.ft_torque_nm) == [0.5, 0.1, -0.2]
                assert tuple(s.ft_counts) == node.sent[-1][1] == (160, -32, 48, 100, 20, -40)
                assert s.link_status[link] == LINK_OPEN | LINK_SYNCED and s.link_bad[link] == 0
                # one record per F/T slot (80 Hz; the first from the frame after, the slot's
                # retry), the answer to the request before it; one request left outstanding
                assert s.link_records[link] == 40 == len(node.sent) - 1
                assert "F/T on CAN node 3" in _texts(rig)
                node.set_load((-4.0, 0.0, 1.0), (0.0, 0.0, 0.25))
                rig.run(0.05)
                s = rig.reader.read_inputs()
                assert list(s.ft_force_n) == [-4.0, 0.0, 1.0] and s.ft_torque_nm[2] == 0.25
                node.mute_replies = 10**6  # the node stops answering: the slot goes stale, once said
                rig.run(0.3)
                s = rig.reader.read_inputs()
                assert s.link_status[link] == LINK_OPEN | LINK_STALE and s.link_bad[link] > 0
                said = [t for t in _texts(rig) if t.startswith("F/T CAN")]
                assert said == ["F/T CAN node 3: no answer within 0.1 s"]
            finally:
                rig.svc.ft.close()


def _gone(name: str) -> bool:
    return not os.path.exists(f"/dev/shm/{name}")


@pytest.mark.realtime
def test_serve_hid_fake_says_simulated_and_fills_the_slot(capsys):
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    try:
        assert main(["serve", "--hid", "fake", "--duration", "0.5", "--buffer", name]) == 0
        cap = capsys.readouterr()
        assert "simulated HID hand controller: fake SpaceMouse (SIMULATED" in cap.out + cap.err
        with Client.attach(name) as c:
            s = c.read_inputs()
            i, link = c.layout.slot("hc", "hid"), c.layout.slot("link", "hid_hand_controller")
            assert s.hc_valid[i] and not s.hc_fault[i] and not s.hc_deadman[i]  # a fake never holds the deadman
            assert s.link_status[link] == LINK_OPEN | LINK_SYNCED
            assert any(m.text.startswith("simulated HID hand controller") for m in c.messages())
    finally:
        Bit3Buffer.unlink(name)


@pytest.mark.parametrize("value", ["foo", "hidraw0", "AUTO", ""])
def test_serve_hid_bad_value_is_a_usage_error(value, capsys):
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    assert main(["serve", "--hid", value, "--duration", "0.1", "--buffer", name]) == 2
    err = capsys.readouterr().err
    assert f"--hid {value}: expected auto" in err and "fake" in err and "/dev/hidraw" in err
    assert "Traceback" not in err and _gone(name)


def test_serve_hid_auto_without_a_device_or_without_hidapi(monkeypatch, capsys):
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    monkeypatch.setattr(hidmod, "default_opener", lambda: FakeHidBus())  # hidapi lists nothing
    assert main(["serve", "--hid", "auto", "--duration", "0.1", "--buffer", name]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--hid auto: no SpaceMouse found" in err and "--hid fake" in err
    assert _gone(name)
    mouse = FakeHidDevice(0x046D, 0xC077, path=b"/dev/hidraw-mouse")  # a plain mouse is no SpaceMouse
    monkeypatch.setattr(hidmod, "default_opener", lambda: FakeHidBus(mouse))
    assert main(["serve", "--hid", "auto", "--duration", "0.1", "--buffer", name]) == 1
    assert "no SpaceMouse found" in capsys.readouterr().err

    def missing():
        raise ImportError("No module named 'hid'")
    monkeypatch.setattr(hidmod, "default_opener", missing)
    assert main(["serve", "--hid", "auto", "--duration", "0.1", "--buffer", name]) == 1
    err = capsys.readouterr().err
    assert "--hid auto: hidapi is not installed (No module named 'hid')" in err and "Traceback" not in err
    assert _gone(name)


@pytest.mark.realtime
def test_serve_hid_auto_takes_the_first_spacemouse(monkeypatch, capsys):
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    mouse = FakeHidDevice(0x046D, 0xC077, path=b"/dev/hidraw-mouse")
    nav = FakeHidDevice(0x046D, 0xC626, path=b"/dev/hidraw-nav", product_string="SpaceNavigator")
    monkeypatch.setattr(hidmod, "default_opener", lambda: FakeHidBus(mouse, nav))
    try:
        assert main(["serve", "--hid", "auto", "--duration", "0.3", "--buffer", name]) == 0
        out = capsys.readouterr()
        assert "HID hand controller: /dev/hidraw-nav (SpaceNavigator)" in out.err
        assert "simulated" not in out.err.lower() and nav.opens == 1 and mouse.opens == 0
    finally:
        Bit3Buffer.unlink(name)


def test_serve_hid_path_that_is_not_there(capsys):
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    assert main(["serve", "--hid", "/dev/hidraw-pfma-none", "--duration", "0.1", "--buffer", name]) == 1
    err = capsys.readouterr().err
    assert "--hid /dev/hidraw-pfma-none: no such device" in err and "Traceback" not in err and _gone(name)


@pytest.mark.realtime
def test_serve_ft_on_can_virtual_end_to_end(capsys):
    """``pfma serve --ft can://virtual/CH`` in this process (python-can's virtual bus does
    not cross processes), the fake CAN node answering from its Notifier thread."""
    channel = f"pfma-ft-{uuid.uuid4().hex}"
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    with can.Bus(interface="virtual", channel=channel) as node_bus, FakeCanFtNode(node_bus, node_id=5) as node:
        node.set_load((1.0, 2.0, 3.0), (0.1, 0.2, 0.3))
        try:
            assert main(["serve", "--ft", f"can://virtual/{channel}?node=5", "--duration", "1",
                         "--buffer", name]) == 0
            with Client.attach(name) as c:
                s = c.read_inputs()
                link = c.layout.slot("link", "ft_sensor")
                assert list(s.ft_force_n) == [1.0, 2.0, 3.0] and list(s.ft_torque_nm) == [0.1, 0.2, 0.3]
                assert s.link_records[link] > 20 and s.link_bad[link] == 0
        finally:
            Bit3Buffer.unlink(name)


@pytest.mark.parametrize("url, status, text", [
    ("", 2, "--ft: an empty URL"),
    ("can://virtual", 2, "is not of the form can://INTERFACE/CHANNEL"),
    ("can:virtual/ft", 2, "is not of the form can://INTERFACE/CHANNEL"),
    ("can://virtual/ft?node=16", 2, "a CAN F/T node id is 0..15"),
    ("can://virtual/ft?node=x", 2, "a CAN F/T node id is 0..15"),
    ("can://virtual/ft?rate=5", 2, "unknown option 'rate'"),
    ("can://socketcna/can0", 1, "python-can has no interface 'socketcna'; did you mean socketcan"),
    ("can://socketcan/pfma-no-such-if", 1, "cannot open CAN channel 'pfma-no-such-if' on socketcan"),
    ("/dev/pfma-no-such-tty", 1, "F/T port /dev/pfma-no-such-tty: [Errno 2] could not open port"),
])
def test_serve_bad_ft_url(url, status, text, capsys):
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    assert main(["serve", "--ft", url, "--duration", "0.1", "--buffer", name]) == status
    err = capsys.readouterr().err
    assert text in err and "Traceback" not in err and _gone(name)


def test_serve_ft_given_twice(capsys):
    assert main(["serve", "--ft", "can://virtual/a", "--ft-port", "/dev/ttyUSB0", "--buffer", "unused"]) == 2
    assert "given twice with different URLs" in capsys.readouterr().err


def test_serve_ft_can_without_python_can(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "can", None)  # import can -> ImportError
    monkeypatch.setitem(sys.modules, "can.interfaces", None)
    name = "pfma-serve-" + uuid.uuid4().hex[:6]
    assert main(["serve", "--ft", "can://socketcan/can0", "--duration", "0.1", "--buffer", name]) == 1
    err = capsys.readouterr().err
    assert "--ft can://socketcan/can0: python-can is not installed" in err and "Traceback" not in err
    assert _gone(name)
