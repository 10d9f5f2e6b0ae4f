"""Mvme400 driver and byte port against the fake MVME400 in the fake rack (simulated time)."""

from __future__ import annotations

import pytest

from drivers.mvme400 import Mvme400, Mvme400Port
from drivers.mvme400.registers import (
    CMD_ERROR_RESET, INIT_WR4, MVME400, RR1_RX_OVERRUN, WR4_X16, char_time_s, max_poll_interval_s,
)
from fakes.mvme400 import FakeMvme400
from fakes.rack import FakeRack
from fakes.testing import assert_register_writes
from pfma.clock import SimClock
from pfma.errors import BoardError, BusError, LinkError, PfmaTimeoutError

CT = char_time_s(19200)


@pytest.fixture
def rack() -> FakeRack:
    return FakeRack(clock=SimClock())


@pytest.fixture
def fake(rack) -> FakeMvme400:
    return rack.add(0x0000, FakeMvme400(name="sio", clock=rack.clock))


@pytest.fixture
def board(rack, fake) -> Mvme400:
    b = Mvme400(rack, 0x0000, name="sio", clock=rack.clock)
    b.init()
    return b


def test_even_byte_access_is_bus_error_naming_board_register_address(rack, fake):
    with pytest.raises(BusError) as e:
        rack.write8(0x000C, 0x18)
    err = e.value
    assert (err.board, err.addr, err.op) == ("sio", 0x000C, "write")
    assert "SIO_CTRL_A" in str(err) and "0x000C" in str(err)


def test_init_traffic(fake, board):
    assert_register_writes(fake, [
        ("PIA_CRA", 0x00), ("PIA_PRA", 0x18), ("PIA_CRA", 0x04),  # DDRA = 0x18
        ("PIA_CRB", 0x00), ("PIA_PRB", 0xFF), ("PIA_CRB", 0x04),  # DDRB = 0xFF
        ("PIA_PRB", 0xFF),  # both channels 19200 (code 0xF)
        ("PIA_PRA", 0x00),  # FAIL LED off
        ("SIO_CTRL_A", 0x18), ("SIO_CTRL_A", 0x18),  # channel reset, twice
        ("SIO_CTRL_B", 0x18), ("SIO_CTRL_B", 0x18),
        ("SIO_CTRL_A", 0x02), ("SIO_CTRL_A", 0x14),  # WR2A first
        ("SIO_CTRL_B", 0x02), ("SIO_CTRL_B", 0x00),  # WR2B vector
        ("SIO_CTRL_A", 0x04), ("SIO_CTRL_A", 0x44),  # WR4 x16, 1 stop, no parity
        ("SIO_CTRL_A", 0x03), ("SIO_CTRL_A", 0xE1),  # WR3 8 bits, auto enables, Rx on
        ("SIO_CTRL_A", 0x05), ("SIO_CTRL_A", 0xEA),  # WR5 DTR, 8 bits, Tx on, RTS
        ("SIO_CTRL_B", 0x04), ("SIO_CTRL_B", 0x44),
        ("SIO_CTRL_B", 0x03), ("SIO_CTRL_B", 0xE1),
        ("SIO_CTRL_B", 0x05), ("SIO_CTRL_B", 0xEA),
        ("SIO_CTRL_A", 0x29), ("SIO_CTRL_A", 0x00),  # WR1A via reset-Tx-int + pointer 1
        ("SIO_CTRL_B", 0x29), ("SIO_CTRL_B", 0x04),  # WR1B status affects vector
    ], width=8)
    assert INIT_WR4 & 0xC0 == WR4_X16
    assert not fake.fail_led
    assert fake.programmed_baud(0) == fake.programmed_baud(1) == 19200


def test_init_without_auto_enables(rack, fake):
    b = Mvme400(rack, 0, name="sio", clock=rack.clock)
    b.init(9600, 4800, auto_enables=False)
    assert b.read_register(0, 0) & 0x04  # TBE after reset
    assert fake.programmed_baud(0) == 9600 and fake.programmed_baud(1) == 4800
    assert ("w", 8, 0x0D, 0xC1) in fake.traffic


def test_baud_programming(fake, board):
    assert fake.pia.port_b_output() >> 4 == 0xF  # 19200 on channel A: high nibble 0xF
    board.set_baud(0, 9600)
    assert fake.pia.port_b_output() == 0xEF and fake.programmed_baud(0) == 9600
    board.set_baud(1, 134.5)
    assert fake.pia.port_b_output() == 0xE3
    assert board.port(1).baudrate == 134.5
    with pytest.raises(ValueError, match=r"sio channel A .*0x0000.*12345.*19200"):
        board.set_baud(0, 12345)
    with pytest.raises(ValueError, match="not 0"):
        board.set_baud(2, 9600)
    with pytest.raises(ValueError):
        board.port(0).baudrate = 38400
    # a wrong WR4 clock multiplier changes the real rate: x64 gives a quarter
    board.write_register(0, 4, 0xC4)
    assert fake.programmed_baud(0) == 9600 / 4


def test_set_baud_before_init_is_refused(rack, fake):
    b = Mvme400(rack, 0, name="sio", clock=rack.clock)
    with pytest.raises(BoardError, match="before init"):
        b.set_baud(0, 19200)


def test_bytes_round_trip_both_directions_at_19200(rack, fake, board):
    port = board.port(0, timeout=0.1)
    assert isinstance(port, Mvme400Port)
    t0 = rack.clock.now()
    fake.peer(0).send(b"hello\r\n")
    assert port.read(7) == b"hello\r\n"
    elapsed = rack.clock.now() - t0
    assert 7 * CT <= elapsed < 9 * CT  # paced by the line, not instantaneous
    t0 = rack.clock.now()
    assert port.write(b"QS\r") == 3
    port.flush()
    assert fake.peer(0).received() == b"QS\r"
    assert 3 * CT <= rack.clock.now() - t0 < 5 * CT
    assert port.stats.rx_bytes == 7 and port.stats.tx_bytes == 3 and port.stats.overruns == 0
    # channel B is independent
    fake.peer(1).send(b"B")
    assert board.port(1, timeout=0.01).read(1) == b"B"
    assert fake.peer(0).received() == b"QS\r"


def test_attached_device_sees_board_bytes_and_answers(rack, fake, board):
    class Echo:
        def __init__(self):
            self.out = bytearray()
            self.t_s = 0.0

        def advance(self, dt_s):
            self.t_s += dt_s

        def receive(self, data):
            self.out += data.upper()

        def transmit(self, max_bytes):
            data, self.out = bytes(self.out[:max_bytes]), self.out[max_bytes:]
            return data

    dev = Echo()
    fake.peer(0).attach(dev)
    port = board.port(0, timeout=0.05)
    port.write(b"abc")
    assert port.read(3) == b"ABC"
    assert dev.t_s == pytest.approx(rack.clock.now(), abs=1e-3)


def test_read_timeout_on_the_injected_clock(rack, fake, board):
    port = board.port(0, timeout=0.02)
    fake.peer(0).send(b"xy")
    t0 = rack.clock.now()
    assert port.read(5) == b"xy"
    assert rack.clock.now() - t0 == pytest.approx(0.02, abs=CT)
    port.timeout = 0
    t0 = rack.clock.now()
    assert port.read(5) == b""
    assert rack.clock.now() - t0 < 1e-4  # non-blocking: a few bus accesses only
    fake.peer(0).send(b"z")
    rack.clock.advance(2 * CT)
    assert port.in_waiting == 1
    port.reset_input_buffer()
    assert port.in_waiting == 0


def test_autopoll_off_reads_only_the_buffer_the_owner_drains(rack, fake, board):
    """The service drains the FIFO on its own schedule; its decoders' reads must not make
    register accesses of their own."""
    port = board.port(0, timeout=0)
    port.autopoll = False
    fake.peer(0).send(b"ab")
    rack.clock.advance(3 * CT)
    mark = len(fake.traffic)
    assert port.in_waiting == 0 and port.read(5) == b"" and port.read_all() == b""
    assert len(fake.traffic) == mark  # not one bus access
    assert board.poll() == 2  # the owner's drain
    assert port.in_waiting == 2 and port.read(5) == b"ab"
    # a blocking read still polls (it would otherwise wait out its timeout for nothing)
    port.timeout = 0.01
    fake.peer(0).send(b"c")
    assert port.read(1) == b"c"


def test_overrun_when_not_polled_for_more_than_three_characters(rack, fake, board):
    port = board.port(0, timeout=0)
    fake.peer(0).send(b"ABCDEF")
    rack.clock.advance(10 * CT)  # the driver does not poll
    mark = len(fake.traffic)
    assert port.poll() == 3
    assert port.read(10) == b"ABC"
    assert port.stats.overruns == 1
    assert fake.peer(0).lost == 3
    assert ("w", 8, 0x0D, CMD_ERROR_RESET) in fake.traffic[mark:]  # error reset issued
    assert not board.read_register(0, 1) & RR1_RX_OVERRUN  # and the latch is clear


def test_poll_cadence_needed_at_full_line_rate(rack, fake, board):
    """A continuous 19200-baud stream overruns the 3-deep FIFO if polled only every
    3.125 ms frame (6 characters per frame); polling every 3 character times is enough."""
    data = bytes(range(200))
    for period_s, lossless in ((3.125e-3, False), (max_poll_interval_s(19200) * 0.95, True)):
        port = board.port(0, timeout=0)
        port.reset_input_buffer()
        port.stats.overruns = 0
        fake.peer(0).send(data)
        got = bytearray()
        end = rack.clock.now() + len(data) * CT + 0.01
        while rack.clock.now() < end:
            rack.clock.advance(period_s)
            port.poll()
            got += port.read(1000)
        assert (bytes(got) == data) is lossless
        assert (port.stats.overruns == 0) is lossless


def test_baud_mismatch_refused_and_counted(rack, fake, board):
    peer = fake.peer(0)
    peer.baud = 9600
    port = board.port(0, timeout=0.01)
    peer.send(b"abc")
    assert port.read(3) == b""
    assert peer.baud_mismatches == 3
    port.write(b"x")
    port.flush()
    assert peer.received() == b"" and peer.baud_mismatches == 4
    board.set_baud(0, 9600)
    peer.send(b"ok")
    assert port.read(2) == b"ok"


def test_cts_low_blocks_tx(rack, fake, board):
    fake.inject("cts_low", channel=0)
    port = board.port(0, write_timeout=0.01)
    assert not port.cts and port.cd
    with pytest.raises(PfmaTimeoutError, match=r"sio:A.*after 1 of 2 bytes.*CTS NOT asserted.*0x000D"):
        port.write(b"AB")  # 'A' waits in the Tx buffer, 'B' cannot be written
    assert fake.peer(0).received() == b""
    board.port(1).write(b"b")  # channel B unaffected
    board.port(1).flush()
    assert fake.peer(1).received() == b"b"
    fake.clear("cts_low")
    fake.step(2 * CT)
    assert fake.peer(0).received() == b"A"


def test_dcd_low_gates_receiver(rack, fake, board):
    fake.inject("dcd_low")
    port = board.port(0, timeout=0.01)
    fake.peer(0).send(b"lost")
    assert port.read(4) == b""
    assert fake.peer(0).dropped == 4
    fake.set_dcd(0, True)
    fake.clear()
    fake.peer(0).send(b"ok")
    assert port.read(2) == b"ok"


def test_line_errors_counted(rack, fake, board):
    port = board.port(1, timeout=0.01)
    fake.peer(1).send(b"f", error="framing")
    fake.peer(1).send(b"p", error="parity")
    assert port.read(2) == b"fp"
    assert port.stats.framing_errors == 1 and port.stats.parity_errors == 1
    fake.inject("overrun", channel=1)
    fake.peer(1).send(b"o")
    port.read(1)
    assert port.stats.overruns == 1


def test_wr0_pointer_and_vector(rack, fake, board):
    rack.write8(0x0D, 0x01)  # pointer -> RR1
    assert rack.read8(0x0D) & 0x01  # all sent
    assert rack.read8(0x0D) & 0x04  # pointer back to 0: RR0 (TBE)
    assert board.read_register(1, 2) & 0x07 == 7  # 8086 mode, nothing pending
    board.write_register(0, 1, 0x18)  # WR1A: Rx interrupt on all characters
    fake.peer(0).send(b"v")
    rack.clock.advance(2 * CT)
    assert board.read_register(0, 0) & 0x02  # interrupt pending (channel A RR0)
    assert board.read_register(1, 2) & 0x07 == 6  # A Rx char available
    board.write_register(0, 2, 0x04)  # WR2A: 8085 mode -> code in V4..V2
    assert (board.read_register(1, 2) >> 2) & 0x07 == 6


def test_closed_port_and_bad_channel(board):
    port = board.port(0)
    port.close()
    with pytest.raises(LinkError, match="closed"):
        port.read(1)
    port.open()
    assert port.read(0) == b""
    with pytest.raises(ValueError, match="channel 3"):
        board.port(3)


def test_table_records_assumptions():
    assert MVME400.window == 0x20 and MVME400.byte_lanes == "odd"
    assert MVME400.reg("SIO_CTRL_A").offset == 0x0D
    assert MVME400.constants["baud_codes"][0xF] == 19200
    assert any("assumed" in a for a in MVME400.assumptions)
