"""FakePia6821 semantics (section 5 / R5) and the PIA side of the MVME410/MVME400 fakes."""

from __future__ import annotations

import pytest

from drivers.pio.registers import CR_IRQ1, CR_IRQ2
from fakes.mvme400 import FakeMvme400
from fakes.mvme410 import FakeMvme410
from fakes.pia import FakePia6821
from fakes.rack import FakeRack
from pfma.clock import SimClock
from pfma.errors import BusError

PRA, CRA, PRB, CRB = 0, 1, 2, 3


@pytest.fixture
def pia() -> FakePia6821:
    return FakePia6821("t")


def test_reset_selects_ddr_and_b2_selects_data(pia):
    pia.write(PRA, 0x0F)  # CRA = 0 after reset: this is DDRA
    assert pia.ddr("a") == 0x0F
    assert pia.read(PRA) == 0x0F
    pia.write(CRA, 0x04)
    pia.write(PRA, 0xA5)  # now the output latch
    assert pia.ddr("a") == 0x0F
    assert pia.port_a_output() == 0x05  # latch AND DDR
    assert pia.read(PRA) == 0xF5  # output bits read back, input pins float high


def test_port_a_pins_high_when_undriven_port_b_reads_latch(pia):
    pia.write(CRA, 0x04)
    assert pia.read(PRA) == 0xFF
    pia.drive_port_a(0x12)
    assert pia.read(PRA) == 0x12
    pia.drive_port_a(None)
    assert pia.read(PRA) == 0xFF
    pia.write(PRB, 0xF0)  # DDRB
    pia.write(CRB, 0x04)
    pia.write(PRB, 0x5A)
    pia.drive_port_b(0x0C)
    assert pia.read(PRB) == 0x5C  # latch for outputs, pins for inputs
    assert pia.port_b_output() == 0x50


def test_c1_edge_sets_flag_data_read_clears_it(pia):
    pia.write(CRA, 0x04)  # C1 falling edge active
    pia.drive_ca1(True)
    assert not pia.read(CRA) & CR_IRQ1
    pia.drive_ca1(False)
    assert pia.read(CRA) & CR_IRQ1
    assert pia.read(CRA) & CR_IRQ1  # reading CR does not clear
    pia.write(CRA, 0x00)
    pia.read(PRA)  # DDR read does not clear
    assert pia.read(CRA) & CR_IRQ1
    pia.write(CRA, 0x04)
    pia.read(PRA)
    assert not pia.read(CRA) & CR_IRQ1
    pia.write(CRB, 0x06)  # CB1 rising edge active
    pia.drive_cb1(False)
    assert not pia.read(CRB) & CR_IRQ1
    pia.drive_cb1(True)
    assert pia.read(CRB) & CR_IRQ1


def test_c2_input_edge_and_irq_outputs(pia):
    pia.write(CRA, 0x04 | 0x10 | 0x08 | 0x01)  # CA2 rising, C2 IRQ on, C1 IRQ on
    pia.drive_ca2(False)
    assert not pia.read(CRA) & CR_IRQ2
    pia.drive_ca2(True)
    assert pia.read(CRA) & CR_IRQ2
    assert pia.irq_a
    pia.read(PRA)
    assert not pia.irq_a and not pia.read(CRA) & (CR_IRQ1 | CR_IRQ2)
    pia.write(CRA, 0xC4)  # writes to b7/b6 ignored
    assert pia.read(CRA) == 0x04
    pia.drive_ca1(True)
    pia.drive_ca1(False)
    assert not pia.irq_a  # flag set, but CRA b0 = 0
    assert pia.read(CRA) & CR_IRQ1


def test_ca2_read_strobe_restored_by_ca1(pia):
    events = []
    pia.on_strobe = events.append
    pia.write(CRA, 0x24)  # CA2 strobe, restore on CA1 active (falling) edge
    assert pia.ca2_level
    pia.read(PRA)
    assert not pia.ca2_level
    pia.drive_ca1(False)
    assert pia.ca2_level and events == ["a"]
    pia.write(CRA, 0x2C)  # restore after one E cycle: a complete pulse per read
    levels = []
    pia.on_c2 = lambda side, level: levels.append((side, level))
    pia.read(PRA)
    assert levels == [("a", False), ("a", True)] and pia.ca2_level


def test_cb2_write_strobe_and_mame_restore_on_read(pia):
    pia.write(PRB, 0xFF)
    pia.write(CRB, 0x2C)  # CB2 write strobe, E-cycle restore
    levels = []
    pia.on_c2 = lambda side, level: levels.append((side, level))
    pia.write(PRB, 0x11)
    assert levels == [("b", False), ("b", True)]
    pia.write(CRB, 0x24)  # restore on CB1: MAME restores only when the PRB read clears IRQB1
    pia.write(PRB, 0x22)
    assert not pia.cb2_level
    pia.drive_cb1(False)
    assert not pia.cb2_level and pia.read(CRB) & CR_IRQ1
    pia.read(PRB)
    assert pia.cb2_level
    pia.read(PRA)  # a read of PRA never strobes CB2
    assert pia.cb2_level


def test_set_reset_mode_and_irq2_reads_zero_as_output(pia):
    events = []
    pia.on_strobe = events.append
    pia.write(CRA, 0x04)
    pia.drive_ca2(True)
    pia.drive_ca2(False)
    assert pia.read(CRA) & CR_IRQ2
    pia.write(CRA, 0x34)  # set/reset, CA2 = 0
    assert not pia.ca2_level and not pia.read(CRA) & CR_IRQ2
    pia.write(CRA, 0x3C)
    assert pia.ca2_level and events == ["a"]
    pia.drive_ca2(False)  # no effect while an output
    assert pia.ca2_level


def test_bad_side_is_value_error(pia):
    with pytest.raises(ValueError, match="side"):
        pia.ddr("c")


# -- boards ------------------------------------------------------------------------------
def test_mvme410_fake_decode():
    rack = FakeRack(clock=SimClock())
    fake = rack.add(0x0040, FakeMvme410(name="pio_user", clock=rack.clock))
    with pytest.raises(BusError) as e:
        rack.write8(0x0048, 0)
    assert e.value.board == "pio_user" and e.value.addr == 0x0048
    assert "PIA2_PRA" in str(e.value)
    with pytest.raises(BusError, match="not decoded"):
        rack.read8(0x0051)  # +0x11: inside the window, not used
    rack.write8(0x004B, 0x04)  # PIA2 CRA: select data
    fake.drive_inputs(2, 0x3C)
    assert rack.read8(0x0049) == 0x3C
    assert rack.read16(0x0048) == 0xFF3C  # D16 cycle reaches the odd byte, upper lane 0xFF
    fake.inject("no_answer")
    with pytest.raises(BusError, match="does not answer"):
        rack.read8(0x0049)


def test_mvme400_fake_pia_inputs():
    rack = FakeRack(clock=SimClock())
    fake = rack.add(0x0000, FakeMvme400(name="sio", clock=rack.clock))
    rack.write8(0x01, 0x18)  # DDRA
    rack.write8(0x03, 0x04)
    assert rack.read8(0x01) == 0xC7  # DSR x2 asserted, LED off, jumpers 7
    rack.write8(0x01, 0x10)  # FAIL LED on
    assert fake.fail_led
    assert rack.read8(0x01) == 0xF7  # bit 5 mirrors bit 4
    fake.set_dsr(1, False)
    assert rack.read8(0x01) == 0x77
    assert fake.programmed_baud(0) is None  # port B not driven yet
