"""Register-level fake of the MVME400: MC6821 (baud select) + uPD7201 (2 async channels).

Register map, bit values and assumptions: ``drivers.mvme400.registers`` (section 4, R4).

- PIA: a full :class:`fakes.pia.FakePia6821`. Port A inputs: jumper code 7 on bits 0..2,
  bit 5 mirrors the FAIL LED output bit 4, bits 6/7 DSR asserted (1). Port B's nibbles,
  when driven (DDRB bits = 1), select each channel's rate (PB7..4 = A, PB3..0 = B).
- 7201: WR0 pointer (the next control access reaches WRn/RRn, then the pointer is 0),
  WR1..WR5, RR0..RR2, channel reset, 3-deep Rx FIFO (a character finding it full is lost
  and RR1 b5 latches until error reset), Tx buffer + shift register with TBE and all-sent,
  status-affects-vector in 8085 and 8086 positions, CTS/DCD asserted by default, auto
  enables (Tx gated by CTS, Rx by DCD).
- Each channel has a byte peer (:class:`SerialPeer`) at the far end of the cable. A
  character takes 10/baud s of model time. The peer talks at its own ``baud``; when the
  board's programmed rate (port B code and WR4 clock multiplier) differs, characters are
  refused in both directions and counted in ``peer.baud_mismatches``.

Model time follows the board's clock: every bus access first runs the line up to
``clock.now()``; ``step(dt_s)`` runs ``dt_s`` more (never double-counting a period the
clock also covered). An access that finds no character due, no transmission ending and
none to start before ``clock.now()`` only moves the far ends' time (and asks an idle far
end for output), so polling stays cheap.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Protocol

from drivers.mvme400.registers import (
    BAUD_CODES, BAUD_SHIFT, BITS_PER_CHAR, CLOCK_MULTIPLIERS, CMD_CHANNEL_RESET, CMD_ERROR_RESET,
    CMD_RESET_EXT_STATUS, CMD_RESET_TX_INT, MVME400, PA_DSR, PA_FAIL_LED, PA_FAIL_LED_STATUS,
    PA_JUMPERS, RR0_CTS, RR0_DCD, RR0_INT_PENDING, RR0_RX_AVAILABLE, RR0_TX_EMPTY, RR1_ALL_SENT,
    RR1_FRAMING_ERROR, RR1_PARITY_ERROR, RR1_RX_OVERRUN, RX_FIFO_DEPTH, VECTOR_NONE, WR0_CMD_MASK,
    WR0_PTR_MASK, WR1_EXT_INT_EN, WR1_RX_INT_MASK, WR1_STATUS_AFFECTS_VECTOR, WR1_TX_INT_EN,
    WR2A_BUS_MODE_MASK, WR2A_8086, WR3_AUTO_ENABLES, WR3_RX_8BITS, WR3_RX_BITS_MASK, WR3_RX_ENABLE,
    WR4_CLOCK_MASK, WR4_PARITY_EN, WR4_STOP_MASK, WR5_TX_8BITS, WR5_TX_BITS_MASK, WR5_TX_ENABLE,
)
from fakes.board import FakeBoard, NoAnswer
from fakes.pia import FakePia6821, even_byte_reason
from pfma.clock import Clock

_PIA_RS = {0x01: 0, 0x03: 1, 0x05: 2, 0x07: 3}
_DATA = {0x09: 0, 0x0B: 1}
_CTRL = {0x0D: 0, 0x0F: 1}
JUMPER_CODE = 7  #: R4: both jumper banks read 7 (meaning unknown)


class ByteDevice(Protocol):
    """A protocol fake on the far end of a serial line (e.g. the F/T controller fake)."""

    def receive(self, data: bytes) -> None:
        """Bytes the board transmitted (one call per character as it completes)."""

    def transmit(self, max_bytes: int) -> bytes:
        """Up to ``max_bytes`` bytes to send now (b"" when idle)."""

    # optional: ``advance(dt_s)`` is called as model time passes, before ``transmit``


class SerialPeer:
    """The far end of one channel's cable.

    :param board: the fake board
    :param channel: 0 (A) or 1 (B)
    :param baud: the peer's line rate (default 19200, the PFMA lines)
    """

    def __init__(self, board: "FakeMvme400", channel: int, baud: float = 19200) -> None:
        self._board = board
        self.channel = channel
        self.baud = baud  #: line rate the peer talks (must equal the board's programmed rate)
        self.device: ByteDevice | None = None  #: optional protocol fake at the far end
        self.baud_mismatches = 0  #: characters refused because the programmed rate differs
        self.dropped = 0  #: characters that reached a disabled receiver (WR3 b0 = 0 or DCD low)
        self.lost = 0  #: characters lost to Rx FIFO overrun
        self.framing_errors = 0  #: board transmitted in a format other than 8N1
        self._queue: deque[tuple[float, int, str | None]] = deque()  # (due time, byte, error)
        self._line_free_t = -math.inf
        self._received = bytearray()
        self._device_t = board.t

    @property
    def char_time_s(self) -> float:
        return BITS_PER_CHAR / self.baud

    def attach(self, device: ByteDevice | None) -> None:
        """Put a protocol fake (``receive``/``transmit``, optional ``advance(dt_s)``) on the
        far end (None removes it)."""
        self._board._sync()
        if self.device is not None and getattr(self.device, "on_line_change", None) is not None:
            self.device.on_line_change = None
        self.device = device
        self._device_t = self._board.t
        if device is not None and hasattr(device, "on_line_change"):
            device.on_line_change = self._board._unquiet  # its faults change when it talks next
        self._board._unquiet()

    def _advance_device(self, t: float) -> None:
        if t > self._device_t:
            advance = getattr(self.device, "advance", None)
            if advance is not None:
                advance(t - self._device_t)
            self._device_t = t

    def send(self, data: bytes, error: str | None = None) -> None:
        """Queue ``data`` for the board; each character arrives 10/baud s after the previous.

        :param error: ``"framing"`` or ``"parity"`` to deliver these characters with that error
        """
        if error not in (None, "framing", "parity"):
            raise ValueError(f"{self._board.name}: unknown line error {error!r}")
        self._board._sync()
        self._enqueue(bytes(data), self._board.t, error)

    def _enqueue(self, data: bytes, not_before: float, error: str | None = None) -> None:
        self._board._unquiet()
        ct = self.char_time_s
        for value in data:
            start = max(self._line_free_t, not_before)
            self._line_free_t = start + ct
            self._queue.append((self._line_free_t, value, error))

    @property
    def pending(self) -> int:
        """Characters queued towards the board, not yet arrived."""
        return len(self._queue)

    def received(self, clear: bool = False) -> bytes:
        """Everything the board transmitted so far (``clear=True`` also empties the record)."""
        self._board._sync()
        out = bytes(self._received)
        if clear:
            self._received.clear()
        return out


class _Channel:
    """State of one 7201 channel."""

    def __init__(self, idx: int) -> None:
        self.idx = idx
        self.wr = [0] * 8
        self.reset()

    def reset(self) -> None:
        keep2 = self.wr[2]  # WR2A/WR2B survive a channel reset (inferred, Z80 SIO family)
        self.wr = [0] * 8
        self.wr[2] = keep2
        self.pointer = 0
        self.fifo: deque[tuple[int, bool]] = deque()  # (byte, framing error)
        self.parity_latch = False
        self.overrun_latch = False
        self.tx_buf: int | None = None
        self.shifting: int | None = None
        self.tx_done_t = math.inf  # end of the character shifting out (inf while none is)
        self.tx_int_pending = False
        self.ext_pending = False
        self.last_rx = 0


class FakeMvme400(FakeBoard):
    """Fake MVME400 with a byte peer on each channel.

    :param name: board name (rack)
    :param clock: shared clock (default SimClock)
    """

    description = MVME400
    #: ``overrun`` (one-shot: latch RR1 b5 now; ``channel=`` 0/1, default both),
    #: ``cts_low`` / ``dcd_low`` (``channel=`` 0/1, default both) until cleared
    FAULTS = ("overrun", "cts_low", "dcd_low")

    def __init__(self, name: str | None = None, clock: Clock | None = None) -> None:
        super().__init__(name, clock)
        self.t = self.clock.now()
        self._quiet_until = -math.inf  # see _advance / _next_event_t
        self.pia = FakePia6821(f"{self.name}.PIA")
        self._ch = [_Channel(0), _Channel(1)]
        self._peers = [SerialPeer(self, 0), SerialPeer(self, 1)]
        self._lines = tuple(zip(self._ch, self._peers))  # (channel, peer) pairs, A then B
        self._cts = [True, True]
        self._dcd = [True, True]
        self._dsr = [True, True]
        self._lines_seen = [(True, True), (True, True)]
        self._update_pia_inputs()

    # -- physical side -------------------------------------------------------------------
    def peer(self, channel: int) -> SerialPeer:
        """The byte peer on ``channel`` (0 = A, 1 = B)."""
        return self._peers[self._check_channel(channel)]

    def _check_channel(self, channel: int) -> int:
        if channel not in (0, 1):
            raise ValueError(f"{self.name}: channel {channel!r} not 0 (A) or 1 (B)")
        return channel

    def set_cts(self, channel: int, asserted: bool) -> None:
        """Drive the CTS input of ``channel``."""
        self._sync()
        self._cts[self._check_channel(channel)] = bool(asserted)
        self._lines_changed()

    def set_dcd(self, channel: int, asserted: bool) -> None:
        """Drive the DCD input of ``channel``."""
        self._sync()
        self._dcd[self._check_channel(channel)] = bool(asserted)
        self._lines_changed()

    def set_dsr(self, channel: int, asserted: bool) -> None:
        """Drive the DSR line of ``channel`` (PIA PA6 / PA7)."""
        self._dsr[self._check_channel(channel)] = bool(asserted)
        self._update_pia_inputs()

    @property
    def fail_led(self) -> bool:
        """FAIL LED (PA4 output)."""
        return bool(self.pia.port_a_output() & PA_FAIL_LED)

    def programmed_baud(self, channel: int) -> float | None:
        """Rate the board runs ``channel`` at: port B code x 16 / WR4 multiplier (None: not driven)."""
        ch = self._check_channel(channel)
        mask = 0xF << BAUD_SHIFT[ch]
        if self.pia.ddr("b") & mask != mask:
            return None
        code = (self.pia.port_b_output() & mask) >> BAUD_SHIFT[ch]
        return BAUD_CODES[code] * 16 / CLOCK_MULTIPLIERS[self._ch[ch].wr[4] & WR4_CLOCK_MASK]

    def cts(self, channel: int) -> bool:
        return self._cts_on(self._check_channel(channel))

    def dcd(self, channel: int) -> bool:
        return self._dcd_on(self._check_channel(channel))

    def _cts_on(self, ch: int) -> bool:
        return self._cts[ch] and not (self.faults and self._fault_on("cts_low", ch))

    def _dcd_on(self, ch: int) -> bool:
        return self._dcd[ch] and not (self.faults and self._fault_on("dcd_low", ch))

    def _fault_on(self, fault: str, ch: int) -> bool:
        if fault not in self.faults:
            return False
        want = self.faults[fault].get("channel")
        return want is None or want == ch

    # -- faults ---------------------------------------------------------------------------
    def inject(self, fault: str, **params) -> None:
        self._sync()
        super().inject(fault, **params)
        if fault == "overrun":
            del self.faults["overrun"]  # one-shot
            for c in self._ch:
                if params.get("channel") in (None, c.idx):
                    c.overrun_latch = True
        self._lines_changed()

    def clear(self, fault: str | None = None) -> None:
        self._sync()
        super().clear(fault)
        self._lines_changed()

    def _lines_changed(self) -> None:
        self._unquiet()
        for c in self._ch:
            now = (self._cts_on(c.idx), self._dcd_on(c.idx))
            if now != self._lines_seen[c.idx]:
                self._lines_seen[c.idx] = now
                if c.wr[1] & WR1_EXT_INT_EN:
                    c.ext_pending = True
            self._try_start_tx(c, self.t)

    def _update_pia_inputs(self) -> None:
        led = self.pia.port_a_output() & PA_FAIL_LED
        value = (JUMPER_CODE & PA_JUMPERS) | (PA_FAIL_LED_STATUS if led else 0)
        for ch in (0, 1):
            if self._dsr[ch]:
                value |= PA_DSR[ch]
        self.pia.drive_port_a(value, mask=0xE7)

    # -- time ---------------------------------------------------------------------------------
    def _sync(self) -> None:
        self._advance(self.clock.now())

    def step(self, dt_s: float) -> None:
        """Run ``dt_s`` more of model time (characters on the lines)."""
        self._advance(max(self.t + dt_s, self.clock.now()))

    def _advance(self, t_to: float) -> None:
        if t_to <= self.t:
            return
        if t_to < self._quiet_until:
            # nothing can happen on either line before _quiet_until (no character arrives,
            # none finishes or starts shifting out, neither far end has output due): only
            # the board's time moves; the far ends catch up at the next event (their
            # ``advance(dt)`` takes any dt in one call)
            self.t = t_to
            return
        t = self.t
        for c, peer in self._lines:
            queue = peer._queue
            if queue and queue[0][0] > t_to and c.tx_done_t > t_to \
                    and (c.tx_buf is None or c.shifting is not None):
                # fast path: no character arrives, none finishes or starts shifting out before
                # t_to (and the far end is not asked for output while its line is busy)
                if peer.device is not None:
                    if t > peer._device_t:
                        peer._advance_device(t)
                    peer._advance_device(t_to)
                continue
            self._advance_channel(c, peer, t_to)
        self.t = t_to
        self._quiet_until = self._next_event_t()

    def _next_event_t(self) -> float:
        """Board time before which no line event can happen: the first queued character's
        arrival, a transmission's end, or a far end's next output (from its optional
        ``next_output_s()``: its own time before which ``transmit`` returns nothing, None
        when it cannot say); -inf when that is not known, so every access runs the lines."""
        q = math.inf
        for c, peer in self._lines:
            if c.tx_buf is not None and c.shifting is None:
                return -math.inf  # a buffered character may start as soon as it is allowed
            queue = peer._queue
            if queue:
                e = queue[0][0]
            elif peer.device is not None:
                hint = getattr(peer.device, "next_output_s", None)
                n = hint() if hint is not None else None
                if n is None:
                    return -math.inf
                e = peer._device_t + (n - peer.device.t_s)
            else:
                continue
            if c.tx_done_t < e:
                e = c.tx_done_t
            if e < q:
                q = e
        for c in self._ch:
            if c.tx_done_t < q:
                q = c.tx_done_t
        return q

    def _unquiet(self) -> None:
        """Something changed that the lines' next event depends on (a register write, a
        fault, a far end attached or queued bytes): every access runs the lines again
        until they have been run once."""
        self._quiet_until = -math.inf

    def _advance_channel(self, c: _Channel, peer: SerialPeer, t_to: float) -> None:
        """Run one channel and its far end from ``self.t`` to ``t_to``, event by event.

        At each event time: the far end's time catches up, a buffered Tx character starts
        shifting if it may, and a far end whose line is idle (nothing queued) is asked for as
        many characters as could start by ``t_to`` or the Tx completion, whichever is first;
        then the earlier of the next Rx arrival and the Tx completion happens (the arrival
        on a tie). ``_advance`` skips this for a channel where nothing can happen.
        """
        queue = peer._queue
        t = self.t
        while True:
            device = peer.device
            if device is not None and t > peer._device_t:
                peer._advance_device(t)
            if c.shifting is None and c.tx_buf is not None:
                self._try_start_tx(c, t)
            t_tx = c.tx_done_t  # inf while nothing is shifting
            if device is not None and not queue:
                line_free_t = peer._line_free_t
                start = t if t > line_free_t else line_free_t  # max(line_free_t, t)
                horizon = t_tx if t_tx < t_to else t_to  # min(t_to, t_tx)
                if start <= horizon:
                    n = int((horizon - start) / (BITS_PER_CHAR / peer.baud)) + 1  # char_time_s
                    data = device.transmit(n)
                    if data:
                        peer._enqueue(bytes(data[:n]), t)
                        continue
            t_rx = queue[0][0] if queue else math.inf
            if t_rx > t_to and t_tx > t_to:
                if device is not None and t_to > peer._device_t:
                    peer._advance_device(t_to)
                return
            if t_rx <= t_tx:
                t = t_rx
                _, value, err = queue.popleft()
                self._deliver_rx(c, peer, value, err)
            else:
                t = t_tx
                self._complete_tx(c, peer)

    def _rate_ok(self, c: _Channel, peer: SerialPeer) -> bool:
        rate = self.programmed_baud(c.idx)
        return rate is not None and abs(rate - peer.baud) <= 0.01 * peer.baud

    def _deliver_rx(self, c: _Channel, peer: SerialPeer, value: int, err: str | None) -> None:
        if not self._rate_ok(c, peer):
            peer.baud_mismatches += 1
            return
        auto = c.wr[3] & WR3_AUTO_ENABLES
        if not c.wr[3] & WR3_RX_ENABLE or (auto and not self._dcd_on(c.idx)):
            peer.dropped += 1
            return
        fmt_ok = (c.wr[3] & WR3_RX_BITS_MASK) == WR3_RX_8BITS and c.wr[4] & WR4_STOP_MASK \
            and not c.wr[4] & WR4_PARITY_EN
        if len(c.fifo) >= RX_FIFO_DEPTH:
            c.overrun_latch = True
            peer.lost += 1
            return
        c.fifo.append((value, err == "framing" or not fmt_ok))
        if err == "parity":
            c.parity_latch = True

    def _tx_allowed(self, c: _Channel) -> bool:
        if not c.wr[5] & WR5_TX_ENABLE:
            return False
        if c.wr[3] & WR3_AUTO_ENABLES and not self._cts_on(c.idx):
            return False
        return self.programmed_baud(c.idx) is not None

    def _try_start_tx(self, c: _Channel, t: float) -> None:
        if c.shifting is None and c.tx_buf is not None and self._tx_allowed(c):
            c.shifting, c.tx_buf = c.tx_buf, None
            c.tx_done_t = t + BITS_PER_CHAR / self.programmed_baud(c.idx)
            c.tx_int_pending = True

    def _complete_tx(self, c: _Channel, peer: SerialPeer) -> None:
        value, c.shifting, c.tx_done_t = c.shifting, None, math.inf
        if not self._rate_ok(c, peer):
            peer.baud_mismatches += 1
            return
        fmt_ok = (c.wr[5] & WR5_TX_BITS_MASK) == WR5_TX_8BITS and c.wr[4] & WR4_STOP_MASK \
            and not c.wr[4] & WR4_PARITY_EN
        if not fmt_ok:
            peer.framing_errors += 1
            return
        peer._received.append(value)
        if peer.device is not None:
            peer.device.receive(bytes([value]))

    # -- interrupts / vector -----------------------------------------------------------
    def _pending_codes(self) -> list[int]:
        """Pending status-affects-vector codes, highest priority first (A before B)."""
        codes = []
        for c in (self._ch[0], self._ch[1]):
            base = 4 if c.idx == 0 else 0
            rx_mode = c.wr[1] & WR1_RX_INT_MASK
            if rx_mode and c.fifo:
                special = c.overrun_latch or c.fifo[0][1] or (c.parity_latch and rx_mode == 0x10)
                codes.append(base + (3 if special else 2))
            if c.wr[1] & WR1_TX_INT_EN and c.tx_int_pending:
                codes.append(base + 0)
            if c.wr[1] & WR1_EXT_INT_EN and c.ext_pending:
                codes.append(base + 1)
        return codes

    def _int_pending(self) -> bool:
        """Whether any status-affects-vector code is pending (``_pending_codes()`` non-empty)."""
        for c in self._ch:
            wr1 = c.wr[1]
            if (wr1 & WR1_RX_INT_MASK and c.fifo) or (wr1 & WR1_TX_INT_EN and c.tx_int_pending) \
                    or (wr1 & WR1_EXT_INT_EN and c.ext_pending):
                return True
        return False

    def _vector(self) -> int:
        b = self._ch[1]
        vec = b.wr[2]
        if not b.wr[1] & WR1_STATUS_AFFECTS_VECTOR:
            return vec
        pending = self._pending_codes()
        code = pending[0] if pending else VECTOR_NONE
        if self._ch[0].wr[2] & WR2A_BUS_MODE_MASK == WR2A_8086:
            return (vec & ~0x07) | code
        return (vec & ~0x1C) | (code << 2)

    # -- bus side -------------------------------------------------------------------------
    def _check(self, offset: int, width: int) -> None:
        if width == 8 and 0 <= offset < self.description.window and "no_answer" not in self.faults:
            if offset & 1:
                return  # an odd byte in the window: decoded (what every register access is)
            raise NoAnswer(even_byte_reason(self.description, offset))
        super()._check(offset, width)

    def _read8(self, offset: int) -> int:
        t = self.clock.now()
        if t > self.t:
            self._advance(t)
        i = _CTRL.get(offset)
        if i is not None:
            c = self._ch[i]
            n, c.pointer = c.pointer, 0
            return self._read_rr(c, n)
        i = _DATA.get(offset)
        if i is not None:
            c = self._ch[i]
            if c.fifo:
                c.last_rx = c.fifo.popleft()[0]
            return c.last_rx
        if offset in _PIA_RS:
            return self.pia.read(_PIA_RS[offset])
        raise NoAnswer(f"offset +0x{offset:02X} is not decoded (registers at +0x01..+0x0F)")

    def _read_rr(self, c: _Channel, n: int) -> int:
        if n == 0:
            idx = c.idx
            v = RR0_RX_AVAILABLE if c.fifo else 0
            v |= RR0_TX_EMPTY if c.tx_buf is None else 0
            v |= RR0_DCD if self._dcd_on(idx) else 0
            v |= RR0_CTS if self._cts_on(idx) else 0
            if idx == 0 and self._int_pending():
                v |= RR0_INT_PENDING
            return v
        if n == 1:
            v = RR1_ALL_SENT if c.tx_buf is None and c.shifting is None else 0
            v |= RR1_PARITY_ERROR if c.parity_latch else 0
            v |= RR1_RX_OVERRUN if c.overrun_latch else 0
            v |= RR1_FRAMING_ERROR if c.fifo and c.fifo[0][1] else 0
            return v
        if n == 2 and c.idx == 1:
            return self._vector()
        return 0x00

    def _write8(self, offset: int, value: int) -> None:
        t = self.clock.now()
        if t > self.t:
            self._advance(t)
        self._quiet_until = -math.inf  # a write may load the Tx buffer or change a mode
        if offset in _PIA_RS:
            self.pia.write(_PIA_RS[offset], value)
            self._update_pia_inputs()
            return
        if offset in _DATA:
            c = self._ch[_DATA[offset]]
            c.tx_buf = value  # a full buffer is overwritten (the earlier character is lost)
            c.tx_int_pending = False
            self._try_start_tx(c, self.t)
            return
        if offset in _CTRL:
            c = self._ch[_CTRL[offset]]
            if c.pointer:
                c.wr[c.pointer], c.pointer = value, 0
                self._try_start_tx(c, self.t)
                return
            self._write_wr0(c, value)
            return
        raise NoAnswer(f"offset +0x{offset:02X} is not decoded (registers at +0x01..+0x0F)")

    def _write_wr0(self, c: _Channel, value: int) -> None:
        c.wr[0] = value
        cmd = value & WR0_CMD_MASK
        c.pointer = value & WR0_PTR_MASK
        if cmd == CMD_CHANNEL_RESET:
            c.reset()
        elif cmd == CMD_RESET_EXT_STATUS:
            c.ext_pending = False
        elif cmd == CMD_RESET_TX_INT:
            c.tx_int_pending = False
        elif cmd == CMD_ERROR_RESET:
            c.parity_latch = c.overrun_latch = False
