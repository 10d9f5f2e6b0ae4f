"""A second, independent model of the register models R1-R5, for the drivers' tests.

Written from the register tables (hardware-registers.md R1-R5, as copied into
``drivers/*/registers.py``) without using ``fakes/``: the drivers must work against
*any* bus object with ``read8/read16/write8/write16`` that implements the documented
model, not only against the project's own fakes. So this model deliberately differs
from the fakes where R1-R5 leave room:

- a bus access costs **no** model time: a conversion or a serial character completes
  only as the shared clock moves (as it does on real time, where the driver's polls
  can come faster than the 4 us conversion);
- each board decodes only its registers (RTD +0x00..+0x0B; odd-byte boards +0x01..+0x0F);
  anything else, 8-bit access to a word board, 16-bit access to an odd-byte board
  included, is a bare ``BusError(addr, width, op)`` that names no board: the drivers
  must add the board and register themselves;
- the matrix switcher acknowledges at once, inside the CRA write that ends the strobe;
- block transfers are plain loops of single accesses (no cheaper path anywhere), and the
  ADC's scan mode is written here from its R3 description, not from ``fakes.adc``.

Physical side: attributes (``rtd1.angle``, ``adc.volts``, ``pia.pins``...), the
``Sio`` peer (``peer_send``/``peer_recv``) and the clock (``pfma.clock.SimClock``).
"""

from __future__ import annotations

import math

from pfma.errors import BusError


class NoDecode(Exception):
    """The board does not decode this offset (the rack turns it into a BusError)."""


# -- R1: VMIVME-4940 --------------------------------------------------------------------
class Rdc:
    def __init__(self) -> None:
        self.angle = [0.0] * 4  # rad, the physical side
        self.fault = [False] * 4
        self.reference = True
        self.control = 0
        self._held = [0] * 4

    def counts(self, ch: int) -> int:
        return int(math.floor(self.angle[ch] % (2 * math.pi) / (2 * math.pi) * 16384)) & 0x3FFF

    def read16(self, off: int) -> int:
        if off in (0, 2, 4, 6):
            ch = off // 2
            return self._held[ch] if self.control >> ch & 1 else self.counts(ch)
        if off == 8:
            return sum(1 << n for n in range(4) if self.fault[n]) | (0x10 if self.reference else 0)
        if off == 0x0A:
            return self.control
        raise NoDecode

    def write16(self, off: int, value: int) -> None:
        if off in (0, 2, 4, 6, 8):
            return  # read-only: ignored
        if off != 0x0A:
            raise NoDecode
        for ch in range(4):
            if value >> ch & 1 and not self.control >> ch & 1:
                self._held[ch] = self.counts(ch)
        self.control = value & 0x400F


# -- R2: VMIVME-4100 ---------------------------------------------------------------------
class Dac:
    def __init__(self) -> None:
        self.code = [0x800] * 16
        self.ctrl = 0  # D14..D8
        self.writes: list[tuple[int, int]] = []

    def volts(self, ch: int) -> float:
        return -10.0 + 20.0 * self.code[ch] / 4096 if self.ctrl & 0x01 else 0.0

    def read16(self, off: int) -> int:
        if 0 <= off < 0x20:
            return self.ctrl << 8
        raise NoDecode

    def write16(self, off: int, value: int) -> None:
        if not 0 <= off < 0x20:
            raise NoDecode
        self.writes.append((off, value))
        if value & 0x8000:
            self.ctrl = value >> 8 & 0x7F
        else:
            self.code[off // 2] = value & 0x0FFF


# -- R3: DVME-611B -----------------------------------------------------------------------
class Adc:
    """R3 with its scan mode: START with b0 = 1 converts channel k (sampled at 4k us after
    the START) into SCAN[k] (word at 0x40 + 2k) at 4(k+1) us; busy 128 us, then EOC, DATA =
    channel 31. A sample is taken the first time the model is touched after its time (the
    tests set ``volts`` before they scan)."""

    def __init__(self, clock) -> None:
        self.clock = clock
        self.volts = [0.0] * 32
        self.stuck_busy = False
        self.ch = self.autoinc = self.ie = self.eoc = 0
        self.result = 0
        self.scan_buf = [0] * 32
        self._due: float | None = None
        self._pending = self._pending_ch = 0
        self._scan_from: float | None = None  # START time of a scan in progress
        self._taken: list[int] = []  # the scan's samples so far, channel order

    def _code(self, ch: int) -> int:
        v = min(10.0, max(-10.0, self.volts[ch]))
        return min(4095, int(math.floor((v + 10.0) / 20.0 * 4096)))

    def _run(self) -> None:
        if self.stuck_busy:
            return
        now = self.clock.now()
        if self._scan_from is not None:
            for k in range(len(self._taken), 32):
                if now < self._scan_from + k * 4e-6:
                    break
                self._taken.append(self._code(k))
            for k, code in enumerate(self._taken):
                if now >= self._scan_from + (k + 1) * 4e-6:
                    self.scan_buf[k] = code
            if now >= self._scan_from + 32 * 4e-6:
                self._scan_from, self._due, self.result, self.eoc = None, None, self._taken[31], 1
            return
        if self._due is not None and now >= self._due:
            self._due, self.result, self.eoc = None, self._pending, 1
            self.scan_buf[self._pending_ch] = self._pending

    def read16(self, off: int) -> int:
        self._run()
        busy = self._due is not None
        if off == 0:
            return (self.ch | self.autoinc << 5 | self.ie << 14 | (0x100 if busy else 0)
                    | self.eoc << 15)
        if off == 4:
            if not busy:
                self.eoc = 0
                if self.autoinc:
                    self.ch = (self.ch + 1) % 32
            return self.result
        if off == 6:
            return 0x0611
        if 0x40 <= off < 0x80:
            return self.scan_buf[(off - 0x40) // 2]
        raise NoDecode

    def write16(self, off: int, value: int) -> None:
        self._run()
        if off == 0:
            self.ch, self.autoinc, self.ie = value & 0x1F, value >> 5 & 1, value >> 14 & 1
        elif off == 2 and value & 1:  # scan
            self._scan_from, self._taken = self.clock.now(), []
            self._due, self.eoc = self._scan_from + 32 * 4e-6, 0
            self._run()  # channel 0 is sampled at once
        elif off == 2:
            self._pending, self._pending_ch = self._code(self.ch), self.ch
            self._scan_from = None
            self._due, self.eoc = self.clock.now() + 4e-6, 0
        elif off not in (4, 6) and not 0x40 <= off < 0x80:
            raise NoDecode


# -- MC6821 (R4 PIA, R5) ------------------------------------------------------------------
class Pia:
    def __init__(self) -> None:
        self.cr = {"a": 0, "b": 0}
        self.ddr = {"a": 0, "b": 0}
        self.latch = {"a": 0, "b": 0}
        self.pins = {"a": 0xFF, "b": 0xFF}  # driven input levels (undriven = high)
        self.flag1 = {"a": 0, "b": 0}
        self.c1 = {"a": 1, "b": 1}
        self.c2 = {"a": 1, "b": 1}  # C2 output level
        self.on_c2 = None  # f(side, old, new)

    def output(self, s: str) -> int:
        return self.latch[s] & self.ddr[s]

    def _set_c2(self, s: str, level: int) -> None:
        old, self.c2[s] = self.c2[s], level
        if old != level and self.on_c2:
            self.on_c2(s, old, level)

    def read(self, rs: int) -> int:
        s = "ab"[rs >> 1]
        if rs & 1:
            return self.flag1[s] << 7 | self.cr[s]
        if not self.cr[s] & 0x04:
            return self.ddr[s]
        self.flag1[s] = 0
        return (self.latch[s] & self.ddr[s]) | (self.pins[s] & ~self.ddr[s] & 0xFF)

    def write(self, rs: int, value: int) -> None:
        s = "ab"[rs >> 1]
        if rs & 1:
            self.cr[s] = value & 0x3F
            if value & 0x30 == 0x30:  # C2 output, set/reset mode
                self._set_c2(s, value >> 3 & 1)
        elif self.cr[s] & 0x04:
            self.latch[s] = value
        else:
            self.ddr[s] = value

    def drive_c1(self, s: str, level: int) -> None:
        old, self.c1[s] = self.c1[s], level
        if old != level and bool(level) == bool(self.cr[s] & 0x02):
            self.flag1[s] = 1


class OddByteBoard:
    def __init__(self, chips: dict[int, tuple[object, int]]) -> None:
        self._at = chips  # offset -> (chip, register select)

    def read8(self, off: int) -> int:
        if off not in self._at:
            raise NoDecode
        chip, rs = self._at[off]
        return chip.read(rs)

    def write8(self, off: int, value: int) -> None:
        if off not in self._at:
            raise NoDecode
        chip, rs = self._at[off]
        chip.write(rs, value)


class Mvme410(OddByteBoard):
    """R5: PIA1 at +1/3/5/7, PIA2 at +9/B/D/F; a matrix switcher on PIA1 port A."""

    def __init__(self) -> None:
        self.pia1, self.pia2 = Pia(), Pia()
        super().__init__({1 + 2 * i: (self.pia1, i) for i in range(4)}
                         | {9 + 2 * i: (self.pia2, i) for i in range(4)})
        self.routes: list[int] = []
        self.acknowledge = True
        self.pia1.on_c2 = self._strobe

    def _strobe(self, side: str, old: int, new: int) -> None:
        if side == "a" and not old and new:  # CA2 back high: latch, then pulse CA1
            self.routes.append(self.pia1.output("a"))
            if self.acknowledge:
                self.pia1.drive_c1("a", 0)
                self.pia1.drive_c1("a", 1)


# -- R4: MVME400 ---------------------------------------------------------------------------
BAUD = (50, 75, 110, 134.5, 150, 300, 600, 1200, 1800, 2000, 2400, 3600, 4800, 7200, 9600, 19200)


class SioChannel:
    def __init__(self, board: "Mvme400", idx: int) -> None:
        self.board, self.idx = board, idx
        self.cts = self.dcd = True
        self.peer_baud = 19200
        self.to_peer = bytearray()
        self.line: list[tuple[float, int]] = []  # (arrival time, byte) from the peer
        self.reset()

    def reset(self) -> None:
        self.wr = [0] * 8
        self.ptr = 0
        self.fifo: list[int] = []
        self.overrun = 0
        self.txbuf: int | None = None
        self.shift: tuple[float, int] | None = None  # (done time, byte)

    def baud(self) -> float | None:
        shift = 4 if self.idx == 0 else 0
        if (self.board.pia.ddr["b"] >> shift) & 0xF != 0xF:
            return None
        mult = {0x00: 1, 0x40: 16, 0x80: 32, 0xC0: 64}[self.wr[4] & 0xC0]
        return BAUD[self.board.pia.output("b") >> shift & 0xF] * 16 / mult

    def char_s(self) -> float:
        return 10.0 / (self.baud() or 1e-3)

    def run(self, now: float) -> None:
        tx_on = self.wr[5] & 0x08 and (self.cts or not self.wr[3] & 0x20)
        while True:
            if self.shift is None and self.txbuf is not None and tx_on:
                self.shift, self.txbuf = (now + self.char_s(), self.txbuf), None
            if self.shift is not None and now >= self.shift[0]:
                if self.baud() == self.peer_baud:
                    self.to_peer.append(self.shift[1])
                self.shift = None
                continue
            break
        rx_on = self.wr[3] & 0x01 and (self.dcd or not self.wr[3] & 0x20)
        while self.line and self.line[0][0] <= now:
            _, byte = self.line.pop(0)
            if not rx_on or self.baud() != self.peer_baud:
                continue
            if len(self.fifo) == 3:
                self.overrun = 1
            else:
                self.fifo.append(byte)

    def read_rr(self) -> int:
        n, self.ptr = self.ptr, 0
        if n == 0:
            return ((1 if self.fifo else 0) | (4 if self.txbuf is None else 0)
                    | (8 if self.dcd else 0) | (0x20 if self.cts else 0))
        if n == 1:
            return (1 if self.txbuf is None and self.shift is None else 0) | self.overrun << 5
        return 0

    def write_wr(self, value: int) -> None:
        if self.ptr:
            self.wr[self.ptr], self.ptr = value, 0
            return
        self.ptr = value & 0x07
        if value & 0x38 == 0x18:
            self.reset()
        elif value & 0x38 == 0x30:
            self.overrun = 0


class Mvme400(OddByteBoard):
    """R4: PIA at +1/3/5/7, uPD7201 data A/B at +9/+B, control A/B at +D/+F."""

    def __init__(self, clock) -> None:
        self.clock = clock
        self.pia = Pia()
        super().__init__({1 + 2 * i: (self.pia, i) for i in range(4)})
        self.ch = (SioChannel(self, 0), SioChannel(self, 1))

    def _sync(self) -> None:
        now = self.clock.now()
        for c in self.ch:
            c.run(now)

    def read8(self, off: int) -> int:
        if off == 1:  # PA inputs: jumpers 7, b5 mirrors the LED output b4, DSR b6/b7 asserted
            led = self.pia.latch["a"] >> 4 & 1
            self.pia.pins["a"] = 0x07 | led << 5 | 0xC0
        if off not in (9, 0x0B, 0x0D, 0x0F):
            return super().read8(off)
        self._sync()
        c = self.ch[(off >> 1) & 1]
        if off < 0x0D:
            return c.fifo.pop(0) if c.fifo else 0
        return c.read_rr()

    def write8(self, off: int, value: int) -> None:
        if off not in (9, 0x0B, 0x0D, 0x0F):
            return super().write8(off, value)
        self._sync()
        c = self.ch[(off >> 1) & 1]
        if off < 0x0D:
            if c.txbuf is None:
                c.txbuf = value
        else:
            c.write_wr(value)
        self._sync()

    def peer_send(self, ch: int, data: bytes) -> None:
        """The far end sends ``data``: one character per 10/baud s from now."""
        self._sync()
        c = self.ch[ch]
        t = max([self.clock.now()] + [due for due, _ in c.line])
        for byte in data:
            t += 10.0 / c.peer_baud
            c.line.append((t, byte))

    def peer_recv(self, ch: int) -> bytes:
        self._sync()
        out = bytes(self.ch[ch].to_peer)
        self.ch[ch].to_peer.clear()
        return out


# -- the rack ------------------------------------------------------------------------------
class RModelRack:
    """The PFMA rack (IRSS report 3.4.2 addresses) on the R1-R5 models above.

    :param clock: shared time base (``pfma.clock.SimClock``); bus accesses do not move it
    """

    def __init__(self, clock) -> None:
        self.clock = clock
        self.rtd1, self.rtd2, self.dac, self.adc = Rdc(), Rdc(), Dac(), Adc(clock)
        self.sio, self.pio_video, self.pio_user = Mvme400(clock), Mvme410(), Mvme410()
        self._map = [  # base, size, board, 16-bit board?
            (0x0100, 0x0C, self.rtd1, True), (0x0200, 0x0C, self.rtd2, True),
            (0xD000, 0x20, self.dac, True), (0xC000, 0x80, self.adc, True),
            (0x0000, 0x10, self.sio, False), (0x0020, 0x10, self.pio_video, False),
            (0x0040, 0x10, self.pio_user, False),
        ]

    def _board(self, addr: int, width: int, op: str):
        for base, size, board, word in self._map:
            if base <= addr < base + size:
                if (width == 16) == word and not (word and addr % 2):
                    return board, addr - base
                break
        raise BusError(addr, width, op)

    def _do(self, addr: int, width: int, op: str, value: int | None = None):
        if value is not None and (type(value) is not int or not 0 <= value < 1 << width):
            raise ValueError(f"write{width} 0x{addr:04X}: bad value {value!r}")
        board, off = self._board(addr, width, op)
        try:
            if value is None:
                return getattr(board, f"read{width}")(off)
            getattr(board, f"write{width}")(off, value)
        except NoDecode:
            raise BusError(addr, width, op) from None

    def read8(self, addr: int) -> int:
        return self._do(addr, 8, "read")

    def read16(self, addr: int) -> int:
        return self._do(addr, 16, "read")

    def write8(self, addr: int, value: int) -> None:
        self._do(addr, 8, "write", value)

    def write16(self, addr: int, value: int) -> None:
        self._do(addr, 16, "write", value)

    # block transfers: consecutive words, each one access of the model (no cheaper path),
    # checked as the contract says; the first word nobody answers is named
    def read_block16(self, addr: int, n: int) -> list[int]:
        if type(n) is not int or n < 1 or not 0 <= addr <= 0x10000 - 2 * n:
            raise ValueError(f"read_block16 0x{addr:04X}: bad block of {n!r} words")
        if addr % 2:
            raise BusError(addr, 16, "read")
        return [self.read16(addr + 2 * i) for i in range(n)]

    def write_block16(self, addr: int, words) -> None:
        words = list(words)
        if not words or not 0 <= addr <= 0x10000 - 2 * len(words):
            raise ValueError(f"write_block16 0x{addr:04X}: bad block of {len(words)} words")
        for i, w in enumerate(words):
            if type(w) is not int or not 0 <= w < 0x10000:
                raise ValueError(f"write_block16 0x{addr + 2 * i:04X}: bad value {w!r}")
        if addr % 2:
            raise BusError(addr, 16, "write")
        for i, w in enumerate(words):
            self.write16(addr + 2 * i, w)
