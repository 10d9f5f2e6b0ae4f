"""CAN F/T transport on python-can's virtual bus (same process); on vcan0 where the kernel offers
it (skipped otherwise, saying why); on a real can0 in the lab."""

from __future__ import annotations

import os
import re
import select
import shutil
import socket
import subprocess
import uuid

import can
import pytest

from drivers.serial_ft.can_ft import (CAN_LAYOUT, CanFtSensor, CanUrl, CanUrlError, frame_id, is_can_url,
                                      open_can_url, parse_can_url)
from fakes.ft_can import FakeCanFtNode
from pfma.clock import SimClock
from pfma.errors import ConfigError, LinkError, PfmaTimeoutError


@pytest.fixture
def can_pair():
    channel = f"ft-{uuid.uuid4().hex}"
    with can.Bus(interface="virtual", channel=channel) as host, can.Bus(interface="virtual", channel=channel) as nb:
        yield host, nb


def test_layout_identifiers():
    assert [frame_id(3, k) for k in ("request", "forces", "torques", "ack")] == [0x130, 0x131, 0x132, 0x133]
    assert all(row.dlc <= 8 for row in CAN_LAYOUT.values())
    with pytest.raises(ConfigError):
        CanFtSensor(None, 16)


@pytest.mark.realtime
def test_read_pairs_two_frames_into_one_reading(can_pair):
    host, nb = can_pair
    clock = SimClock(5.0)
    with FakeCanFtNode(nb, node_id=3) as node:
        node.set_load((10.0, -2.0, 3.0), (0.5, 0.1, -0.2))
        s = CanFtSensor(host, 3, clock=clock, timeout_s=1.0)
        r = s.read()
        assert r.counts == node.sent[-1][1] == (160, -32, 48, 100, 20, -40)
        assert r.force_n == (10.0, -2.0, 3.0) and r.torque_nm == (0.5, 0.1, -0.2)
        assert r.t_s == 5.0 and r.seq == 0 and s.stats().records == 1


@pytest.mark.realtime
def test_bias_stack_over_can(can_pair):
    host, nb = can_pair
    with FakeCanFtNode(nb, node_id=1) as node:
        node.set_load((4.0, 0, 0), (0, 0, 0))
        s = CanFtSensor(host, 1, timeout_s=1.0)
        assert s.bias() == 1
        assert s.read().counts == (0,) * 6
        node.set_load((6.0, 0, 0), (0, 0, 0))
        assert s.read().force_n[0] == 2.0
        assert s.unbias() == 0 and s.read().force_n[0] == 6.0
        s.bias(), s.bias()
        assert s.clear_bias() == 0


@pytest.mark.realtime
def test_other_nodes_and_mispaired_frames(can_pair):
    host, nb = can_pair
    with FakeCanFtNode(nb, node_id=2) as node:
        s = CanFtSensor(host, 5, timeout_s=0.05)  # nobody is node 5
        with pytest.raises(PfmaTimeoutError, match="CAN node 5"):
            s.read()
        s2 = CanFtSensor(host, 2, timeout_s=1.0)
        node.break_pairing = 1
        with pytest.raises(LinkError, match="do not pair"):
            s2.read()
        assert s2.stats().bad_records == 1
        node.mute_replies = 1
        s2.timeout_s = 0.05
        with pytest.raises(PfmaTimeoutError):
            s2.read()
        s2.timeout_s = 1.0
        assert s2.read().status == 0  # a late answer to a muted request cannot be mistaken


def test_read_records_never_waits_and_pairs_answers_one_call_later(can_pair):
    """The service's F/T slot: collect the answer to the previous request, send the next;
    the node answers between calls (``pump``), so this runs in simulated time."""
    host, nb = can_pair
    clock = SimClock(1.0)
    node = FakeCanFtNode(nb, node_id=4)
    node.set_load((2.0, 0.0, -1.0), (0.0, 0.25, 0.0))
    s = CanFtSensor(host, 4, clock=clock, timeout_s=0.1)
    assert s.read_records() == [] and node.pump() == 1  # the first call only asks
    clock.advance(0.0125)
    (r,) = s.read_records()
    assert r.force_n == (2.0, 0.0, -1.0) and r.torque_nm == (0.0, 0.25, 0.0) and r.t_s == 1.0125
    node.mute_replies = 1
    assert node.pump() == 1  # ... and asked again: that request is lost
    clock.advance(0.05)
    assert s.read_records() == [] and node.pump() == 0  # still waiting: no second request
    clock.advance(0.06)
    assert s.read_records() == [] and s.stats().bad_records == 1  # > 0.1 s: counted, asked anew
    assert s.errors == 1 and s.last_error == "no answer within 0.1 s"
    node.pump()
    node.break_pairing = 1
    (r,) = s.read_records()  # the answer to the repeated request; a mis-paired one next
    node.pump()
    assert s.read_records() == [] and s.stats().bad_records == 2 and "do not pair" in s.last_error
    node.pump()
    assert len(s.read_records()) == 1 and s.stats().records == 3
    assert s.record_due() is False and s.stop_stream() == []


def test_an_answer_after_stop_is_ignored(can_pair):
    host, nb = can_pair
    node = FakeCanFtNode(nb, node_id=1)
    s = CanFtSensor(host, 1, clock=SimClock(), timeout_s=0.1)
    s.read_records()
    s.stop_stream()
    node.pump()
    assert s.read_records() == [] and s.stats().records == 0  # the forgotten answer; asked again
    node.pump()
    assert len(s.read_records()) == 1


@pytest.mark.parametrize("url, spec", [
    ("can://socketcan/can0", CanUrl("socketcan", "can0", 0, None)),
    ("CAN://virtual/ft?node=15", CanUrl("virtual", "ft", 15, None)),
    ("can://pcan/PCAN_USBBUS1?bitrate=1000000&node=2", CanUrl("pcan", "PCAN_USBBUS1", 2, 1000000)),
    ("can://slcan//dev/ttyACM0", CanUrl("slcan", "/dev/ttyACM0", 0, None)),
])
def test_can_urls(url, spec):
    assert is_can_url(url) and parse_can_url(url) == spec


@pytest.mark.parametrize("url, text", [
    ("can://socketcan", "not of the form"), ("can://", "not of the form"), ("can:socketcan/can0", "not of the form"),
    ("can:///can0", "not of the form"), ("can://virtual/ft?node=16", "0..15"), ("can://virtual/ft?node=-1", "0..15"),
    ("can://virtual/ft?bitrate=fast", "bit rate"), ("can://virtual/ft?bitrate=0", "bit rate"),
    ("can://virtual/ft?id=3", "unknown option 'id'"), ("can://virtual/ft?node", "bad query field"),
])
def test_malformed_can_urls(url, text):
    with pytest.raises(CanUrlError, match=re.escape(text)):
        parse_can_url(url)


def test_serial_urls_are_not_can():
    assert not any(is_can_url(u) for u in ("/dev/ttyUSB0", "socket://127.0.0.1:5000", "COM3", "loop://"))


@pytest.mark.realtime
def test_open_can_url_opens_and_closes_its_bus():
    channel = f"ft-{uuid.uuid4().hex}"
    with can.Bus(interface="virtual", channel=channel) as nb:
        with FakeCanFtNode(nb, node_id=2) as node:
            node.set_load((3.0, 0, 0), (0, 0, 0))
            s = open_can_url(f"can://virtual/{channel}?node=2", timeout_s=1.0)
            assert s.owns_bus and s.node_id == 2 and s.read().force_n == (3.0, 0.0, 0.0)
            s.close()
            assert not s.owns_bus
            s.close()  # idempotent
    with pytest.raises(ConfigError, match="no interface 'virtaul'; did you mean virtual"):
        open_can_url("can://virtaul/x")
    with pytest.raises(CanUrlError):
        open_can_url("can://virtual")


# -- socketcan: vcan0 in CI when the kernel offers it; real can0 in the lab -----------------

def _vcan0() -> tuple[str | None, str]:
    """("vcan0", "") when a vcan0 is up or could be made so (as root: ``ip link add dev vcan0
    type vcan; ip link set up vcan0``), else (None, why not)."""
    if not hasattr(socket, "AF_CAN"):
        return None, "this Python's socket module has no AF_CAN"
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as err:
        return None, f"the kernel offers no AF_CAN sockets ({err})"
    exists = os.path.exists("/sys/class/net/vcan0")
    up = exists and "UP" in _ip_flags("vcan0")
    if up:
        return "vcan0", ""
    if os.geteuid() != 0:
        return None, ("vcan0 is down and this is not root" if exists else
                      "no vcan0 interface, and not root to create it (ip link add dev vcan0 type vcan)")
    ip = shutil.which("ip")
    if ip is None:
        return None, "no vcan0 interface, and no ip command (iproute2) to create it"
    if not exists:
        made = subprocess.run([ip, "link", "add", "dev", "vcan0", "type", "vcan"], capture_output=True, text=True)
        if made.returncode != 0:
            return None, f"cannot create vcan0 (no vcan kernel module?): {made.stderr.strip() or made.returncode}"
    upped = subprocess.run([ip, "link", "set", "up", "vcan0"], capture_output=True, text=True)
    if upped.returncode != 0:
        return None, f"cannot bring vcan0 up: {upped.stderr.strip() or upped.returncode}"
    return "vcan0", ""


def _ip_flags(ifname: str) -> str:
    try:
        with open(f"/sys/class/net/{ifname}/flags") as f:
            return "UP" if int(f.read(), 16) & 1 else ""
    except (OSError, ValueError):
        return ""


@pytest.mark.realtime
def test_socketcan_vcan0_round_trip_with_fake_node():
    """The driver on a kernel CAN socket (vcan0), both ways: the blocking read and the
    service's read_records. Runs wherever the kernel offers vcan (CI: .ci/run sets it up
    as root); skipped, saying exactly why, where it does not."""
    ch, why = _vcan0()
    if ch is None:
        pytest.skip(f"vcan0 not available: {why}")
    with can.Bus(interface="socketcan", channel=ch) as host, can.Bus(interface="socketcan", channel=ch) as nb:
        with FakeCanFtNode(nb, node_id=9) as node:  # its Notifier thread answers
            node.set_load((1.0, 2.0, 3.0), (0.1, 0.2, 0.3))
            s = CanFtSensor(host, 9, clock=SimClock(), timeout_s=5.0)
            assert s.read().counts == (16, 32, 48, 20, 40, 60)
            assert s.read_records() == []  # asks
            recs: list = []
            for _ in range(4):  # the two answer frames; each wait bounded, none timed
                if not select.select([host.fileno()], [], [], 5.0)[0]:
                    break
                recs = s.read_records()
                if recs:
                    break
            assert [r.force_n for r in recs] == [(1.0, 2.0, 3.0)]


@pytest.mark.lab
def test_socketcan_can0_round_trip_with_fake_node():
    """Lab: a real can0 (its bus terminated, nothing else answering node 7)."""
    if not os.path.exists("/sys/class/net/can0"):
        pytest.skip("no can0 interface")
    with can.Bus(interface="socketcan", channel="can0") as host, can.Bus(interface="socketcan", channel="can0") as nb:
        with FakeCanFtNode(nb, node_id=7) as node:
            node.set_load((1.0, 2.0, 3.0), (0.1, 0.2, 0.3))
            assert CanFtSensor(host, 7, timeout_s=0.5).read().counts == (16, 32, 48, 20, 40, 60)
