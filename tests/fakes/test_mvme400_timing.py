"""FakeMvme400 line timing under dense polling (the cheap path of an access where nothing
happens must not move any event): Rx arrival, 3-deep FIFO + overrun, Tx completion, the
far end's time, CTS gating and RR0's interrupt-pending bit."""

from __future__ import annotations

import pytest

from drivers.mvme400.registers import (
    BITS_PER_CHAR, INIT_WR4, RR0_CTS, RR0_DCD, RR0_INT_PENDING, RR0_RX_AVAILABLE, RR0_TX_EMPTY,
    RR1_ALL_SENT, RR1_RX_OVERRUN,
)
from fakes.mvme400 import FakeMvme400
from pfma.clock import SimClock

DATA = (0x09, 0x0B)
CTRL = (0x0D, 0x0F)
CT = BITS_PER_CHAR / 19200  # one character at 19200 baud


def make_board() -> tuple[FakeMvme400, SimClock]:
    """A board initialised as the driver does it: both channels 19200 8N1, auto enables."""
    clock = SimClock()
    b = FakeMvme400("sio", clock)
    for off, v in ((0x07, 0x00), (0x05, 0xFF), (0x07, 0x04), (0x05, 0xFF)):  # PB = 0xFF: 19200
        b.write8(off, v)
    for ctrl in CTRL:
        for reg, v in ((0, 0x18), (4, INIT_WR4), (3, 0xE1), (5, 0xEA)):
            if reg:
                b.write8(ctrl, reg)
            b.write8(ctrl, v)
    return b, clock


def rr(b: FakeMvme400, ch: int, n: int) -> int:
    if n:
        b.write8(CTRL[ch], n)
    return b.read8(CTRL[ch])


class Recorder:
    """A far end that only records: its time and what it received."""

    def __init__(self) -> None:
        self.t_s = 0.0
        self.got: list[tuple[float, bytes]] = []

    def advance(self, dt_s: float) -> None:
        self.t_s += dt_s

    def receive(self, data: bytes) -> None:
        self.got.append((self.t_s, data))

    def transmit(self, max_bytes: int) -> bytes:
        return b""


@pytest.mark.parametrize("ch", [0, 1])
def test_rx_arrivals_and_overrun_do_not_depend_on_polling(ch):
    dense, dclock = make_board()
    once, oclock = make_board()
    for b in (dense, once):
        b.peer(ch).send(b"ABCDE")
    t0 = dclock.now()
    seen_at = None
    for _ in range(int(4.5 * CT / 3e-6)):  # poll RR0 every 3 us (the FIFO is never read)
        dclock.advance(3e-6)
        if seen_at is None and rr(dense, ch, 0) & RR0_RX_AVAILABLE:
            seen_at = dclock.now()
    assert t0 + CT <= seen_at < t0 + CT + 3e-6  # the first access at or after one char time
    oclock.advance(dclock.now() - t0)
    rr(once, ch, 0)  # one access catches up the same stretch
    for b in (dense, once):
        assert rr(b, ch, 1) & RR1_RX_OVERRUN  # 4th character found the FIFO full
        assert b.peer(ch).lost == 1 and b.peer(ch).pending == 1
        assert [b.read8(DATA[ch]) for _ in range(3)] == list(b"ABC")
        assert not rr(b, ch, 0) & RR0_RX_AVAILABLE
    dclock.advance(CT)
    assert dense.read8(DATA[ch]) == ord("E")


def test_tx_completes_at_char_time_under_dense_polling():
    b, clock = make_board()
    far = Recorder()
    b.peer(1).attach(far)
    clock.advance(0.3 * CT)
    b.peer(1).send(b"0123456789")  # the line towards the board stays busy meanwhile
    clock.advance(0.3 * CT)
    b.write8(DATA[1], 0x41)
    t0 = clock.now()
    assert not rr(b, 1, 1) & RR1_ALL_SENT
    assert rr(b, 1, 0) & RR0_TX_EMPTY  # the buffer moved to the shift register at once
    b.write8(DATA[1], 0x42)  # buffered behind the first: starts when the first ends
    arrived = []  # access time at which each character reached the far end
    for _ in range(300):  # poll RR1 every 5 us
        clock.advance(5e-6)
        all_sent = rr(b, 1, 1) & RR1_ALL_SENT
        arrived += [clock.now()] * (len(far.got) - len(arrived))
        if all_sent:
            break
    assert [d for _, d in far.got] == [b"A", b"B"]
    assert t0 + CT <= arrived[0] < t0 + CT + 5e-6
    assert t0 + 2 * CT <= arrived[1] < t0 + 2 * CT + 5e-6  # back to back
    assert far.t_s == pytest.approx(b.t, abs=1e-12)  # the far end keeps the board's time


def test_buffered_character_starts_once_the_rate_is_programmed():
    b, clock = make_board()
    far = Recorder()
    b.peer(0).attach(far)
    for off, v in ((0x07, 0x00), (0x05, 0x00), (0x07, 0x04)):  # DDRB = 0: no rate selected
        b.write8(off, v)
    assert b.programmed_baud(0) is None
    b.write8(DATA[0], 0x55)
    b.peer(0).send(b"0123456789")  # the line towards the board stays busy meanwhile
    for _ in range(20):
        clock.advance(CT / 10)
        assert not rr(b, 0, 1) & RR1_ALL_SENT
    for off, v in ((0x07, 0x00), (0x05, 0xFF), (0x07, 0x04)):  # DDRB = 0xFF: 19200 again
        b.write8(off, v)
    t0 = b.t  # the next access starts the buffered character at the board's time
    arrived = None
    for _ in range(400):
        clock.advance(3e-6)
        rr(b, 0, 0)
        if far.got:
            arrived = clock.now()
            break
    assert far.got[0][1] == b"\x55"
    assert t0 + CT <= arrived < t0 + CT + 3e-6


def test_far_end_time_catches_up_at_the_lines_next_event():
    """While nothing can happen on the lines (a character on its way, none due) an access
    moves only the board's time; the far end's time catches up in one step at the next
    event, before it is asked for output, and then follows each access again."""
    b, clock = make_board()
    far = Recorder()
    b.peer(0).attach(far)
    b.peer(0).send(b"0123456789")  # line busy towards the board for 10 char times
    t_sent = clock.now()
    for _ in range(200):
        clock.advance(1e-6)
        rr(b, 0, 0)
        assert t_sent <= far.t_s <= clock.now()
    assert far.t_s < clock.now()  # not moved on every access
    while b.peer(0).pending:  # the characters arrive (read, so the FIFO never overruns)
        clock.advance(CT / 4)
        while rr(b, 0, 0) & 0x01:
            b.read8(DATA[0])
    for _ in range(20):  # the line is idle and the far end (no next_output_s) is asked each access
        clock.advance(1e-6)
        rr(b, 0, 0)
        assert far.t_s == pytest.approx(clock.now(), abs=1e-12)


@pytest.mark.parametrize("ch", [0, 1])
def test_cts_fault_holds_a_buffered_character_until_cleared(ch):
    b, clock = make_board()
    far = Recorder()
    b.peer(ch).attach(far)
    b.inject("cts_low", channel=ch)
    assert not rr(b, ch, 0) & RR0_CTS
    assert rr(b, 1 - ch, 0) & RR0_CTS and rr(b, 1 - ch, 0) & RR0_DCD
    b.write8(DATA[ch], 0x55)
    for _ in range(50):
        clock.advance(CT / 10)
        assert not rr(b, ch, 0) & RR0_TX_EMPTY  # auto enables: nothing starts
    assert far.got == []
    b.clear("cts_low")  # starts shifting now
    clock.advance(CT - 1e-6)
    assert not rr(b, ch, 1) & RR1_ALL_SENT and far.got == []
    clock.advance(1.5e-6)
    assert rr(b, ch, 1) & RR1_ALL_SENT
    assert [d for _, d in far.got] == [b"\x55"]


def test_rr0_interrupt_pending_follows_channel_b_rx():
    b, clock = make_board()
    b.write8(CTRL[1], 1)
    b.write8(CTRL[1], 0x18 | 0x04)  # WR1B: all-characters Rx interrupts, status affects vector
    assert not rr(b, 0, 0) & RR0_INT_PENDING
    b.peer(1).send(b"x")
    clock.advance(CT)
    assert rr(b, 0, 0) & RR0_INT_PENDING  # RR0 b1 is valid in channel A only
    assert not rr(b, 1, 0) & RR0_INT_PENDING
    assert rr(b, 1, 2) == 2 << 2  # RR2B: WR2A = 0 is an 8085 mode, code "b_rx_char" in b4..b2
    b.read8(DATA[1])
    assert not rr(b, 0, 0) & RR0_INT_PENDING
