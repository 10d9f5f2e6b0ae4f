"""VMIVME-4940 resolver-to-digital driver, against the fake through a FakeRack and
against a minimal register model written here from R1 alone."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.rtd import RtdStatus, Vmivme4940
from fakes.rack import FakeRack
from fakes.rtd import FakeVmivme4940
from fakes.testing import assert_register_writes, fake_rack_of_kinds
from pfma.clock import SimClock
from pfma.errors import BusError

BASE = 0x0100
LSB = 2 * math.pi / 16384


@pytest.fixture
def rig():
    rack = FakeRack(clock=SimClock())
    fake = rack.add(BASE, FakeVmivme4940(name="rtd1", clock=rack.clock))
    return rack, fake, Vmivme4940(rack, BASE, name="rtd1")


def _wrap_err(a: float, b: float) -> float:
    """a - b wrapped into [-pi, pi)."""
    return (a - b + math.pi) % (2 * math.pi) - math.pi


@pytest.mark.parametrize("angle", [0.0, 1e-5, 0.5, math.pi, 4.0, 2 * math.pi - 1e-4])
def test_angle_round_trip_within_one_lsb(rig, angle):
    rack, fake, rtd = rig
    fake.set_angle_rad(2, angle)
    got = rtd.read_angles_rad()[2]
    assert 0 <= got < 2 * math.pi
    assert 0 <= _wrap_err(angle, got) < LSB  # truncating converter: reads at or just below


@pytest.mark.parametrize("angle, expected", [(-0.25, 2 * math.pi - 0.25), (2 * math.pi + 0.3, 0.3),
                                             (4 * math.pi, 0.0), (-2 * math.pi, 0.0),
                                             (-1e-9, 2 * math.pi - LSB)])
def test_angles_wrap_into_zero_two_pi(rig, angle, expected):
    rack, fake, rtd = rig
    fake.set_angle_rad(0, angle)
    got = rtd.read_angle_rad(0)
    assert 0 <= got < 2 * math.pi
    assert abs(_wrap_err(got, expected)) < LSB


def test_fourteen_bit_quantisation(rig):
    rack, fake, rtd = rig
    fake.set_angle_rad(0, 1234 * LSB + 0.4 * LSB)
    fake.set_angle_rad(1, 1234 * LSB + 0.99 * LSB)
    fake.set_counts(2, 16383)
    fake.set_counts(3, 16384 + 5)  # wraps
    assert rtd.read_counts() == (1234, 1234, 16383, 5)
    # bits 15..14 of every channel word read 0 (right-justified 14-bit)
    assert rack.read16(BASE + 4) == 0x3FFF
    angles = rtd.read_angles_rad()
    assert angles[2] == pytest.approx(16383 * LSB)
    assert rtd.counts_per_rev == 16384 and rtd.lsb_rad == pytest.approx(LSB)


def test_read_angles_fills_preallocated_array(rig):
    rack, fake, rtd = rig
    fake.set_angles_rad([0.1, 0.2, 0.3, 0.4])
    out = np.zeros(4)
    res = rtd.read_angles_rad(out)
    assert res is out
    assert np.all(np.abs(out - [0.1, 0.2, 0.3, 0.4]) < LSB)


def test_status_clean(rig):
    rack, fake, rtd = rig
    st = rtd.status()
    assert st == RtdStatus(faults=(False,) * 4, reference_present=True, raw=0x0010)
    assert st.ok


def test_loss_of_signal_sets_fault_and_freezes_channel(rig):
    rack, fake, rtd = rig
    fake.set_angles_rad([1.0, 2.0, 3.0, 4.0])
    fake.inject("loss_of_signal", channel=2)
    fake.set_angles_rad([1.5, 2.5, 3.5, 4.5])
    st = rtd.status()
    assert st.faults == (False, False, True, False)
    assert st.reference_present and not st.ok
    a = rtd.read_angles_rad()
    assert abs(a[2] - 3.0) < LSB  # frozen
    assert abs(a[1] - 2.5) < LSB  # the others keep tracking
    fake.clear("loss_of_signal")
    assert rtd.status().ok
    assert abs(rtd.read_angle_rad(2) - 3.5) < LSB


def test_loss_of_signal_zero_mode_and_two_channels(rig):
    rack, fake, rtd = rig
    fake.set_angles_rad([1.0, 2.0, 3.0, 4.0])
    fake.inject("loss_of_signal", channel=0, mode="zero")
    fake.inject("loss_of_signal", channel=3)
    assert rtd.status().faults == (True, False, False, True)
    assert rtd.read_counts()[0] == 0


def test_reference_loss_faults_every_channel(rig):
    rack, fake, rtd = rig
    fake.set_angle_rad(1, 1.0)
    fake.set_reference(False)
    fake.set_angle_rad(1, 2.0)
    st = rtd.status()
    assert st.faults == (True,) * 4 and not st.reference_present
    assert abs(rtd.read_angle_rad(1) - 1.0) < LSB
    fake.set_reference(True)
    assert rtd.status().ok and abs(rtd.read_angle_rad(1) - 2.0) < LSB


def test_hold_freezes_and_release_tracks(rig):
    rack, fake, rtd = rig
    fake.set_angle_rad(1, 1.0)
    start = len(fake.traffic)
    rtd.hold(1)
    fake.set_angle_rad(1, 2.0)
    assert abs(rtd.read_angle_rad(1) - 1.0) < LSB
    rtd.release(1)
    assert abs(rtd.read_angle_rad(1) - 2.0) < LSB
    rtd.hold()
    rtd.release()
    assert_register_writes(fake, [("CONTROL", 0x0002), ("CONTROL", 0x0000),
                                  ("CONTROL", 0x000F), ("CONTROL", 0x0000)], since=start)


def test_fail_led_bit(rig):
    rack, fake, rtd = rig
    rtd.hold(0)
    rtd.set_fail_led(False)
    assert not fake.fail_led_on and rtd.read_control() == 0x4001
    rtd.set_fail_led(True)
    assert fake.fail_led_on and rtd.read_control() == 0x0001


def test_stuck_bit_visible(rig):
    rack, fake, rtd = rig
    fake.set_counts(0, 0)
    fake.set_counts(1, 0x3FFF)
    fake.inject("stuck_bit", register="CH0", bit=13, value=1)
    fake.inject("stuck_bit", register=0x02, bit=0, value=0)
    assert rtd.read_counts()[:2] == (0x2000, 0x3FFE)
    fake.clear("stuck_bit")
    assert rtd.read_counts()[:2] == (0, 0x3FFF)


def test_bus_error_names_board_register_address(rig):
    rack, fake, rtd = rig
    fake.inject("no_answer")
    with pytest.raises(BusError) as exc:
        rtd.read_counts()
    msg = str(exc.value)
    assert "rtd1" in msg and "CH0" in msg and "0x0100" in msg
    with pytest.raises(BusError, match=r"rtd1 STATUS at A16 0x0108"):
        rtd.status()
    with pytest.raises(BusError, match=r"rtd1 CONTROL at A16 0x010A"):
        rtd.hold(3)


def test_default_name_and_missing_board():
    rack = FakeRack(clock=SimClock())
    rtd = Vmivme4940(rack, 0x0200)
    with pytest.raises(BusError, match=r"vmivme4940@0x0200 CH0 at A16 0x0200"):
        rtd.read_counts()


@pytest.mark.parametrize("bad", [-1, 4, 1.0, "0"])
def test_bad_channel_is_value_error(rig, bad):
    rack, fake, rtd = rig
    with pytest.raises(ValueError, match=r"rtd1 \(A16 0x0100\): channel"):
        rtd.read_angle_rad(bad)


@pytest.mark.parametrize("whole", [False, True], ids=["analog-boards", "whole-rack"])
def test_from_config_rack(whole):
    if whole:
        rack = FakeRack.from_config(clock=SimClock())
    else:
        rack = fake_rack_of_kinds(("vmivme4940", "vmivme4100", "dvme611"), clock=SimClock())
    for name, base in (("rtd1", 0x0100), ("rtd2", 0x0200)):
        rack[name].set_angles_rad([0.1, 1.1, 2.1, 3.1])
        got = Vmivme4940(rack, base, name=name).read_angles_rad()
        assert np.all(np.abs(got - [0.1, 1.1, 2.1, 3.1]) < LSB)


# -- the driver against a minimal model of R1, written from the table in the reference ----
class MiniRdc:
    """R1 in a few lines: CH0..3 right-justified 14-bit words, STATUS 0x08, CONTROL 0x0A."""

    def __init__(self, base: int) -> None:
        self.base, self.words = base, {0: 0, 2: 0, 4: 0, 6: 0, 8: 0x10, 0xA: 0}
        self.writes: list[tuple[int, int]] = []

    def read16(self, addr: int) -> int:
        off = addr - self.base
        if off not in self.words:
            raise BusError(addr, 16, "read")
        return self.words[off]

    def write16(self, addr: int, value: int) -> None:
        self.writes.append((addr, value))
        if addr - self.base == 0xA:
            self.words[0xA] = value

    def read8(self, addr: int) -> int:
        raise BusError(addr, 8, "read")

    def write8(self, addr: int, value: int) -> None:
        raise BusError(addr, 8, "write")

    def read_block16(self, addr: int, n: int) -> list[int]:
        return [self.read16(addr + 2 * i) for i in range(n)]

    def write_block16(self, addr: int, words) -> None:
        for i, w in enumerate(words):
            self.write16(addr + 2 * i, w)


def test_driver_needs_only_the_register_model():
    bus = MiniRdc(0x0200)
    bus.words.update({0: 0, 2: 4096, 4: 8192, 6: 16383, 8: 0b10100})
    rtd = Vmivme4940(bus, 0x0200, name="mini")
    assert rtd.read_counts() == (0, 4096, 8192, 16383)
    assert np.allclose(rtd.read_angles_rad(), [0, math.pi / 2, math.pi, 2 * math.pi - LSB])
    st = rtd.status()
    assert st.faults == (False, False, True, False) and st.reference_present
    rtd.hold(0, 3)
    assert bus.writes == [(0x020A, 0x0009)]
