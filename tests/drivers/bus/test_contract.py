"""The RegisterBus contract, run unchanged against every backend.

Backends:

- ``fake``: the fake rack, ``open_bus("fake")`` on a SimClock;
- ``modbus``: ``ModbusTcpBus`` over loopback TCP to a real pymodbus server
  (``fakes.modbus_gateway``) hosting a fake rack;
- ``devicefile``: ``DeviceFileBus`` on an ordinary temporary file standing in for
  the mmap'd VME window (A16 0xC000-0xDFFF at file offset 0);
- ``spy``: ``SpyBus`` over the fake rack (``open_bus("spy+fake")``).

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

Block transfers (``read_block16``/``write_block16``): the same words as single accesses,
in address order; an odd address refused (AlignmentError), a block past 0xFFFF or of no
words a ``ValueError``, a bad word refused before ANY word is written, a word nobody
answers a ``BusError`` naming it (on Modbus: the first word of the failing request).
The Modbus-only parts (splitting at 125/123 words, function code 23) count requests at
the gateway, at the end of this file.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import pytest

from drivers.adc.registers import AUTOINC, CSR, DATA, EOC, START
from drivers.bus import ReadWriteBlockBus, RegisterBus, open_bus
from drivers.bus.devicefile import DeviceFileBus
from drivers.bus.modbus import MAX_READ_WORDS, MAX_WRITE_WORDS, ModbusTcpBus
from drivers.bus.spy import SpyBus
from fakes.modbus_gateway import ModbusGateway
from pfma.clock import SimClock
from pfma.errors import AlignmentError, BusError
from tests.drivers.bus.tinybus import TinyBus, quiet_pymodbus

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
    set_inputs: Callable[[list[int]], None]  #: present 4 words at input_addr .. input_addr+6
    block_out_addr: int  #: 16 writable words from here on (the DAC channels on the rack)
    written: Callable[[int], list[int]]  #: what the world holds for the first n of those words
    live_then_dead: tuple[int, int, int]  #: (addr, n, first word nobody answers) of a block
    with_rack: Callable | None = None  #: run f(rack) on the hosted fake rack (None: no rack)
    dead_addr: int = DEAD


def _rack_side(bus, rack, lock=None) -> Side:
    """The fake rack's physical side; ``lock`` guards a rack served by a gateway thread."""

    def with_rack(f):
        if lock is None:
            return f(rack)
        with lock:
            return f(rack)

    def set_input(value: int) -> None:
        with_rack(lambda r: r["rtd1"].set_counts(0, value))  # rtd1 CH0 at A16 0x0100 (R1)

    def set_inputs(values: list[int]) -> None:
        def put(r):
            for ch, v in enumerate(values):
                r["rtd1"].set_counts(ch, v)  # rtd1 CH0..CH3 at A16 0x0100-0x0106 (R1)
        with_rack(put)

    return Side(bus=bus, input_addr=0x0100, set_input=set_input,
                input_bytes_readable=lock is not None,  # Modbus reads the word, picks a byte
                ctrl_addr=0xD000, ctrl_readback=lambda v: v & 0x7F00,  # R2: CTRL in b14..8
                byte_reg=0x0021,  # pio_video PIA1 PRA/DDRA (DDRA after reset)
                odd_word_addr=0xD001, set_inputs=set_inputs,
                block_out_addr=0xD000,  # dac DAC[0..15] (R2: D15 = 0 loads the channel)
                written=lambda n: with_rack(lambda r: [int(c) for c in r["dac"].codes[:n]]),
                # rtd1 STATUS 0x0108, CONTROL 0x010A, then 0x010C: not decoded (R1)
                live_then_dead=(0x0108, 3, 0x010C), with_rack=with_rack)


@pytest.fixture(params=["fake", "modbus", "devicefile", "spy"])
def side(request, tmp_path) -> Iterator[Side]:
    if request.param == "fake":
        rack = open_bus("fake", clock=SimClock())
        yield _rack_side(rack, rack)
    elif request.param == "spy":
        spy = open_bus("spy+fake", clock=SimClock())
        yield _rack_side(spy, spy.bus)
    elif request.param == "modbus":
        rack = open_bus("fake", clock=SimClock())
        with quiet_pymodbus(), ModbusGateway(rack) as gw, \
                ModbusTcpBus("127.0.0.1", gw.port, timeout=2.0) as bus:
            yield _rack_side(bus, rack, gw.lock)
    else:
        path = tmp_path / "vme_a16_window"
        path.write_bytes(bytes(0x2000))

        def set_inputs(values: list[int]) -> None:
            with open(path, "r+b") as f:
                f.seek(0x0100)
                f.write(b"".join(v.to_bytes(2, "big") for v in values))

        def written(n: int) -> list[int]:
            raw = path.read_bytes()[0x1000:0x1000 + 2 * n]  # A16 0xD000 on
            return [int.from_bytes(raw[i:i + 2], "big") for i in range(0, 2 * n, 2)]

        with DeviceFileBus(path, size=0x2000, base=0xC000) as bus:
            yield Side(bus=bus, input_addr=0xC100, set_input=lambda v: set_inputs([v]),
                       input_bytes_readable=True, ctrl_addr=0xD000, ctrl_readback=lambda v: v,
                       byte_reg=0xD021, odd_word_addr=0xD001, set_inputs=set_inputs,
                       block_out_addr=0xD000, written=written,
                       live_then_dead=(0xDFFC, 4, 0xE000))  # the window ends at 0xDFFF


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


# -- block transfers ---------------------------------------------------------------------------
def test_block_read_returns_the_words_in_address_order(side):
    side.set_inputs([0x0123, 0x1456, 0x2789, 0x3ABC])
    assert side.bus.read_block16(side.input_addr, 4) == [0x0123, 0x1456, 0x2789, 0x3ABC]
    assert side.bus.read_block16(side.input_addr + 2, 2) == [0x1456, 0x2789]
    assert side.bus.read_block16(side.input_addr, 1) == [side.bus.read16(side.input_addr)]


def test_block_write_reaches_every_word(side):
    words = [0x100 * i + i for i in range(16)]  # D15 = 0: DAC loads on the rack
    side.bus.write_block16(side.block_out_addr, words)
    assert side.written(16) == words
    side.bus.write_block16(side.block_out_addr + 4, (0x0ABC,))  # any sequence of ints
    assert side.written(3)[2] == 0x0ABC


def test_block_round_trip_matches_single_accesses(side):
    side.set_inputs([0x0011, 0x0022, 0x0033, 0x0044])
    singles = [side.bus.read16(side.input_addr + 2 * i) for i in range(4)]
    assert side.bus.read_block16(side.input_addr, 4) == singles


@pytest.mark.parametrize("op", ["read", "write"])
def test_block_at_an_odd_address_is_refused_before_any_access(side, op):
    side.bus.write_block16(side.block_out_addr, [0x0111] * 4)
    addr = side.block_out_addr + 1
    with pytest.raises(AlignmentError) as info:  # a BusError and a ValueError
        if op == "read":
            side.bus.read_block16(addr, 2)
        else:
            side.bus.write_block16(addr, [0x0222, 0x0222])
    assert (info.value.addr, info.value.width, info.value.op) == (addr, 16, op)
    assert f"0x{addr:04X}" in str(info.value)
    assert side.written(4) == [0x0111] * 4


@pytest.mark.parametrize("addr, n", [(0xFFFE, 2), (0xFF00, 0x81), (0x0100, 0), (0x0100, -1),
                                     (-2, 1), (0x10000, 1)])
def test_blocks_outside_a16_or_empty_are_value_errors(side, addr, n):
    with pytest.raises(ValueError):
        side.bus.read_block16(addr, n)
    with pytest.raises(ValueError):
        side.bus.write_block16(addr, [0] * max(n, 0))


def test_a_bad_word_is_refused_before_any_word_is_written(side):
    side.bus.write_block16(side.block_out_addr, [0x0111] * 4)
    for bad in (0x10000, -1, 1.5):
        with pytest.raises(ValueError) as info:
            side.bus.write_block16(side.block_out_addr, [0x0222, 0x0222, bad, 0x0222])
        assert f"0x{side.block_out_addr + 4:04X}" in str(info.value)  # names the bad word
    assert side.written(4) == [0x0111] * 4  # not even the words before it


@pytest.mark.parametrize("op", ["read", "write"])
def test_block_nobody_answers_is_a_bus_error_naming_the_address(side, op):
    with pytest.raises(BusError) as info:
        if op == "read":
            side.bus.read_block16(side.dead_addr, 3)
        else:
            side.bus.write_block16(side.dead_addr, [1, 2, 3])
    err = info.value
    assert (err.addr, err.width, err.op) == (side.dead_addr, 16, op)
    assert f"0x{side.dead_addr:04X}" in str(err)


def test_block_into_a_dead_word_names_the_first_word_nobody_answered(side):
    addr, n, dead = side.live_then_dead
    with pytest.raises(BusError) as info:
        side.bus.read_block16(addr, n)
    # a Modbus gateway answers the request as a whole: its first word is all it can name
    expect = addr if isinstance(side.bus, ModbusTcpBus) else dead
    assert (info.value.addr, info.value.op) == (expect, "read")
    assert f"0x{expect:04X}" in str(info.value)


def test_block_read_has_each_registers_side_effects(side):
    """A block over the ADC's CSR, START, DATA and BOARD_ID reads each as a single read
    would, in order: CSR still shows EOC, the DATA word clears it and advances the
    auto-increment channel (R3)."""
    if side.with_rack is None:
        pytest.skip("no register model behind a plain file")
    adc = 0xC000
    side.bus.write16(adc + CSR.offset, AUTOINC.mask | 5)  # auto-increment from channel 5
    side.bus.write16(adc + START.offset, 0)
    side.with_rack(lambda r: r.clock.advance(10e-6))  # the 4 us conversion is over
    csr, start, data, board_id = side.bus.read_block16(adc + CSR.offset, 4)
    assert csr & EOC.mask and csr & 0x1F == 5 and start == 0 and board_id == 0x0611
    after = side.bus.read16(adc + CSR.offset)
    assert not after & EOC.mask and after & 0x1F == 6  # the DATA word's side effects
    assert data == side.bus.read16(adc + DATA.offset)  # the same result, now without EOC


def test_block_write_updates_each_dac_channel(side):
    if side.with_rack is None:
        pytest.skip("no register model behind a plain file")
    side.bus.write_block16(0xD000 + 6, [0x0800, 0x0FFF, 0x0000])
    assert side.with_rack(lambda r: [int(c) for c in r["dac"].codes[3:6]]) == [0x800, 0xFFF, 0]


def test_block_charges_simulated_time_per_word(side):
    if side.with_rack is None:
        pytest.skip("a plain file has no simulated clock")
    t0 = side.with_rack(lambda r: r.clock.now())
    side.bus.read_block16(side.input_addr, 4)
    side.bus.write_block16(side.block_out_addr, [0x800] * 16)
    per_word = side.with_rack(lambda r: r.access_time_s)
    assert side.with_rack(lambda r: r.clock.now()) - t0 == pytest.approx(20 * per_word)


def test_spy_logs_a_block_as_one_access_with_its_words():
    spy = open_bus("spy+fake", clock=SimClock())
    assert isinstance(spy, SpyBus)
    spy.bus["rtd1"].set_counts(1, 0x0042)
    words = spy.read_block16(0x0100, 4)
    spy.write_block16(0xD000, [0x0800, 0x0801])
    read, write = spy.log
    assert (read.op, read.addr, read.count, read.block, read.words) == ("read", 0x0100, 4, True, tuple(words))
    assert (write.op, write.addr, write.count, write.words) == ("write", 0xD000, 2, (0x0800, 0x0801))
    assert str(write) == "writeB2   0xD000 <- 0x0800 0x0801"
    with pytest.raises(BusError):
        spy.read_block16(DEAD, 2)
    assert spy.log[-1].error and spy.log[-1].words is None and spy.log[-1].block


# -- Modbus only: requests per block, function code 23 ----------------------------------------
@pytest.fixture
def tiny_gateway():
    tiny = TinyBus()
    with quiet_pymodbus(), ModbusGateway(tiny) as gw, \
            ModbusTcpBus("127.0.0.1", gw.port, timeout=2.0) as bus:
        yield tiny, gw, bus


@pytest.mark.parametrize("n, sizes", [(1, [1]), (125, [125]), (126, [125, 1]), (300, [125, 125, 50])])
def test_modbus_block_read_splits_at_125_words(tiny_gateway, n, sizes):
    tiny, gw, bus = tiny_gateway
    for i in range(n):
        tiny.words[0x1000 + 2 * i] = i
    before = gw.requests
    assert bus.read_block16(0x1000, n) == list(range(n))
    assert gw.requests - before == len(sizes) and gw.function_codes[before:] == [3] * len(sizes)
    assert [a for _, a, _ in tiny.log] == [0x1000 + 2 * i for i in range(n)]  # each word once, in order
    assert MAX_READ_WORDS == 125


@pytest.mark.parametrize("n, sizes", [(1, [1]), (123, [123]), (124, [123, 1]), (250, [123, 123, 4])])
def test_modbus_block_write_splits_at_123_words(tiny_gateway, n, sizes):
    tiny, gw, bus = tiny_gateway
    before = gw.requests
    bus.write_block16(0x1000, [i + 7 for i in range(n)])
    assert gw.requests - before == len(sizes) and gw.function_codes[before:] == [16] * len(sizes)
    assert tiny.log == [("w", 0x1000 + 2 * i, i + 7) for i in range(n)]
    assert MAX_WRITE_WORDS == 123


def test_modbus_split_block_error_names_the_failing_requests_first_word(tiny_gateway):
    _, gw, bus = tiny_gateway
    start = 0x8000 - 2 * 125  # the second request starts at the dead 0x8000
    with pytest.raises(BusError) as info:
        bus.read_block16(start, 130)
    assert info.value.addr == 0x8000 and gw.requests == 2


def test_modbus_read_write_block_is_one_function_code_23_request(tiny_gateway):
    tiny, gw, bus = tiny_gateway
    assert isinstance(bus, ReadWriteBlockBus)
    tiny.words.update({0x2000: 0x0A, 0x2002: 0x0B})
    before = gw.requests
    got = bus.read_write_block16(0x2000, 2, 0x3000, [0x0C, 0x0D, 0x0E])
    assert got == [0x0A, 0x0B]
    assert gw.requests - before == 1 and gw.function_codes[-1] == 23
    assert tiny.log == [("w", 0x3000, 0x0C), ("w", 0x3002, 0x0D), ("w", 0x3004, 0x0E),
                        ("r", 0x2000, 0x0A), ("r", 0x2002, 0x0B)]  # the write first
    # the write lands before the read: reading what was just written sees it
    assert bus.read_write_block16(0x3002, 1, 0x3002, [0x77]) == [0x77]


def test_modbus_read_write_block_checks_both_blocks_before_the_request(tiny_gateway):
    tiny, gw, bus = tiny_gateway
    before = gw.requests
    with pytest.raises(ValueError):
        bus.read_write_block16(0x2000, 2, 0x3000, [0x10000])
    with pytest.raises(AlignmentError):
        bus.read_write_block16(0x2001, 2, 0x3000, [1])
    with pytest.raises(ValueError):
        bus.read_write_block16(0x2000, 126, 0x3000, [1])  # one request reads at most 125
    with pytest.raises(ValueError):
        bus.read_write_block16(0x2000, 1, 0x3000, [1] * 122)  # and writes at most 121
    assert gw.requests == before and tiny.log == []


def test_only_the_modbus_bus_offers_read_write_blocks(side):
    assert isinstance(side.bus, ReadWriteBlockBus) == isinstance(side.bus, ModbusTcpBus)
