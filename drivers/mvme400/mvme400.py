"""Driver of the Motorola MVME400 dual RS-232C module and a pyserial-like byte port.

Register model, init values and the baud table: ``drivers.mvme400.registers`` (sources
named there: VME/10 ``bios.c``, ``VM400.C``, MAME ``z80sio.cpp``).

Receiving is polled (as ``bios.c`` does): :meth:`Mvme400Port.poll` drains the 7201's
3-deep Rx FIFO into a software buffer. At 19200 baud (1920 characters/s) the FIFO
fills in 3 characters = 1.5625 ms (:func:`max_poll_interval_s`), so a continuous
stream needs a poll at least that often - a poll once per 3.125 ms frame is **not**
enough (6 characters arrive per frame); the port's own ``read()`` polls every
character time. ``stats.max_poll_gap_s`` shows how well a caller keeps up.

Thread safety: every multi-access sequence (WR0 pointer + register) holds the board's
lock, so two threads may use the two channels. The RegisterBus itself must be safe to
call from those threads.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from drivers.bus import RegisterBus
from drivers.mvme400.registers import (
    BAUD_CODES, BAUD_SHIFT, BAUD_TO_CODE, CMD_ERROR_RESET, INIT_CHANNEL_RESET, INIT_WR1_SELECT,
    INIT_WR1A, INIT_WR1B, INIT_WR2A, INIT_WR2B, INIT_WR3, INIT_WR4, INIT_WR5, MVME400,
    PA_DSR, PA_FAIL_LED, PIA_DDRA, PIA_DDRB, RR0_CTS, RR0_DCD, RR0_RX_AVAILABLE, RR0_TX_EMPTY,
    RR1_ALL_SENT, RR1_FRAMING_ERROR, RR1_PARITY_ERROR, RR1_RX_OVERRUN, RX_FIFO_DEPTH,
    WR3_AUTO_ENABLES, char_time_s, max_poll_interval_s,
)
from drivers.pio.pia6821 import Pia6821
from pfma.clock import Clock, MonotonicClock
from pfma.errors import BoardError, BoardInitError, BusError, LinkError, PfmaTimeoutError

CHANNEL_NAMES = ("A", "B")
#: the RR1 bits that mark a received character as damaged
_RR1_ERRORS = RR1_RX_OVERRUN | RR1_PARITY_ERROR | RR1_FRAMING_ERROR

__all__ = ["Mvme400", "Mvme400Port", "LinkStats", "max_poll_interval_s"]


@dataclass
class LinkStats:
    """Counters of one channel since the port was created."""

    rx_bytes: int = 0  #: characters taken from the Rx FIFO
    tx_bytes: int = 0  #: characters written to the Tx buffer
    overruns: int = 0  #: RR1 b5 seen (each time followed by an error reset)
    framing_errors: int = 0  #: RR1 b6 seen with a character
    parity_errors: int = 0  #: RR1 b4 seen
    buffer_overflows: int = 0  #: characters dropped because the software buffer was full
    max_poll_gap_s: float = 0.0  #: longest time between two polls (clock seconds)


class Mvme400:
    """One MVME400 board.

    :param bus: any RegisterBus
    :param base: board base (A16), 0x0000 in the PFMA rack
    :param name: board name for messages (default ``"mvme400@0xNNNN"``)
    :param clock: time base for port timeouts (default MonotonicClock)
    """

    description = MVME400

    def __init__(self, bus: RegisterBus, base: int, name: str | None = None,
                 clock: Clock | None = None) -> None:
        self.bus = bus
        self.base = base
        self.name = name or f"mvme400@0x{base:04X}"
        self.clock = clock if clock is not None else MonotonicClock()
        r = MVME400.reg
        self.pia = Pia6821(bus, base + r("PIA_PRA").offset, base + r("PIA_CRA").offset,
                           base + r("PIA_PRB").offset, base + r("PIA_CRB").offset,
                           name=f"{self.name}.PIA")
        self._data = (base + r("SIO_DATA_A").offset, base + r("SIO_DATA_B").offset)
        self._ctrl = (base + r("SIO_CTRL_A").offset, base + r("SIO_CTRL_B").offset)
        self.lock = threading.RLock()
        self._pa = 0x00
        self._baud_codes: list[int | None] = [None, None]  #: per channel; None before init
        self._ports: dict[int, Mvme400Port] = {}
        self.initialised = False

    # -- register access ----------------------------------------------------------------
    def _channel(self, channel: int) -> int:
        if channel not in (0, 1):
            raise ValueError(f"{self.name}: serial channel {channel!r} not 0 (A) or 1 (B) "
                             f"(board at A16 0x{self.base:04X})")
        return channel

    def _access(self, op: str, addr: int, reg: str, value: int = 0) -> int:
        try:
            if op == "r":
                return self.bus.read8(addr) & 0xFF
            self.bus.write8(addr, value & 0xFF)
            return 0
        except BusError as err:
            if err.board:
                raise
            raise err.with_context(self.name, reg) from None

    def _ctrl_write(self, ch: int, value: int) -> None:
        self._access("w", self._ctrl[ch], f"SIO_CTRL_{CHANNEL_NAMES[ch]}", value)

    def _ctrl_read(self, ch: int) -> int:
        return self._access("r", self._ctrl[ch], f"SIO_CTRL_{CHANNEL_NAMES[ch]}")

    def write_register(self, channel: int, n: int, value: int, command: int = 0) -> None:
        """Write 7201 WRn of ``channel`` (pointer in WR0, then the value).

        :param command: WR0 command bits to issue with the pointer (e.g. reset Tx int)
        """
        ch = self._channel(channel)
        with self.lock:
            if n == 0:
                self._ctrl_write(ch, value)
                return
            self._ctrl_write(ch, (n & 0x07) | command)
            self._ctrl_write(ch, value)

    def read_register(self, channel: int, n: int) -> int:
        """Read 7201 RRn of ``channel`` (RR0 directly, others through the WR0 pointer)."""
        ch = self._channel(channel)
        with self.lock:
            if n:
                self._ctrl_write(ch, n & 0x07)
            return self._ctrl_read(ch)

    def read_data(self, channel: int) -> int:
        """Read the Rx FIFO of ``channel`` (one character)."""
        ch = self._channel(channel)
        return self._access("r", self._data[ch], f"SIO_DATA_{CHANNEL_NAMES[ch]}")

    def write_data(self, channel: int, value: int) -> None:
        """Write the Tx buffer of ``channel`` (one character; check TBE first)."""
        ch = self._channel(channel)
        self._access("w", self._data[ch], f"SIO_DATA_{CHANNEL_NAMES[ch]}", value)

    # -- set-up -------------------------------------------------------------------------
    @staticmethod
    def baud_code(baud: float) -> int:
        """The 4-bit rate code of ``baud``; :raises ValueError: if not in the table."""
        try:
            return BAUD_TO_CODE[baud]
        except KeyError:
            rates = ", ".join(f"{r:g}" for r in BAUD_CODES.values())
            raise ValueError(f"baud rate {baud!r} not available on the MVME400 (rates: {rates})") from None

    def _checked_code(self, ch: int, baud: float) -> int:
        try:
            return self.baud_code(baud)
        except ValueError as err:
            raise ValueError(f"{self.name} channel {CHANNEL_NAMES[ch]} (A16 0x{self.base:04X}): {err}") from None

    def _write_baud(self) -> None:
        pb = 0
        for ch, code in enumerate(self._baud_codes):
            pb |= (code or 0) << BAUD_SHIFT[ch]
        self.pia.write_port("b", pb)

    def init(self, baud_a: float = 19200, baud_b: float = 19200, *, auto_enables: bool = True) -> None:
        """Initialise the PIA and both 7201 channels (polled, 8N1, x16 clock).

        PIA (``VM400.C``): CRA = 0x00, DDRA = 0x18, CRA = 0x04; CRB = 0x00, DDRB = 0xFF,
        CRB = 0x04; PB = baud codes (PB7..4 channel A, PB3..0 channel B); PA = 0x00
        (FAIL LED off). 7201 (``bios.c``): channel reset 0x18 written **twice** per channel;
        WR2A = 0x14 first, WR2B = 0x00; per channel WR4 = 0x44, WR3 = 0xE1, WR5 = 0xEA;
        WR1A = 0x00, WR1B = 0x04 via WR0 = 0x29.

        :param baud_a: channel A rate (rack channel 0)
        :param baud_b: channel B rate (rack channel 1)
        :param auto_enables: WR3 b5 as ``bios.c`` (Tx gated by CTS, Rx by DCD); pass False
            when the cable does not wire CTS/DCD
        :raises ValueError: for a rate not in the table
        :raises BoardInitError: if a channel's Tx buffer is not empty after reset
        """
        codes = [self._checked_code(0, baud_a), self._checked_code(1, baud_b)]
        wr3 = INIT_WR3 if auto_enables else INIT_WR3 & ~WR3_AUTO_ENABLES
        with self.lock:
            self.pia.configure("a", PIA_DDRA)
            self.pia.configure("b", PIA_DDRB)
            self._baud_codes = list(codes)
            self._write_baud()
            self._pa = 0x00
            self.pia.write_port("a", self._pa)
            for ch in (0, 1):
                # DO NOT OPTIMIZE (bios.c): the second write reaches WR0 even if a pointer was pending
                self._ctrl_write(ch, INIT_CHANNEL_RESET)
                self._ctrl_write(ch, INIT_CHANNEL_RESET)
            self.write_register(0, 2, INIT_WR2A)
            self.write_register(1, 2, INIT_WR2B)
            for ch in (0, 1):
                self.write_register(ch, 4, INIT_WR4)
                self.write_register(ch, 3, wr3)
                self.write_register(ch, 5, INIT_WR5)
            self._ctrl_write(0, INIT_WR1_SELECT)
            self._ctrl_write(0, INIT_WR1A)
            self._ctrl_write(1, INIT_WR1_SELECT)
            self._ctrl_write(1, INIT_WR1B)
            for ch in (0, 1):
                rr0 = self._ctrl_read(ch)
                if not rr0 & RR0_TX_EMPTY:
                    raise BoardInitError(
                        f"{self.name}: channel {CHANNEL_NAMES[ch]} Tx buffer not empty after reset "
                        f"(RR0 = 0x{rr0:02X} at A16 0x{self._ctrl[ch]:04X})")
            self.initialised = True
        for ch, port in self._ports.items():
            port._baud = BAUD_CODES[codes[ch]]

    def set_baud(self, channel: int, baud: float) -> None:
        """Program ``channel``'s rate through the PIA port B nibble.

        :raises ValueError: for a rate not in the table or a bad channel
        :raises BoardError: before :meth:`init`
        """
        ch = self._channel(channel)
        code = self._checked_code(ch, baud)
        if not self.initialised:
            raise BoardError(f"{self.name}: set_baud before init() (board at A16 0x{self.base:04X})")
        with self.lock:
            self._baud_codes[ch] = code
            self._write_baud()
        if ch in self._ports:
            self._ports[ch]._baud = BAUD_CODES[code]

    def baud(self, channel: int) -> float | None:
        """The rate last programmed for ``channel`` (None before init)."""
        code = self._baud_codes[self._channel(channel)]
        return None if code is None else BAUD_CODES[code]

    def set_fail_led(self, on: bool) -> None:
        """FAIL LED on/off (PA4)."""
        with self.lock:
            self._pa = (self._pa | PA_FAIL_LED) if on else (self._pa & ~PA_FAIL_LED)
            self.pia.write_port("a", self._pa)

    def dsr(self, channel: int) -> bool:
        """DSR input of ``channel`` (PA6 / PA7)."""
        ch = self._channel(channel)
        with self.lock:
            return bool(self.pia.read_port("a") & PA_DSR[ch])

    def port(self, channel: int, **settings) -> "Mvme400Port":
        """The byte port of ``channel`` (0 = A, 1 = B); created once, then reused.

        :param settings: ``timeout``, ``write_timeout``, ``max_buffer_bytes`` on first creation
        """
        ch = self._channel(channel)
        if ch not in self._ports:
            self._ports[ch] = Mvme400Port(self, ch, **settings)
        else:
            for key, value in settings.items():
                setattr(self._ports[ch], key, value)
        return self._ports[ch]

    def poll(self) -> int:
        """Drain the Rx FIFO of every port created so far; returns characters moved."""
        moved = 0
        for p in self._ports.values():  # a plain loop: this runs thousands of times a second
            if p.is_open:
                moved += p.poll()
        return moved


class Mvme400Port:
    """A pyserial-like byte port on one 7201 channel (polled).

    :param board: the initialised :class:`Mvme400`
    :param channel: 0 (A) or 1 (B)
    :param timeout: ``read`` wait in seconds: None = until ``size`` bytes, 0 = non-blocking
    :param write_timeout: longest wait for the Tx buffer per character (None = forever)
    :param max_buffer_bytes: software receive buffer bound (excess is counted and dropped)
    :param write_queue: ``write`` queues the bytes and returns at once; :meth:`poll` moves
        one queued byte into the Tx buffer whenever it is empty (for callers that must not
        wait 0.52 ms per character, such as the service's frame)

    ``autopoll`` (default True): ``in_waiting``, ``read_all`` and non-blocking reads
    (``timeout == 0``) drain the FIFO first. An owner that drains it itself on a schedule
    (the service, several times a frame) sets it False, so decoding reads only the
    software buffer instead of making another dozen register accesses per call.
    """

    def __init__(self, board: Mvme400, channel: int, timeout: float | None = 1.0,
                 write_timeout: float | None = 0.1, max_buffer_bytes: int = 65536,
                 write_queue: bool = False) -> None:
        self.board = board
        self.channel = channel
        self.timeout = timeout
        self.write_timeout = write_timeout
        self.max_buffer_bytes = max_buffer_bytes
        self.name = f"{board.name}:{CHANNEL_NAMES[channel]}"
        self.port = self.name  # pyserial attribute
        self.stats = LinkStats()
        self.is_open = True
        self._buf = bytearray()
        self.write_queue = write_queue
        self._txq = bytearray()
        self._baud = board.baud(channel)
        self._last_poll_t: float | None = None
        self.autopoll = True

    # -- pyserial-like settings ---------------------------------------------------------
    @property
    def baudrate(self) -> float | None:
        """The programmed rate; setting it reprograms the board (ValueError if not in the table)."""
        return self._baud

    @baudrate.setter
    def baudrate(self, baud: float) -> None:
        self.board.set_baud(self.channel, baud)

    def _check_open(self) -> None:
        if not self.is_open:
            raise LinkError(f"{self.name}: port is closed")

    def _char_time_s(self) -> float:
        return char_time_s(self._baud or 19200)

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        """Close the port (the board keeps running; the software buffer is dropped)."""
        self.is_open = False
        self._buf.clear()

    def __enter__(self) -> "Mvme400Port":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- receive --------------------------------------------------------------------------
    def poll(self) -> int:
        """Drain the hardware Rx FIFO into the software buffer; returns characters moved.

        Per character: RR0 b0, then RR1 (errors), then the data register; an error in
        RR1 is counted and cleared with WR0 error reset (0x30).
        """
        if not self.is_open:
            self._check_open()
        b = self.board
        ch = self.channel
        buf, stats = self._buf, self.stats
        now = b.clock.now()
        last = self._last_poll_t
        if last is not None and now - last > stats.max_poll_gap_s:
            stats.max_poll_gap_s = now - last
        self._last_poll_t = now
        moved = 0
        # the same register sequence as read_register/read_data/write_register, with the
        # bus calls bound once: this runs several times per frame in the service
        read8, write8 = b.bus.read8, b.bus.write8
        ctrl, data = b._ctrl[ch], b._data[ch]
        errors = _RR1_ERRORS
        with b.lock:
            try:
                # bounded: a stuck RR0 b0 cannot hang the caller
                for _ in range(4 * RX_FIFO_DEPTH):
                    if not read8(ctrl) & RR0_RX_AVAILABLE:
                        break
                    write8(ctrl, 1)  # WR0 pointer -> RR1 (errors of the character at the head)
                    rr1 = read8(ctrl)
                    value = read8(data) & 0xFF
                    if rr1 & errors:
                        stats.overruns += bool(rr1 & RR1_RX_OVERRUN)
                        stats.parity_errors += bool(rr1 & RR1_PARITY_ERROR)
                        stats.framing_errors += bool(rr1 & RR1_FRAMING_ERROR)
                        write8(ctrl, CMD_ERROR_RESET)
                    stats.rx_bytes += 1
                    moved += 1
                    if len(buf) >= self.max_buffer_bytes:
                        stats.buffer_overflows += 1
                    else:
                        buf.append(value)
                if self._txq and read8(ctrl) & RR0_TX_EMPTY:
                    write8(data, self._txq.pop(0))
                    stats.tx_bytes += 1
            except BusError as err:
                if err.board:
                    raise
                reg = ("SIO_CTRL_" if err.addr == ctrl else "SIO_DATA_") + CHANNEL_NAMES[ch]
                raise err.with_context(b.name, reg) from None
        return moved

    @property
    def in_waiting(self) -> int:
        """Bytes available now (polls first, unless ``autopoll`` is off)."""
        if self.autopoll:
            self.poll()
        return len(self._buf)

    def read(self, size: int = 1) -> bytes:
        """Up to ``size`` bytes received within ``timeout`` seconds (on the board's clock).

        Polls the FIFO once per character time while waiting.
        """
        self._check_open()
        if size <= 0:
            return b""
        clock = self.board.clock
        deadline = None if self.timeout is None else clock.now() + self.timeout
        while True:
            if self.autopoll or self.timeout != 0:
                self.poll()
            if len(self._buf) >= size or self.timeout == 0:
                break
            now = clock.now()
            if deadline is not None and now >= deadline:
                break
            wake = now + self._char_time_s()
            clock.sleep_until(wake if deadline is None else min(wake, deadline))
        out = bytes(self._buf[:size])
        del self._buf[:size]
        return out

    def read_all(self) -> bytes:
        """Everything buffered now (non-blocking)."""
        if self.autopoll:
            self.poll()
        out = bytes(self._buf)
        self._buf.clear()
        return out

    def reset_input_buffer(self) -> None:
        """Discard the hardware FIFO and the software buffer."""
        self.poll()
        self._buf.clear()

    # -- transmit -------------------------------------------------------------------------
    def _wait_tx(self, what: str, mask: int, use_rr1: bool, done: int, total: int) -> None:
        b = self.board
        clock = b.clock
        deadline = None if self.write_timeout is None else clock.now() + self.write_timeout
        while True:
            reg = b.read_register(self.channel, 1 if use_rr1 else 0)
            if reg & mask:
                return
            self.poll()  # keep the Rx FIFO drained while waiting
            now = clock.now()
            if deadline is not None and now >= deadline:
                rr0 = b.read_register(self.channel, 0)
                raise PfmaTimeoutError(
                    f"{self.name}: {what} not reached within {self.write_timeout} s after {done} of "
                    f"{total} bytes (CTS {'asserted' if rr0 & RR0_CTS else 'NOT asserted'}, "
                    f"DCD {'asserted' if rr0 & RR0_DCD else 'NOT asserted'}; SIO_CTRL_"
                    f"{CHANNEL_NAMES[self.channel]} at A16 0x{b._ctrl[self.channel]:04X})")
            wake = now + self._char_time_s() / 2
            clock.sleep_until(wake if deadline is None else min(wake, deadline))

    def write(self, data: bytes | bytearray | memoryview) -> int:
        """Send ``data``: per character wait for TBE (RR0 b2, bounded by ``write_timeout``).

        :returns: number of bytes written
        :raises PfmaTimeoutError: when the Tx buffer stays full (CTS low with auto enables,
            Tx disabled); the message says how many bytes went out and the CTS/DCD state
        """
        self._check_open()
        data = bytes(data)
        if self.write_queue:
            if len(self._txq) + len(data) > self.max_buffer_bytes:
                raise PfmaTimeoutError(f"{self.name}: transmit queue full ({len(self._txq)} bytes "
                                       f"waiting); the line is not keeping up")
            self._txq += data
            return len(data)
        for i, value in enumerate(data):
            # the lock is taken per register access, never across a wait
            self._wait_tx("Tx buffer empty (RR0 b2)", RR0_TX_EMPTY, False, i, len(data))
            self.board.write_data(self.channel, value)
            self.stats.tx_bytes += 1
        return len(data)

    def flush(self) -> None:
        """Wait until every written character has left the shift register (RR1 b0 all sent)."""
        self._check_open()
        self._wait_tx("all sent (RR1 b0)", RR1_ALL_SENT, True, self.stats.tx_bytes, self.stats.tx_bytes)

    def reset_output_buffer(self) -> None:
        """Discard bytes queued by ``write`` in ``write_queue`` mode."""
        self._txq.clear()

    @property
    def out_waiting(self) -> int:
        """Bytes queued and not yet in the Tx buffer (``write_queue`` mode)."""
        return len(self._txq)

    # -- modem lines -----------------------------------------------------------------------
    @property
    def cts(self) -> bool:
        return bool(self.board.read_register(self.channel, 0) & RR0_CTS)

    @property
    def cd(self) -> bool:
        return bool(self.board.read_register(self.channel, 0) & RR0_DCD)

    @property
    def dsr(self) -> bool:
        return self.board.dsr(self.channel)
