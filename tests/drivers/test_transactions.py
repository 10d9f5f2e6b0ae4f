"""The drivers use the fewest bus transactions the register model allows (issue 16 item 2).

Counted with the spy (``drivers.bus.spy``) over the fake rack: a block transfer is one
access line, so the number of lines is the number of bus transactions.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivers.adc import Dvme611
from drivers.adc.registers import CSR, DVME611, SCAN, SCAN_CMD, START
from drivers.bus import open_bus
from drivers.bus.spy import SpyBus
from drivers.dac import Vmivme4100
from drivers.rtd import Vmivme4940
from pfma.clock import SimClock
from pfma.errors import BusError

LSB = 20.0 / 4096


@pytest.fixture
def spy() -> SpyBus:
    bus = open_bus("spy+fake", clock=SimClock())
    bus.logger = None
    return bus


def _lines(spy: SpyBus):
    return [(a.op, a.addr, a.block, a.count) for a in spy.log]


def test_dac_write_all_is_one_block_write(spy):
    dac = Vmivme4100(spy, 0xD000, name="dac")
    dac.enable_outputs()
    spy.clear()
    volts = np.linspace(-9.0, 9.0, 16)
    dac.write_volts_all(volts)
    assert _lines(spy) == [("write", 0xD000, True, 16)]
    assert np.allclose(spy.bus["dac"].output_volts_all(), volts, atol=LSB)
    spy.clear()
    dac.zero_all()
    assert _lines(spy) == [("write", 0xD000, True, 16)]
    assert list(spy.bus["dac"].codes) == [0x800] * 16


def test_rtd_board_read_is_one_block_read(spy):
    spy.bus["rtd2"].set_counts(3, 0x1234)
    spy.bus["rtd2"].set_reference(False)
    rtd = Vmivme4940(spy, 0x0200, name="rtd2")
    counts, status = rtd.read_counts_status()
    assert _lines(spy) == [("read", 0x0200, True, 5)]  # CH0..CH3 and STATUS
    assert counts[3] == 0x1234 and not status.reference_present and all(status.faults)
    spy.clear()
    assert rtd.read_counts()[3] == 0x1234
    assert _lines(spy) == [("read", 0x0200, True, 4)]


def test_rtd_block_agrees_with_single_reads(spy):
    spy.bus["rtd1"].set_angles_rad([0.5, 1.5, 2.5, 3.5])
    spy.bus["rtd1"].inject("loss_of_signal", channel=2)
    rtd = Vmivme4940(spy, 0x0100, name="rtd1")
    counts, status = rtd.read_counts_status()
    assert counts == tuple(rtd.read_channel_counts(ch) for ch in range(4))
    assert status == rtd.status() and status.faults == (False, False, True, False)


def test_adc_scan_is_one_start_polls_and_one_block_read(spy):
    assert DVME611.constants["scan_mode"] is True  # the table selects the scan mode
    v = np.linspace(-9.5, 9.5, 32)
    spy.bus["adc"].set_inputs_volts(v)
    adc = Dvme611(spy, 0xC000, name="adc")
    got = adc.scan_volts()
    assert np.all(np.abs(got - v) <= LSB)
    lines = _lines(spy)
    assert lines[0] == ("write", 0xC000 + START.offset, False, 1)
    assert spy.log[0].value == SCAN_CMD.mask
    assert lines[-1] == ("read", 0xC000 + SCAN.offset, True, 32)
    polls = lines[1:-1]
    assert polls and all(p == ("read", 0xC000 + CSR.offset, False, 1) for p in polls)
    # the scan takes 32 x 4 us; at 1 us per simulated access the polls cover it
    assert len(polls) >= 128
    assert spy.bus["adc"].scans == 1 and spy.bus["adc"].conversions == 1


def test_adc_per_channel_fallback_is_selected_by_the_table(spy, monkeypatch):
    monkeypatch.setitem(DVME611.constants, "scan_mode", False)
    v = np.linspace(-5.0, 5.0, 32)
    spy.bus["adc"].set_inputs_volts(v)
    adc = Dvme611(spy, 0xC000, name="adc")
    assert np.all(np.abs(adc.scan_volts() - v) <= LSB)
    assert not any(a.block for a in spy.log)
    starts = [a for a in spy.log if a.op == "write" and a.addr == 0xC000 + START.offset]
    assert len(starts) == 32 and all(a.value == 0 for a in starts)
    assert spy.bus["adc"].scans == 0


def test_adc_split_scan_lets_the_caller_work_meanwhile(spy):
    """start_scan() then read_scan() after 128 us of other work: a single EOC poll."""
    spy.bus["adc"].set_inputs_volts(np.full(32, 2.5))
    adc = Dvme611(spy, 0xC000, name="adc")
    adc.start_scan()
    spy.bus.clock.advance(130e-6)  # the caller's other register work
    spy.clear()
    codes = adc.read_scan()
    assert _lines(spy) == [("read", 0xC000, False, 1), ("read", 0xC040, True, 32)]
    assert codes == [int((2.5 + 10.0) / LSB)] * 32


class _Flaky:
    """The fake rack behind a spy, with writes to the addresses in ``bad`` unanswered (a
    block stops at the first of them, the words before it written: the block contract)."""

    def __init__(self, spy: SpyBus, bad: set[int]) -> None:
        self.spy, self.bad = spy, bad
        self.read16, self.write16 = spy.read16, spy.write16
        self.blocks = 0  #: block writes attempted

    def write_block16(self, addr, words):
        self.blocks += 1
        for i in range(len(words)):
            if addr + 2 * i in self.bad:
                if i:
                    self.spy.write_block16(addr, list(words[:i]))
                raise BusError(addr + 2 * i, 16, "write", reason="flaky slot")
        self.spy.write_block16(addr, words)


def test_dac_block_failing_mid_way_writes_the_rest_as_one_more_block(spy):
    flaky = _Flaky(spy, {0xD006})
    dac = Vmivme4100(flaky, 0xD000, name="dac")
    with pytest.raises(BusError, match=r"dac DAC\[3\] at A16 0xD006"):
        dac.write_volts_all(np.full(16, 5.0))
    assert flaky.blocks == 2
    assert _lines(spy) == [("write", 0xD000, True, 3), ("write", 0xD008, True, 12)]
    assert [int(c) for c in spy.bus["dac"].codes] == [0xC00] * 3 + [0x800] + [0xC00] * 12
    assert dac.shadow_counts[3] == 0x800 and dac.shadow_counts[4] == 0xC00


def test_dac_block_failing_at_its_first_word_is_one_transaction(spy):
    """A gateway that stopped answering fails the block at its first word: one failed
    request (one timeout), not sixteen."""
    dead = _Flaky(spy, {0xD000 + 2 * n for n in range(16)})
    dac = Vmivme4100(dead, 0xD000, name="dac")
    with pytest.raises(BusError, match=r"dac DAC\[0\] at A16 0xD000"):
        dac.zero_all()
    assert dead.blocks == 1 and spy.log == []  # one attempt; no word-by-word retries
