"""CAN F/T transport on python-can's virtual bus (same process), plus a lab socketcan test."""

from __future__ import annotations

import os
import socket
import uuid

import can
import pytest

from drivers.serial_ft.can_ft import CAN_LAYOUT, CanFtSensor, frame_id
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


def _socketcan_channel():
    if not hasattr(socket, "AF_CAN"):
        return None
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError:
        return None
    for ch in ("vcan0", "can0"):
        if os.path.exists(f"/sys/class/net/{ch}"):
            return ch
    return None


@pytest.mark.lab
def test_socketcan_round_trip_with_fake_node():
    """Lab: needs a vcan0 (``ip link add vcan0 type vcan; ip link set vcan0 up``) or can0
    with nothing else answering node 7."""
    ch = _socketcan_channel()
    if ch is None:
        pytest.skip("no AF_CAN socket or no can0/vcan0 interface")
    with can.Bus(interface="socketcan", channel=ch) as host, can.Bus(interface="socketcan", channel=ch) as nb:
        with FakeCanFtNode(nb, node_id=7) as node:
            node.set_load((1.0, 2.0, 3.0), (0.1, 0.2, 0.3))
            assert CanFtSensor(host, 7, timeout_s=0.5).read().counts == (16, 32, 48, 20, 40, 60)
