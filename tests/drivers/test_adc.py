"""DVME-611 A/D driver, against the fake through a FakeRack (1 us simulated time per
access, 4 us conversions) and against a minimal register model written here from R3."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.adc import Dvme611
from drivers.adc.registers import DVME611
from fakes.adc import FakeDvme611
from fakes.rack import FakeRack
from fakes.testing import assert_register_writes, fake_rack_of_kinds
from pfma.clock import SimClock
from pfma.errors import BoardError, BusError

BASE = 0xC000
LSB = 20.0 / 4096
EOC, BUSY = 0x8000, 0x0100


@pytest.fixture
def per_channel(monkeypatch):
    """The register table of a board without the scan mode: the driver scans channel by
    channel (START, EOC, DATA with auto-increment), the fallback sequence."""
    monkeypatch.setitem(DVME611.constants, "scan_mode", False)


@pytest.fixture
def rig():
    rack = FakeRack(clock=SimClock())
    fake = rack.add(BASE, FakeDvme611(name="adc", clock=rack.clock))
    return rack, fake, Dvme611(rack, BASE, name="adc")


def _csr_reads(fake, since=0):
    return [v for op, w, off, v in fake.traffic[since:] if op == "r" and off == 0x00]


def test_single_conversion(rig):
    rack, fake, adc = rig
    fake.set_input_volts(5, 3.3)
    t0 = rack.clock.now()
    code = adc.read_counts(5)
    assert code == math.floor((3.3 + 10.0) / LSB)
    assert_register_writes(fake, [("CSR", 5), ("START", 0)])
    polls = _csr_reads(fake)
    assert any(v & BUSY for v in polls) and polls[-1] & EOC  # busy first, then EOC
    assert rack.clock.now() - t0 >= 4e-6  # the conversion took its model time
    assert adc.read_volts(5) == pytest.approx(3.3, abs=LSB)


@pytest.mark.parametrize("volts, code", [(-10.0, 0), (0.0, 0x800), (10.0 - LSB, 0xFFF),
                                         (10.0, 0xFFF), (-12.0, 0), (12.0, 0xFFF),
                                         (-LSB / 2, 0x7FF)])
def test_offset_binary_clip_and_floor(rig, volts, code):
    rack, fake, adc = rig
    fake.set_input_volts(0, volts)
    assert adc.read_counts(0) == code


@pytest.mark.usefixtures("per_channel")
def test_scan_32_channels_auto_increment(rig):
    rack, fake, adc = rig
    v = np.linspace(-9.87, 9.93, 32)
    fake.set_inputs_volts(v)
    got = adc.scan_volts()
    assert got.shape == (32,) and np.all(np.abs(got - v) <= LSB)
    # one CSR write (channel 0 + auto-increment), then only STARTs: the board advanced itself
    writes = [(off, val) for op, w, off, val in fake.traffic if op == "w"]
    assert writes[0] == (0x00, 0x0020)
    assert writes[1:] == [(0x02, 0)] * 32
    assert fake.conversions == 32


def test_scan_fills_preallocated_array(rig):
    rack, fake, adc = rig
    fake.set_inputs_volts(np.full(32, 1.0))
    out = np.zeros(32, dtype=np.int64)
    assert adc.scan(out) is out
    assert np.all(out == math.floor(11.0 / LSB))
    vout = np.zeros(32)
    assert adc.scan_volts(vout) is vout and np.allclose(vout, 1.0, atol=LSB)


def test_single_read_after_scan_leaves_auto_increment(rig):
    rack, fake, adc = rig
    fake.set_input_volts(9, -2.0)
    adc.scan()
    assert adc.read_volts(9) == pytest.approx(-2.0, abs=LSB)
    assert fake.csr == 9  # single mode again


@pytest.mark.usefixtures("per_channel")
def test_busy_stuck_raises_board_error_not_hang(rig):
    rack, fake, adc = rig
    fake.inject("busy_stuck")
    start = len(fake.traffic)
    with pytest.raises(BoardError) as exc:
        adc.read_counts(7)
    msg = str(exc.value)
    assert "busy stuck" in msg and "adc" in msg and "channel 7" in msg and "0xC000" in msg
    assert len(_csr_reads(fake, start)) >= adc.max_polls  # bounded by polls and wall time
    exact = Dvme611(rack, BASE, name="adc", min_wait_s=0)
    start = len(fake.traffic)
    with pytest.raises(BoardError, match=r"after 64 polls$"):
        exact.read_counts(7)
    assert len(_csr_reads(fake, start)) == exact.max_polls  # min_wait_s=0: polls only
    with pytest.raises(BoardError, match="busy stuck converting channel 0"):
        adc.scan()
    fake.clear("busy_stuck")
    fake.set_input_volts(7, 1.0)
    assert adc.read_volts(7) == pytest.approx(1.0, abs=LSB)


def test_missing_eoc_raises_no_eoc(rig):
    rack, fake, adc = rig
    fake.inject("stuck_bit", register="CSR", bit=15, value=0)
    small = Dvme611(rack, BASE, name="adc", max_polls=8, min_wait_s=0)
    with pytest.raises(BoardError, match=r"adc: no EOC converting channel 3: CSR at A16 0xC000"):
        small.read_counts(3)


def test_stuck_data_bit_visible(rig):
    rack, fake, adc = rig
    fake.set_input_volts(2, 0.0)  # 0x800
    fake.inject("stuck_bit", register="DATA", bit=0, value=1)
    assert adc.read_counts(2) == 0x801
    fake.inject("stuck_bit", register="DATA", bit=11, value=0)
    assert adc.read_counts(2) == 0x001


@pytest.mark.usefixtures("per_channel")
def test_bus_error_names_board_register_address(rig):
    rack, fake, adc = rig
    fake.inject("no_answer")
    with pytest.raises(BusError) as exc:
        adc.read_counts(4)
    msg = str(exc.value)
    assert "adc" in msg and "CSR" in msg and "channel 4" in msg and "0xC000" in msg
    with pytest.raises(BusError, match=r"adc CSR \(channel 0\) at A16 0xC000"):
        adc.scan()


def test_bus_error_on_data_register():
    rack = FakeRack(clock=SimClock())
    fake = rack.add(BASE, FakeDvme611(name="adc", clock=rack.clock))

    class NoData:  # the DATA register does not answer
        read8, write8, write16 = rack.read8, rack.write8, rack.write16

        def read16(self, addr):
            if addr == BASE + 4:
                raise BusError(addr, 16, "read")
            return rack.read16(addr)

    with pytest.raises(BusError, match=r"read16 adc DATA \(channel 1\) at A16 0xC004"):
        Dvme611(NoData(), BASE, name="adc").read_counts(1)
    assert fake.conversions == 1


@pytest.mark.parametrize("bad", [-1, 32, 2.0, None])
def test_bad_channel_is_value_error(rig, bad):
    rack, fake, adc = rig
    with pytest.raises(ValueError, match=r"adc \(A16 0xC000\): channel"):
        adc.read_counts(bad)
    assert fake.traffic == []


def test_constructor_arguments(rig):
    rack, fake, adc = rig
    with pytest.raises(ValueError):
        Dvme611(rack, BASE, max_polls=0)
    with pytest.raises(ValueError):
        Dvme611(rack, BASE, min_wait_s=-1.0)
    five = Dvme611(rack, BASE, range_volts=5.0)
    assert five.volts_from_counts(0xFFF) == pytest.approx(5.0 - 10.0 / 4096)
    assert five.name == "dvme611@0xC000"


@pytest.mark.parametrize("whole", [False, True], ids=["analog-boards", "whole-rack"])
def test_from_config_rack(whole):
    if whole:
        rack = FakeRack.from_config(clock=SimClock())
    else:
        rack = fake_rack_of_kinds(("vmivme4940", "vmivme4100", "dvme611"), clock=SimClock())
    v = np.linspace(-5, 5, 32)
    rack["adc"].set_inputs_volts(v)
    assert np.all(np.abs(Dvme611(rack, 0xC000, name="adc").scan_volts() - v) <= LSB)


# -- the driver against a minimal model of R3, written from the reference alone ------------
class MiniAdc:
    """R3 in a few lines: CSR (b4..0 channel, b5 auto-increment, b8 BUSY, b15 EOC), START,
    DATA (reading clears EOC and auto-increments). Busy for two CSR reads after START."""

    def __init__(self, base: int, codes) -> None:
        self.base, self.codes = base, list(codes)
        self.csr, self.data, self.busy_reads, self.eoc = 0, 0, 0, False

    def write16(self, addr: int, value: int) -> None:
        off = addr - self.base
        if off == 0:
            self.csr = value & 0x3F
        elif off == 2:
            self.busy_reads, self.eoc = 2, False
            self.data = self.codes[self.csr & 0x1F]

    def read16(self, addr: int) -> int:
        off = addr - self.base
        if off == 0:
            if self.busy_reads:
                self.busy_reads -= 1
                self.eoc = self.busy_reads == 0
                return self.csr | 0x100
            return self.csr | (0x8000 if self.eoc else 0)
        if off == 4:
            self.eoc = False
            if self.csr & 0x20:
                self.csr = (self.csr & ~0x1F) | ((self.csr + 1) & 0x1F)
            return self.data
        raise BusError(addr, 16, "read")

    def read8(self, addr: int) -> int:
        raise BusError(addr, 8, "read")

    def write8(self, addr: int, value: int) -> None:
        raise BusError(addr, 8, "write")

    def read_block16(self, addr: int, n: int) -> list[int]:
        return [self.read16(addr + 2 * i) for i in range(n)]

    def write_block16(self, addr: int, words) -> None:
        for i, w in enumerate(words):
            self.write16(addr + 2 * i, w)


@pytest.mark.usefixtures("per_channel")
def test_driver_needs_only_the_register_model():
    codes = [(n * 131) % 4096 for n in range(32)]
    adc = Dvme611(MiniAdc(0xC000, codes), 0xC000, name="mini")
    assert adc.read_counts(17) == codes[17]
    assert adc.scan().tolist() == codes
    assert adc.read_volts(0) == pytest.approx(-10.0)


@pytest.mark.usefixtures("per_channel")
def test_auto_increment_out_of_step_is_board_error():
    class NoIncrement(MiniAdc):
        def read16(self, addr):
            self.csr &= ~0x20  # this board ignores auto-increment
            return super().read16(addr)

    adc = Dvme611(NoIncrement(0xC000, range(32)), 0xC000, name="mini")
    with pytest.raises(BoardError, match=r"mini: CSR at A16 0xC000 selects channel 0, expected 1"):
        adc.scan()


# -- the scan mode (R3 as assumed: START b0 = 1, results in SCAN) ---------------------------
def test_scan_mode_is_one_start_and_one_block_of_scan(rig):
    rack, fake, adc = rig
    v = np.linspace(-9.87, 9.93, 32)
    fake.set_inputs_volts(v)
    t0 = rack.clock.now()
    got = adc.scan_volts()
    assert np.all(np.abs(got - v) <= LSB)
    assert [(off, val) for op, w, off, val in fake.traffic if op == "w"] == [(0x02, 0x0001)]
    assert [off for op, w, off, val in fake.traffic if op == "r" and off >= 0x40] == \
        list(range(0x40, 0x80, 2))  # every SCAN word once, in order
    assert rack.clock.now() - t0 >= 32 * 4e-6  # the scan took its model time
    assert fake.scans == 1


def test_scan_mode_errors_name_the_scan(rig):
    rack, fake, adc = rig
    fake.inject("busy_stuck")
    exact = Dvme611(rack, BASE, name="adc", min_wait_s=0)
    with pytest.raises(BoardError, match=r"adc: busy stuck scanning channels 0..31: CSR at A16 "
                                         r"0xC000 = 0x0100 after 2048 polls$"):
        exact.scan()
    fake.clear()
    fake.inject("no_answer")
    with pytest.raises(BusError, match=r"write16 adc START \(scan\) at A16 0xC002"):
        adc.scan()


def test_scan_block_error_names_the_scan_word():
    class NoScan:  # the SCAN buffer does not answer
        def __init__(self, bus):
            self.bus = bus
            self.read16, self.write16 = bus.read16, bus.write16

        def read_block16(self, addr, n):
            raise BusError(addr, 16, "read")

    rack = FakeRack(clock=SimClock())
    rack.add(BASE, FakeDvme611(name="adc", clock=rack.clock))
    with pytest.raises(BusError, match=r"read16 adc SCAN\[0\] \(scan\) at A16 0xC040"):
        Dvme611(NoScan(rack), BASE, name="adc").scan()
