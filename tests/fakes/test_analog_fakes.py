"""The analog fakes at register level (raw bus accesses, no drivers): R1-R3 semantics,
decoding, timing on the simulated clock, faults and the shared test helpers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fakes.adc import FakeDvme611
from fakes.board import NoAnswer
from fakes.dac import FakeVmivme4100
from fakes.rack import FakeRack
from fakes.rtd import FakeVmivme4940
from fakes.testing import (StuckBits, assert_register_writes, fake_rack_of_kinds, format_traffic,
                           register_offset)
from pfma.clock import SimClock
from pfma.errors import BusError


@pytest.fixture
def rack():
    r = FakeRack(clock=SimClock())
    r.add(0x0100, FakeVmivme4940(name="rtd1", clock=r.clock))
    r.add(0xD000, FakeVmivme4100(name="dac", clock=r.clock))
    r.add(0xC000, FakeDvme611(name="adc", clock=r.clock))
    return r


# -- common decoding ---------------------------------------------------------------------
@pytest.mark.parametrize("addr", [0x0100, 0x0101, 0xD000, 0xD001, 0xC000, 0xC005])
def test_eight_bit_accesses_are_bus_errors(rack, addr):
    with pytest.raises(BusError, match=f"0x{addr:04X}"):
        rack.read8(addr)
    with pytest.raises(BusError):
        rack.write8(addr, 0)


@pytest.mark.parametrize("addr", [0x010C, 0x011E, 0xC008, 0xC03E, 0xC080, 0xC0FE])
def test_offsets_without_a_register_are_not_decoded(rack, addr):
    with pytest.raises(BusError, match="not decoded"):
        rack.read16(addr)


@pytest.mark.parametrize("addr", [0x0120, 0xD020, 0xC100])
def test_windows_end_where_the_table_says(rack, addr):
    with pytest.raises(BusError, match="no board decodes"):
        rack.read16(addr)


def test_odd_word_address_is_bus_error(rack):
    with pytest.raises(BusError, match=r"dac DAC\[1\] at A16 0xD003"):
        rack.write16(0xD003, 0)


def test_unknown_fault_is_refused():
    for fake in (FakeVmivme4940(), FakeVmivme4100(), FakeDvme611()):
        with pytest.raises(ValueError, match="unknown fault"):
            fake.inject("melted")


def test_no_answer_names_board_register_address(rack):
    rack["adc"].inject("no_answer")
    with pytest.raises(BusError, match=r"read16 adc DATA at A16 0xC004"):
        rack.read16(0xC004)
    rack["adc"].clear()
    assert rack.read16(0xC006) == 0x0611


# -- VMIVME-4940 ----------------------------------------------------------------------------
def test_rtd_channel_words_and_ignored_writes(rack):
    rtd = rack["rtd1"]
    rtd.set_angle_rad(3, math.pi)
    assert rack.read16(0x0106) == 8192
    rack.write16(0x0106, 0x1234)  # angle registers are read-only; the write is ignored
    rack.write16(0x0108, 0xFFFF)  # so is STATUS
    assert rack.read16(0x0106) == 8192 and rack.read16(0x0108) == 0x0010
    assert rtd.counts(3) == 8192


def test_rtd_control_stores_hold_and_led_bits_only(rack):
    rtd = rack["rtd1"]
    rack.write16(0x010A, 0xFFFF)
    assert rack.read16(0x010A) == 0x400F and not rtd.fail_led_on
    rtd.reset()
    assert rack.read16(0x010A) == 0 and rtd.fail_led_on


def test_rtd_hold_latches_on_the_rising_edge(rack):
    rtd = rack["rtd1"]
    rtd.set_counts(0, 100)
    rack.write16(0x010A, 0x0001)
    rtd.set_counts(0, 200)
    rack.write16(0x010A, 0x0001)  # still held: no re-latch
    assert rack.read16(0x0100) == 100
    rack.write16(0x010A, 0x0000)
    assert rack.read16(0x0100) == 200


def test_rtd_fault_parameters_are_checked():
    rtd = FakeVmivme4940()
    with pytest.raises(ValueError, match="channel"):
        rtd.inject("loss_of_signal")
    with pytest.raises(ValueError):
        rtd.inject("loss_of_signal", channel=4)
    with pytest.raises(ValueError, match="mode"):
        rtd.inject("loss_of_signal", channel=0, mode="explode")
    with pytest.raises(KeyError):
        rtd.inject("stuck_bit", register="CH9", bit=0, value=1)
    with pytest.raises(ValueError, match="not finite"):
        rtd.set_angle_rad(0, math.nan)
    assert rtd.faults == {}


# -- VMIVME-4100 ----------------------------------------------------------------------------
def test_dac_d15_selects_control_at_any_offset(rack):
    dac = rack["dac"]
    assert dac.control == 0 and np.all(dac.codes == 0x800)  # reset state (R2)
    rack.write16(0xD01E, 0xC100)  # last channel's address, but D15 = 1
    assert dac.outputs_connected and dac.codes[15] == 0x800
    rack.write16(0xD01E, 0x7ABC)  # D15 = 0: DAC[15] gets D11..D0, D14..D12 ignored
    assert dac.codes[15] == 0xABC and dac.control == 0x4100
    assert dac.output_volts(15) == pytest.approx(-10 + 20 * 0xABC / 4096)


def test_dac_reads_return_control_only(rack):
    rack.write16(0xD004, 0x0FFF)
    rack.write16(0xD000, 0xFF00)  # every control bit
    assert rack.read16(0xD004) == 0x7F00
    assert rack.read16(0xD012) == 0x7F00


def test_dac_reset_disconnects(rack):
    dac = rack["dac"]
    rack.write16(0xD000, 0xC100)
    rack.write16(0xD002, 0x0FFF)
    dac.reset()
    assert not dac.outputs_connected and dac.fail_led_on
    assert np.all(dac.output_volts_all() == 0.0) and np.all(dac.codes == 0x800)
    with pytest.raises(ValueError):
        dac.output_volts(16)


# -- DVME-611 -------------------------------------------------------------------------------
def test_adc_conversion_timing_on_the_board_clock():
    clock = SimClock()
    adc = FakeDvme611(clock=clock)
    adc.set_input_volts(4, 5.0)
    adc.write16(0x00, 4)
    adc.write16(0x02, 0)
    assert adc.read16(0x00) == 0x0104  # BUSY, channel 4
    clock.advance(3.9e-6)
    assert adc.read16(0x00) & 0x8100 == 0x0100
    clock.advance(0.2e-6)
    assert adc.read16(0x00) == 0x8004  # EOC, not busy
    assert adc.read16(0x04) == 3072
    assert adc.read16(0x00) == 0x0004  # DATA read cleared EOC


def test_adc_data_while_busy_returns_previous_result():
    clock = SimClock()
    adc = FakeDvme611(clock=clock)
    adc.set_inputs_volts(np.array([-5.0, 5.0] + [0.0] * 30))
    adc.write16(0x00, 0x20)  # channel 0, auto-increment
    adc.write16(0x02, 0)
    clock.advance(5e-6)
    assert adc.read16(0x04) == 1024 and adc.csr == 0x21  # advanced to channel 1
    adc.write16(0x02, 0)
    assert adc.read16(0x04) == 1024 and adc.csr == 0x21  # busy: old result, no advance
    clock.advance(5e-6)
    assert adc.read16(0x00) & 0x8000
    assert adc.read16(0x04) == 3072 and adc.csr == 0x22


def test_adc_start_clears_eoc_and_scan_buffer_keeps_results():
    clock = SimClock()
    adc = FakeDvme611(clock=clock)
    adc.set_input_volts(31, 9.0)
    adc.write16(0x00, 31)
    adc.write16(0x02, 0)
    clock.advance(4e-6)
    assert adc.read16(0x00) & 0x8000
    adc.write16(0x02, 0)
    assert not adc.read16(0x00) & 0x8000
    clock.advance(4e-6)
    assert adc.read16(0x40 + 62) == math.floor(19.0 / (20 / 4096))
    assert adc.read16(0x40) == 0  # channel 0 never converted


def test_adc_gain_bits_read_zero_and_writes_to_read_only_ignored():
    adc = FakeDvme611()
    adc.write16(0x00, 0xFFFF)
    assert adc.read16(0x00) == 0x403F  # channel 31, auto-increment, IE; gain 00; no EOC/BUSY
    adc.write16(0x06, 0)
    adc.write16(0x04, 0x0FFF)
    assert adc.read16(0x06) == 0x0611 and adc.read16(0x04) == 0
    assert adc.read16(0x02) == 0
    with pytest.raises(NoAnswer):
        adc.write16(0x08, 0)


def test_adc_noise_is_seeded_and_deterministic():
    def run(seed):
        clock = SimClock()
        adc = FakeDvme611(clock=clock)
        adc.noise_counts = 2.0
        adc.seed_noise(seed)
        codes = []
        for _ in range(50):
            adc.write16(0x02, 0)
            clock.advance(4e-6)
            codes.append(adc.read16(0x04))
        return codes

    a, b = run(7), run(7)
    assert a == b and len(set(a)) > 1 and all(abs(c - 0x800) < 20 for c in a)


def test_adc_input_validation():
    adc = FakeDvme611()
    with pytest.raises(ValueError):
        adc.set_input_volts(32, 0.0)
    with pytest.raises(ValueError, match="32"):
        adc.set_inputs_volts([0.0] * 31)


# -- helpers ---------------------------------------------------------------------------------
def test_register_offset_names_and_offsets():
    assert register_offset(FakeVmivme4100.description, "DAC[3]") == 6
    assert register_offset(FakeVmivme4940.description, "CONTROL") == 0x0A
    assert register_offset(FakeDvme611.description, "SCAN[31]") == 0x7E
    assert register_offset(FakeDvme611.description, 0x04) == 0x04
    with pytest.raises(ValueError):
        register_offset(FakeDvme611.description, 0x100)


def test_stuck_bits_combine():
    s = StuckBits(FakeVmivme4940.description)
    assert not s
    s.add("CH1", 0, 1)
    s.add(2, 15, 0)
    assert s.apply(2, 0x8000) == 0x0001 and s.apply(0, 0x8000) == 0x8000
    with pytest.raises(ValueError):
        s.add("CH1", 16, 1)
    with pytest.raises(ValueError):
        s.add("CH1", 1, 2)


def test_assert_register_writes_reports_names(rack):
    rack.write16(0xD000, 0xC100)
    assert_register_writes(rack["dac"], [(0, 0xC100)])
    with pytest.raises(AssertionError, match=r"(?s)expected:.*CTRL.*0xC000.*actual:.*0xC100"):
        assert_register_writes(rack["dac"], [("CTRL", 0xC000)])
    rack.write16(0xD002, 0x0123)
    text = format_traffic(rack["dac"])
    assert "w16 +0x00 CTRL       = 0xC100" in text and "w16 +0x02 DAC[1]     = 0x0123" in text
    rack.write16(0x010A, 0x0001)
    assert format_traffic(rack["rtd1"]) == "w16 +0x0A CONTROL    = 0x0001"


@pytest.mark.parametrize("whole", [False, True], ids=["analog-boards", "whole-rack"])
def test_fake_rack_from_config_uses_these_fakes(whole):
    if whole:
        rack = FakeRack.from_config(clock=SimClock())
    else:
        rack = fake_rack_of_kinds(("vmivme4940", "vmivme4100", "dvme611"), clock=SimClock())
        assert sorted(rack.boards) == ["adc", "dac", "rtd1", "rtd2"]
    assert rack["adc"].clock is rack.clock
    assert isinstance(rack["rtd1"], FakeVmivme4940) and isinstance(rack["rtd2"], FakeVmivme4940)
    assert isinstance(rack["dac"], FakeVmivme4100) and isinstance(rack["adc"], FakeDvme611)
    assert rack.read16(0xC006) == 0x0611 and rack.read16(0xD000) == 0


# -- the ADC's scan mode (START b0 = 1, R3 as assumed) -----------------------------------------
def _code(volts: float) -> int:
    return math.floor((volts + 10.0) / (20 / 4096))


def test_adc_scan_mode_timing_busy_eoc_and_results():
    clock = SimClock()
    adc = FakeDvme611(clock=clock)
    adc.set_inputs_volts(np.linspace(-8.0, 8.0, 32))
    adc.write16(0x00, 0x0025)  # channel 5, auto-increment: left alone by the scan
    adc.write16(0x02, 0x0001)
    assert adc.read16(0x00) == 0x0125  # BUSY, no EOC
    clock.advance(4e-6 * 3)
    assert adc.read16(0x40 + 2 * 2) == _code(np.linspace(-8.0, 8.0, 32)[2])  # SCAN[2] at 12 us
    assert adc.read16(0x40 + 2 * 3) == 0  # SCAN[3] lands at 16 us
    clock.advance(4e-6 * 29 - 1e-9)
    assert adc.read16(0x00) & 0x8100 == 0x0100  # still busy just before 128 us
    clock.advance(2e-9)
    assert adc.read16(0x00) == 0x8025  # EOC, channel and auto-increment unchanged
    v = np.linspace(-8.0, 8.0, 32)
    assert [adc.read16(0x40 + 2 * k) for k in range(32)] == [_code(x) for x in v]
    assert adc.read16(0x04) == _code(v[31]) and adc.scans == 1 and adc.conversions == 1


def test_adc_scan_samples_each_channel_at_its_own_conversion_time():
    """Channel k is sampled 4k us after START: an input change at 10 us reaches channels
    3..31 (sampled at 12 us on) but not 0..2 (sampled at 0, 4, 8 us)."""
    clock = SimClock()
    adc = FakeDvme611(clock=clock)
    adc.set_inputs_volts(np.full(32, -5.0))
    adc.write16(0x02, 0x0001)
    clock.advance(10e-6)
    adc.set_inputs_volts(np.full(32, 5.0))
    clock.advance(200e-6)
    got = [adc.read16(0x40 + 2 * k) for k in range(32)]
    assert got == [_code(-5.0)] * 3 + [_code(5.0)] * 29


def test_adc_scan_block_read_through_the_rack(rack):
    adc = rack["adc"]
    adc.set_inputs_volts(np.linspace(-1.0, 1.0, 32))
    rack.write16(0xC002, 0x0001)
    rack.clock.advance(200e-6)
    t0, before = rack.clock.now(), len(adc.traffic)
    words = rack.read_block16(0xC040, 32)
    assert words == [_code(x) for x in np.linspace(-1.0, 1.0, 32)]
    assert rack.clock.now() - t0 == pytest.approx(32 * rack.access_time_s)  # per word
    assert [(op, off) for op, _, off, _ in adc.traffic[before:]] == [("r", 0x40 + 2 * k) for k in range(32)]


def test_adc_scan_block_read_while_busy_is_word_by_word(rack):
    """During a scan each word is read at its own time: words of channels finished by then
    hold the new results, the rest the old ones."""
    adc = rack["adc"]
    adc.set_inputs_volts(np.full(32, 3.0))
    rack.write16(0xC002, 0x0001)  # 1 us per access: the block starts at t0 + 1 us
    words = rack.read_block16(0xC040, 32)  # word k read at t0 + (k + 2) us
    done = [k for k in range(32) if (k + 2) * 1e-6 >= (k + 1) * 4e-6]
    assert done == [] and words == [0] * 32
    rack.clock.advance(60e-6)
    words = rack.read_block16(0xC040, 32)
    assert words[:10] == [_code(3.0)] * 10 and words[-1] == 0


def test_adc_busy_stuck_scan_never_ends():
    clock = SimClock()
    adc = FakeDvme611(clock=clock)
    adc.inject("busy_stuck")
    adc.write16(0x02, 0x0001)
    clock.advance(1e-3)
    assert adc.read16(0x00) & 0x8100 == 0x0100
