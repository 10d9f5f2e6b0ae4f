"""VMIVME-4100 analog output driver, against the fake through a FakeRack and against a
minimal register model written here from R2 alone."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.dac import Vmivme4100
from fakes.dac import FakeVmivme4100
from fakes.rack import FakeRack
from fakes.testing import assert_register_writes, fake_rack_of_kinds, register_writes
from pfma.clock import SimClock
from pfma.errors import BusError

BASE = 0xD000
LSB = 20.0 / 4096


@pytest.fixture
def rig():
    rack = FakeRack(clock=SimClock())
    fake = rack.add(BASE, FakeVmivme4100(name="dac", clock=rack.clock))
    return rack, fake, Vmivme4100(rack, BASE, name="dac")


def test_construction_touches_nothing(rig):
    rack, fake, dac = rig
    assert fake.traffic == []
    assert not dac.outputs_enabled and not fake.outputs_connected
    assert np.all(dac.shadow_counts == 0x800) and np.all(dac.shadow_volts == 0.0)


def test_enable_sequence_writes_0xc100_once(rig):
    rack, fake, dac = rig
    dac.enable_outputs()
    expected = [(f"DAC[{n}]", 0x800) for n in range(16)] + [("CTRL", 0xC100)]
    assert_register_writes(fake, expected)
    assert [v for _, v in register_writes(fake)].count(0xC100) == 1
    assert dac.outputs_enabled and fake.outputs_connected and not fake.fail_led_on
    assert np.all(fake.output_volts_all() == 0.0)


def test_enable_reloads_values_written_before(rig):
    rack, fake, dac = rig
    dac.write_volts(4, 2.5)
    assert fake.output_volts(4) == 0.0  # still disconnected
    dac.enable_outputs()
    assert fake.output_volts(4) == pytest.approx(2.5, abs=LSB / 2)


def test_outputs_are_zero_volts_while_disconnected(rig):
    rack, fake, dac = rig
    for ch in range(16):
        dac.write_volts(ch, -9.0 + ch)
    assert np.all(fake.output_volts_all() == 0.0) and fake.output_volts(15) == 0.0
    assert fake.codes[3] == dac.shadow_counts[3] != 0x800  # the latch holds the code


def test_shadow_tracks_writes(rig):
    rack, fake, dac = rig
    dac.enable_outputs()
    dac.write_volts(3, 2.5)
    dac.write_counts(7, 0x123)
    dac.write_volts(0, 10.0)
    dac.write_volts(1, -10.0)
    assert np.array_equal(dac.shadow_counts, fake.codes)
    assert dac.shadow_counts[[0, 1, 7]].tolist() == [4095, 0, 0x123]
    assert dac.shadow_volts[3] == pytest.approx(2.5, abs=LSB / 2)
    assert np.allclose(fake.output_volts_all(), dac.shadow_volts)
    assert fake.output_volts(0) == pytest.approx(10.0 - LSB)


def test_write_volts_all(rig):
    rack, fake, dac = rig
    dac.enable_outputs()
    v = np.linspace(-9.5, 9.5, 16)
    dac.write_volts_all(v)
    assert np.all(np.abs(fake.output_volts_all() - v) <= LSB / 2)
    with pytest.raises(ValueError, match="channel 15"):
        dac.write_volts_all(np.r_[v[:15], 11.0])
    assert np.all(np.abs(fake.output_volts_all() - v) <= LSB / 2)  # nothing written


def test_disable_drives_zero_then_disconnects(rig):
    rack, fake, dac = rig
    dac.enable_outputs()
    dac.write_volts_all(np.full(16, 5.0))
    start = len(fake.traffic)
    dac.disable_outputs()
    assert_register_writes(fake, [(f"DAC[{n}]", 0x800) for n in range(16)] + [("CTRL", 0xC000)],
                           since=start)
    assert not dac.outputs_enabled and not fake.outputs_connected
    assert np.all(fake.codes == 0x800) and np.all(dac.shadow_volts == 0.0)
    assert np.all(fake.output_volts_all() == 0.0)


def test_zero_all(rig):
    rack, fake, dac = rig
    dac.enable_outputs()
    dac.write_volts(2, 3.0)
    dac.zero_all()
    assert np.all(fake.output_volts_all() == 0.0) and fake.outputs_connected


def test_board_is_write_only_reads_return_control_bits(rig):
    rack, fake, dac = rig
    dac.write_counts(5, 0xABC)
    assert rack.read16(BASE + 10) == 0x0000
    dac.enable_outputs()
    assert {rack.read16(BASE + 2 * n) for n in range(16)} == {0x4100}
    assert dac.read_control() == 0x4100 and dac.outputs_connected()
    dac.disable_outputs()
    assert dac.read_control() == 0x4000 and not dac.outputs_connected()


@pytest.mark.parametrize("volts", [10.001, -10.5, math.nan, math.inf])
def test_out_of_range_volts_is_value_error(rig, volts):
    rack, fake, dac = rig
    with pytest.raises(ValueError, match=r"dac.*channel 2, A16 0xD004"):
        dac.write_volts(2, volts)
    assert fake.traffic == []


def test_clamp_flag(rig):
    rack, fake, dac = rig
    dac.write_volts(0, 12.0, clamp=True)
    dac.write_volts(1, -99.0, clamp=True)
    assert dac.shadow_counts[:2].tolist() == [4095, 0]
    with pytest.raises(ValueError):
        dac.write_volts(0, math.nan, clamp=True)  # NaN is never clamped into a command


@pytest.mark.parametrize("channel, code", [(16, 0), (-1, 0), (0, 4096), (0, -1), (0, 1.5)])
def test_bad_channel_or_code_is_value_error(rig, channel, code):
    rack, fake, dac = rig
    with pytest.raises(ValueError, match="dac"):
        dac.write_counts(channel, code)


def test_bus_error_names_board_register_address(rig):
    rack, fake, dac = rig
    fake.inject("no_answer")
    with pytest.raises(BusError, match=r"write16 dac DAC\[5\] at A16 0xD00A"):
        dac.write_volts(5, 1.0)
    with pytest.raises(BusError, match=r"dac CTRL at A16 0xD000"):
        dac.read_control()
    assert dac.shadow_counts[5] == 0x800  # a failed write does not reach the shadow


class _FailOne:
    """A bus that loses writes to one address (a flaky slot), else forwards."""

    def __init__(self, bus, *bad: int) -> None:
        self.bus, self.bad = bus, set(bad)
        self.read16, self.read8, self.write8 = bus.read16, bus.read8, bus.write8

    def write16(self, addr: int, value: int) -> None:
        if addr in self.bad:
            raise BusError(addr, 16, "write")
        self.bus.write16(addr, value)

    def read_block16(self, addr: int, n: int) -> list[int]:
        return [self.read16(addr + 2 * i) for i in range(n)]

    def write_block16(self, addr: int, words) -> None:
        for i, w in enumerate(words):
            self.write16(addr + 2 * i, w)


def test_disable_is_fail_safe_on_a_bus_error(rig):
    rack, fake, dac = rig
    dac.enable_outputs()
    dac.write_volts_all(np.full(16, 3.0))
    flaky = Vmivme4100(_FailOne(rack, BASE + 6), BASE, name="dac")
    with pytest.raises(BusError, match=r"dac DAC\[3\] at A16 0xD006"):
        flaky.disable_outputs()
    assert not fake.outputs_connected  # the control word still went out
    assert np.all(np.delete(fake.codes, 3) == 0x800)


def test_zeroing_reaches_every_answering_channel_past_two_adjacent_bad_slots(rig):
    """Once the board has answered, a failing word is skipped and the write goes on: two
    lost slots in a row must not leave the channels after them at their old voltage."""
    rack, fake, dac = rig
    dac.enable_outputs()
    dac.write_volts_all(np.full(16, 3.0))
    flaky = Vmivme4100(_FailOne(rack, BASE + 6, BASE + 8), BASE, name="dac")
    with pytest.raises(BusError, match=r"dac DAC\[3\] at A16 0xD006"):
        flaky.zero_all()
    assert np.all(np.delete(fake.codes, [3, 4]) == 0x800)


def test_stuck_latch_bit_shows_on_output(rig):
    rack, fake, dac = rig
    dac.enable_outputs()
    fake.inject("stuck_bit", register="DAC[2]", bit=11, value=0)
    dac.write_volts(2, 5.0)  # code 3072 = 0xC00 -> 0x400 with b11 stuck at 0
    assert fake.codes[2] == 0x400 and dac.shadow_counts[2] == 0xC00
    assert fake.output_volts(2) == pytest.approx(-5.0)


@pytest.mark.parametrize("whole", [False, True], ids=["analog-boards", "whole-rack"])
def test_from_config_rack(whole):
    if whole:
        rack = FakeRack.from_config(clock=SimClock())
    else:
        rack = fake_rack_of_kinds(("vmivme4940", "vmivme4100", "dvme611"), clock=SimClock())
    dac = Vmivme4100(rack, 0xD000, name="dac")
    dac.enable_outputs()
    dac.write_volts(6, -4.0)
    assert rack["dac"].output_volts(6) == pytest.approx(-4.0, abs=LSB / 2)


# -- the driver against a minimal model of R2, written from the reference alone ------------
class MiniDac:
    """R2 in a few lines: D15 = 1 -> control (D14..D8), else DAC[off/2] = D11..D0;
    any read returns the control bits; 8-bit accesses are bus errors."""

    def __init__(self, base: int) -> None:
        self.base, self.ctrl, self.dac = base, 0, [0x800] * 16

    def write16(self, addr: int, value: int) -> None:
        off = addr - self.base
        if not 0 <= off < 0x20 or off % 2:
            raise BusError(addr, 16, "write")
        if value & 0x8000:
            self.ctrl = value & 0x7F00
        else:
            self.dac[off // 2] = value & 0x0FFF

    def read16(self, addr: int) -> int:
        return self.ctrl

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
    bus = MiniDac(0xD000)
    dac = Vmivme4100(bus, 0xD000, name="mini")
    assert bus.ctrl == 0
    dac.write_volts(1, 0.0)
    dac.write_volts(2, 10.0)
    dac.write_volts(3, -10.0)
    dac.write_volts(4, 5.0)
    assert bus.dac[1:5] == [0x800, 0xFFF, 0x000, 0xC00] and bus.ctrl == 0
    dac.enable_outputs()
    assert bus.ctrl == 0x4100 and dac.outputs_connected()
    dac.disable_outputs()
    assert bus.ctrl == 0x4000 and bus.dac == [0x800] * 16
