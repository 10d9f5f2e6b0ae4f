"""The RegisterBus contract, run unchanged against every backend.

Backends:

- ``fake``: the fake rack, ``open_bus("fake")`` on a SimClock;
- ``modbus``: ``ModbusTcpBus`` over loopback TCP to a real pymodbus server
  (``fakes.modbus_gateway``) hosting a fake rack;
- ``devicefile``: ``DeviceFileBus`` on an ordinary temporary file standing in for
  the mmap'd VME window (A16 0xC000-0xDFFF at file offset 0).

Each fixture gives the bus plus a small "physical side" (:class:`Side`): an input
word the test can set from outside (a resolver's counts on the rack; raw file bytes
on the device file), a control word and what it reads back after a write (R2: the
VMIVME-4100 reads CTRL in bits 14..8, so 0xC100 reads back 0x4100; plain memory
reads back what was written), an 8-bit register on an odd byte (a 6821 DDR on the
MVME410; a byte of the file), an address nobody answers and an odd address inside
a word board.

Agreed behaviour (every backend): big-endian words; ``BusError`` with ``addr``,
``width`` and ``op`` and a message naming the address for an access nobody
answers; a 16-bit access at an odd address refused with a ``BusError``;
out-of-range values refused with ``ValueError`` (never masked) before any access.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import pytest

from drivers.bus import RegisterBus, open_bus
from drivers.bus.devicefile import DeviceFileBus
from drivers.bus.modbus import ModbusTcpBus
from fakes.modbus_gateway import ModbusGateway
from pfma.clock import SimClock
from pfma.errors import BusError
from tests.drivers.bus.tinybus import quiet_pymodbus

DEAD = 0x8000  # no board in the default rack, outside the device-file window


@dataclass
class Side:
    """The physical side of one backend, for the shared assertions."""

    bus: RegisterBus
    input_addr: int  #: a word the world sets (read-only from the bus)
    set_input: Callable[[int], None]  #: present this value (< 0x4000) at input_addr
    input_bytes_readable: bool  #: whether read8 of input_addr/+1 is answered
    ctrl_addr: int  #: a writable word
    ctrl_readback: Callable[[int], int]  #: what read16 returns after write16(ctrl_addr, v)
    byte_reg: int  #: odd address of a read/write 8-bit register
    odd_word_addr: int  #: an odd address inside a word board
    dead_addr: int = DEAD


def _rack_side(bus, rack, lock=None) -> Side:
    """The fake rack's physical side; ``lock`` guards a rack served by a gateway thread."""

    def set_input(value: int) -> None:
        if lock is None:
            rack["rtd1"].set_counts(0, value)  # rtd1 CH0 at A16 0x0100 (R1)
        else:
            with lock:
                rack["rtd1"].set_counts(0, value)

    return Side(bus=bus, input_addr=0x0100, set_input=set_input,
                input_bytes_readable=lock is not None,  # Modbus reads the word, picks a byte
                ctrl_addr=0xD000, ctrl_readback=lambda v: v & 0x7F00,  # R2: CTRL in b14..8
                byte_reg=0x0021,  # pio_video PIA1 PRA/DDRA (DDRA after reset)
                odd_word_addr=0xD001)


@pytest.fixture(params=["fake", "modbus", "devicefile"])
def side(request, tmp_path) -> Iterator[Side]:
    if request.param == "fake":
        rack = open_bus("fake", clock=SimClock())
        yield _rack_side(rack, rack)
    elif request.param == "modbus":
        rack = open_bus("fake", clock=SimClock())
        with quiet_pymodbus(), ModbusGateway(rack) as gw, \
                ModbusTcpBus("127.0.0.1", gw.port, timeout=2.0) as bus:
            yield _rack_side(bus, rack, gw.lock)
    else:
        path = tmp_path / "vme_a16_window"
        path.write_bytes(bytes(0x2000))

        def set_input(value: int) -> None:
            with open(path, "r+b") as f:
                f.seek(0x0100)
                f.write(value.to_bytes(2, "big"))

        with DeviceFileBus(path, size=0x2000, base=0xC000) as bus:
            yield Side(bus=bus, input_addr=0xC100, set_input=set_input, input_bytes_readable=True,
                       ctrl_addr=0xD000, ctrl_readback=lambda v: v, byte_reg=0xD021,
                       odd_word_addr=0xD001)


def test_is_a_register_bus(side):
    assert isinstance(side.bus, RegisterBus)
    assert isinstance(side.bus.describe(), str) and side.bus.describe()


def test_read16_returns_the_physical_word(side):
    for value in (0x1234, 0x0ABC, 0x0000, 0x3FFF):
        side.set_input(value)
        assert side.bus.read16(side.input_addr) == value


def test_words_are_big_endian(side):
    side.set_input(0x1234)
    if side.input_bytes_readable:
        assert side.bus.read8(side.input_addr) == 0x12
        assert side.bus.read8(side.input_addr + 1) == 0x34
    else:  # a D16-only board answers no 8-bit cycle
        with pytest.raises(BusError) as info:
            side.bus.read8(side.input_addr)
        assert (info.value.addr, info.value.width) == (side.input_addr, 8)


def test_control_word_write_then_read(side):
    side.bus.write16(side.ctrl_addr, 0xC100)  # VMIVME-4100 init word (EPICS VMI_ENABLE_OUT)
    assert side.bus.read16(side.ctrl_addr) == side.ctrl_readback(0xC100)
    side.bus.write16(side.ctrl_addr, 0x8000)  # D15 = 1, everything off
    assert side.bus.read16(side.ctrl_addr) == side.ctrl_readback(0x8000)


def test_byte_register_on_an_odd_address(side):
    for value in (0x5A, 0xA5, 0x00):
        side.bus.write8(side.byte_reg, value)
        assert side.bus.read8(side.byte_reg) == value


@pytest.mark.parametrize("op, width, offset", [
    ("read", 16, 0), ("write", 16, 0), ("read", 8, 1), ("write", 8, 1)])
def test_nobody_answers_is_a_bus_error_naming_the_address(side, op, width, offset):
    addr = side.dead_addr + offset
    with pytest.raises(BusError) as info:
        if op == "read":
            getattr(side.bus, f"read{width}")(addr)
        else:
            getattr(side.bus, f"write{width}")(addr, 0x12)
    err = info.value
    assert (err.addr, err.width, err.op) == (addr, width, op)
    assert f"0x{addr:04X}" in str(err)


@pytest.mark.parametrize("op", ["read", "write"])
def test_word_access_at_an_odd_address_is_refused(side, op):
    with pytest.raises(BusError) as info:
        if op == "read":
            side.bus.read16(side.odd_word_addr)
        else:
            side.bus.write16(side.odd_word_addr, 0xC100)
    assert (info.value.addr, info.value.width, info.value.op) == (side.odd_word_addr, 16, op)
    assert f"0x{side.odd_word_addr:04X}" in str(info.value)


def test_out_of_range_values_are_refused_not_masked(side):
    side.bus.write16(side.ctrl_addr, 0xC100)
    before = side.bus.read16(side.ctrl_addr)
    for bad in (0x10000, -1, 0x1C100, 1.5):
        with pytest.raises(ValueError) as info:
            side.bus.write16(side.ctrl_addr, bad)
        assert f"0x{side.ctrl_addr:04X}" in str(info.value)
    for bad in (0x100, -1):
        with pytest.raises(ValueError):
            side.bus.write8(side.byte_reg, bad)
    assert side.bus.read16(side.ctrl_addr) == before  # nothing reached the board


@pytest.mark.parametrize("addr", [-2, 0x10000])
def test_addresses_outside_a16_are_value_errors(side, addr):
    with pytest.raises(ValueError):
        side.bus.read16(addr)
    with pytest.raises(ValueError):
        side.bus.write8(addr + 1, 0)
