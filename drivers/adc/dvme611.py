"""Driver for the Datel DVME-611B 32-channel 12-bit A/D board.

Register model: ``drivers.adc.registers.DVME611`` (R3, assumed). Conversions are
polled with a bounded number of CSR reads, so a dead converter raises
:class:`~pfma.errors.BoardError` instead of hanging the I/O loop. The bound is
``max_polls`` reads **and** at least ``min_wait_s`` of wall-clock time: a board (or
a model of one) whose 4 us conversion runs on real time must not be declared stuck
just because the polls came faster than 4 us apart.

A 32-channel scan takes the fewest bus transactions the register table allows: with
the table's ``scan_mode`` (R3, assumed) one START write with the SCAN bit, EOC polls
(bounded by 32 x ``max_polls`` reads and 32 x ``min_wait_s``: a scan is 32 conversions)
and ONE block read of the SCAN buffer; without it, the per-channel auto-increment
sequence (CSR once, then START, EOC polls and DATA per channel).
"""

from __future__ import annotations

import time

import numpy as np

from drivers.adc.registers import (AUTOINC, BUSY, CSR, DATA, DVME611, EOC, N_CHANNELS, SCAN,
                                   SCAN_CMD, START)
from drivers.bus import RegisterBus
from drivers.registers import check_channel, register_name
from pfma.errors import BoardError, BusError

_EOC = EOC.mask
_BUSY = BUSY.mask
_CH = 0x1F
_AUTOINC = AUTOINC.mask
_CODE = 0x0FFF
_RANGE_VOLTS = DVME611.constants["range_volts"]  #: default bipolar range (assumed +-10 V, R3)


class Dvme611:
    """One DVME-611B board at A16 ``base``.

    :param bus: any object with ``read16``/``write16`` on absolute A16 addresses
    :param base: board base address (0xC000 in the PFMA rack)
    :param name: board name for messages (default ``dvme611@0xBASE``)
    :param range_volts: bipolar input range, +-range_volts offset binary (default: the
        register table's ``range_volts``)
    :param max_polls: CSR reads allowed per conversion before giving up (BoardError)
    :param min_wait_s: after ``max_polls`` reads without EOC, keep polling until this much
        wall-clock time has passed (0 = give up after exactly ``max_polls`` reads); one last
        read is always made after the deadline, so a conversion that ended is never missed
    :param timer: wall-clock seconds for ``min_wait_s`` (default ``time.perf_counter``)
    """

    description = DVME611
    n_channels = N_CHANNELS

    def __init__(self, bus: RegisterBus, base: int, name: str | None = None, *, range_volts: float = _RANGE_VOLTS,
                 max_polls: int = 64, min_wait_s: float = 50e-6, timer=time.perf_counter) -> None:
        if not range_volts > 0:
            raise ValueError(f"range_volts must be positive, not {range_volts!r}")
        if max_polls < 1:
            raise ValueError(f"max_polls must be at least 1, not {max_polls!r}")
        self.bus = bus
        self.base = base
        self.name = name or f"{DVME611.kind}@0x{base:04X}"
        self.range_volts = float(range_volts)
        if not min_wait_s >= 0:
            raise ValueError(f"min_wait_s must be >= 0, not {min_wait_s!r}")
        self.max_polls = int(max_polls)
        self.min_wait_s = float(min_wait_s)
        self._timer = timer
        self.lsb_volts = 2.0 * self.range_volts / DVME611.constants["full_scale_counts"]
        self.zero_code = DVME611.constants["full_scale_counts"] // 2
        self._csr = base + CSR.offset
        self._start = base + START.offset
        self._data = base + DATA.offset
        self._scan = base + SCAN.offset
        self._counts = np.zeros(N_CHANNELS, dtype=np.int64)

    # -- errors / validation ----------------------------------------------------------
    def _bus_error(self, err: BusError, channel: int | None, what: str | None = None) -> BusError:
        reg = register_name(DVME611, err.addr - self.base)
        if channel is not None:
            reg = f"{reg} (channel {channel})"
        elif what:
            reg = f"{reg} ({what})"
        return err.with_context(self.name, reg)

    def _check_channel(self, channel: int) -> int:
        return check_channel(self.name, self.base, channel, N_CHANNELS)

    def _no_eoc(self, channel: int | None, csr: int, polls: int, scale: int = 1) -> BoardError:
        what = "busy stuck" if csr & _BUSY else "no EOC"
        waited = f" and {self.min_wait_s * scale * 1e6:g} us" if self.min_wait_s else ""
        doing = f"converting channel {channel}" if channel is not None else \
            f"scanning channels 0..{N_CHANNELS - 1}"
        return BoardError(
            f"{self.name}: {what} {doing}: CSR at A16 0x{self._csr:04X} "
            f"= 0x{csr:04X} after {polls} polls{waited}")

    # -- conversion ---------------------------------------------------------------------
    def _convert_run(self, csr_word: int, channels: range | tuple[int, ...]) -> list[int]:
        """Write ``csr_word`` to the CSR, then for each channel in turn: START, poll EOC
        (bounded), check that the CSR selects that channel, read DATA. The one conversion
        sequence of single reads and scans; bus calls are bound once (the service scans 32
        channels every other frame, ~5 accesses each).

        :raises BusError: naming the board, register and the channel being converted
        """
        w16, r16 = self.bus.write16, self.bus.read16
        start, csr_addr, data, polls = self._start, self._csr, self._data, range(self.max_polls)
        codes = []
        ch = channels[0]  # a failing CSR write names the first channel
        try:
            w16(csr_addr, csr_word)
            for ch in channels:
                w16(start, 0)
                csr = 0
                for _ in polls:
                    csr = r16(csr_addr)
                    if csr & _EOC:
                        break
                else:
                    csr = self._wait_eoc_slow(ch, csr)
                if csr & _CH != ch:
                    raise BoardError(f"{self.name}: CSR at A16 0x{csr_addr:04X} selects channel "
                                     f"{csr & _CH}, expected {ch} (auto-increment out of step)")
                codes.append(r16(data) & _CODE)
        except BusError as err:
            raise self._bus_error(err, ch) from err
        return codes

    def _wait_eoc_slow(self, channel: int | None, csr: int, scale: int = 1) -> int:
        """``max_polls`` (x ``scale``: 32 for a scan) reads saw no EOC: poll on until
        ``min_wait_s`` (x ``scale``) has passed, then fail."""
        polls = self.max_polls * scale
        if self.min_wait_s > 0:
            timer = self._timer
            deadline = timer() + self.min_wait_s * scale
            while True:
                expired = timer() >= deadline  # checked BEFORE the read: the
                csr = self.bus.read16(self._csr)  # last read always follows the deadline
                polls += 1
                if csr & _EOC:
                    return csr
                if expired:
                    break
        raise self._no_eoc(channel, csr, polls, scale)

    def read_counts(self, channel: int) -> int:
        """Convert one channel; returns the 12-bit code (offset binary).

        :raises ValueError: channel outside 0..31
        :raises BoardError: no end of conversion within ``max_polls`` CSR reads and
            ``min_wait_s`` seconds
        :raises BusError: naming the board, register, channel and address
        """
        ch = self._check_channel(channel)
        return self._convert_run(ch, (ch,))[0]  # CSR: single mode on ch, gain x1, no interrupt

    @property
    def scan_mode(self) -> bool:
        """Whether :meth:`scan` uses the board's scan mode: the register table says
        (``DVME611.constants["scan_mode"]``), read at each scan."""
        return bool(DVME611.constants.get("scan_mode", False))

    def scan(self, out: np.ndarray | None = None) -> np.ndarray:
        """Convert all 32 channels; returns their codes. With the table's ``scan_mode``:
        one START (SCAN), EOC polls, one block read of SCAN; else the per-channel
        auto-increment sequence.

        :param out: optional preallocated integer array of length 32 to fill
        :raises BoardError: no end of scan within the bound (or auto-increment out of step)
        :raises BusError: naming the board and register
        """
        if out is None:
            out = np.empty(N_CHANNELS, dtype=np.int64)
        if self.scan_mode:
            self.start_scan()
            out[:] = self.read_scan()
        else:
            out[:] = self._convert_run(_AUTOINC, range(N_CHANNELS))  # from channel 0
        return out

    def start_scan(self) -> None:
        """Start a scan of all 32 channels (scan mode: one START write with the SCAN bit;
        128 us of conversions follow). :meth:`read_scan` collects it, so a caller may do
        other work while the board converts."""
        try:
            self.bus.write16(self._start, SCAN_CMD.mask)
        except BusError as err:
            raise self._bus_error(err, None, "scan") from err

    def read_scan(self) -> list[int]:
        """Wait for the end of the scan started by :meth:`start_scan` (bounded EOC polls),
        then read all 32 results with ONE block read of SCAN; returns the codes."""
        r16, csr_addr, csr = self.bus.read16, self._csr, 0
        try:
            for _ in range(self.max_polls * N_CHANNELS):
                csr = r16(csr_addr)
                if csr & _EOC:
                    break
            else:
                self._wait_eoc_slow(None, csr, N_CHANNELS)
            words = self.bus.read_block16(self._scan, N_CHANNELS)
        except BusError as err:
            raise self._bus_error(err, None, "scan") from err
        return [w & _CODE for w in words]

    # -- volts --------------------------------------------------------------------------------
    def volts_from_counts(self, counts, out: np.ndarray | None = None):
        """Offset binary code(s) to volts: V = (code - 2048) * LSB (the one place this
        board's coding is applied; zero code and LSB follow the register table's
        ``full_scale_counts`` and the range).

        :param counts: one code (returns a float) or an integer array of codes
        :param out: a float array as long as ``counts`` to fill in place (no allocation:
            the service converts every scan this way); returned
        """
        if out is None:
            return (counts - self.zero_code) * self.lsb_volts
        return np.multiply(np.subtract(counts, self.zero_code, out=out, casting="unsafe"), self.lsb_volts,
                           out=out)

    def read_volts(self, channel: int) -> float:
        """Convert one channel; returns volts."""
        return self.volts_from_counts(self.read_counts(channel))

    def scan_volts(self, out: np.ndarray | None = None) -> np.ndarray:
        """Scan all 32 channels; returns volts (fills ``out`` if given, a float array of 32)."""
        counts = self.scan(self._counts)
        if out is None:
            out = np.empty(N_CHANNELS)
        return self.volts_from_counts(counts, out=out)
