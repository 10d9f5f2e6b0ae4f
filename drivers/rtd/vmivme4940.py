"""Driver for the VMIC VMIVME-4940 4-channel 14-bit resolver-to-digital board.

Register model: ``drivers.rtd.registers.VMIVME4940`` (R1, assumed). Talks only to a
RegisterBus (any object with ``read16``/``write16``); knows nothing of rates or buffers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.bus import RegisterBus
from drivers.registers import check_channel, register_name
from drivers.rtd.registers import ANGLE, CONTROL, N_CHANNELS, STATUS, VMIVME4940
from pfma.errors import BusError


@dataclass(frozen=True)
class RtdStatus:
    """Decoded STATUS word."""

    faults: tuple[bool, ...]  #: per channel (N_CHANNELS): loss of signal or BIT fail
    reference_present: bool  #: 400 Hz reference seen
    raw: int  #: the STATUS word as read

    @property
    def ok(self) -> bool:
        """True when the reference is present and no channel reports a fault."""
        return self.reference_present and not any(self.faults)


class Vmivme4940:
    """One VMIVME-4940 board at A16 ``base``.

    :param bus: any object with ``read16``/``write16`` on absolute A16 addresses
    :param base: board base address (0x0100, 0x0200 in the PFMA rack)
    :param name: board name for messages (default ``vmivme4940@0xBASE``)
    """

    description = VMIVME4940
    n_channels = N_CHANNELS

    def __init__(self, bus: RegisterBus, base: int, name: str | None = None) -> None:
        self.bus = bus
        self.base = base
        self.name = name or f"{VMIVME4940.kind}@0x{base:04X}"
        self._ch_addr = tuple(base + VMIVME4940.reg(f"CH{n}").offset for n in range(N_CHANNELS))
        self._status_addr = base + STATUS.offset
        # R1: CH0..CH3 and STATUS are consecutive words, so one block reads them all;
        # a table that moves STATUS away gets two transactions instead (checked, not assumed)
        self._one_block = (self._ch_addr == tuple(self._ch_addr[0] + 2 * n for n in range(N_CHANNELS))
                           and self._status_addr == self._ch_addr[0] + 2 * N_CHANNELS)
        self._control_addr = base + CONTROL.offset
        self._shift = ANGLE.lsb
        self._mask = (1 << ANGLE.bits) - 1
        self.counts_per_rev = 1 << ANGLE.bits
        self.lsb_rad = VMIVME4940.constants["lsb_rad"]

    # -- errors -------------------------------------------------------------------
    def _bus_error(self, err: BusError) -> BusError:
        """The bus error, renamed with this board's name and the register at its address."""
        return err.with_context(self.name, register_name(VMIVME4940, err.addr - self.base))

    def _check_channel(self, channel: int) -> int:
        return check_channel(self.name, self.base, channel, N_CHANNELS)

    # -- scaling (the ONE place that knows how an angle sits in its word) ----------
    def counts_from_word(self, word: int) -> int:
        """Angle counts (0 .. counts_per_rev-1) in a channel word, per the ANGLE field."""
        return (word >> self._shift) & self._mask

    def angle_from_counts(self, counts: int) -> float:
        """Angle counts to radians, 0 <= angle < 2*pi (natural binary; ``lsb_rad`` from the
        register table's constants)."""
        return counts * self.lsb_rad

    def angles_from_counts(self, counts) -> list[float]:
        """:meth:`angle_from_counts` of several channels, as a list (for the four values of
        a board a list comprehension beats numpy's per-call cost in the service's frame)."""
        lsb = self.lsb_rad
        return [c * lsb for c in counts]

    # -- readings -------------------------------------------------------------------
    def read_counts(self) -> tuple[int, int, int, int]:
        """The four channels' angles in counts (0..16383 for 14 bits): ONE block read of
        CH0..CH3 (consecutive words at 0x00-0x06, R1)."""
        c = self.counts_from_word
        try:
            w0, w1, w2, w3 = self.bus.read_block16(self._ch_addr[0], N_CHANNELS)
        except BusError as err:
            raise self._bus_error(err) from err
        return (c(w0), c(w1), c(w2), c(w3))

    def read_counts_status(self) -> tuple[tuple[int, int, int, int], RtdStatus]:
        """The four angles in counts and the decoded STATUS from ONE block read of
        CH0..CH3 and STATUS (five consecutive words at 0x00-0x08, R1): the board's whole
        reading in one bus transaction."""
        if not self._one_block:
            return self.read_counts(), self.status()
        c = self.counts_from_word
        try:
            w0, w1, w2, w3, status = self.bus.read_block16(self._ch_addr[0], N_CHANNELS + 1)
        except BusError as err:
            raise self._bus_error(err) from err
        return (c(w0), c(w1), c(w2), c(w3)), self._decode_status(status)

    def read_channel_counts(self, channel: int) -> int:
        """One channel's angle in counts."""
        ch = self._check_channel(channel)
        try:
            word = self.bus.read16(self._ch_addr[ch])
        except BusError as err:
            raise self._bus_error(err) from err
        return self.counts_from_word(word)

    def read_angles_rad(self, out: np.ndarray | None = None) -> np.ndarray:
        """The four angles in radians, 0 <= angle < 2*pi (natural binary).

        :param out: optional preallocated float array of length 4 to fill
        """
        angles = self.angles_from_counts(self.read_counts())
        if out is None:
            out = np.empty(N_CHANNELS)
        out[:] = angles
        return out

    def read_angle_rad(self, channel: int) -> float:
        """One channel's angle in radians, 0 <= angle < 2*pi."""
        return self.angle_from_counts(self.read_channel_counts(channel))

    def status(self) -> RtdStatus:
        """Read and decode STATUS."""
        try:
            word = self.bus.read16(self._status_addr)
        except BusError as err:
            raise self._bus_error(err) from err
        return self._decode_status(word)

    @staticmethod
    def _decode_status(word: int) -> RtdStatus:
        return RtdStatus(faults=tuple(bool(word >> n & 1) for n in range(N_CHANNELS)),
                         reference_present=bool(word >> 4 & 1), raw=word)

    # -- CONTROL ------------------------------------------------------------------------
    def read_control(self) -> int:
        """The CONTROL word (hold bits b3..b0, Fail LED off b14)."""
        try:
            return self.bus.read16(self._control_addr)
        except BusError as err:
            raise self._bus_error(err) from err

    def _modify_control(self, clear: int, set_: int) -> None:
        word = (self.read_control() & ~clear) | set_
        try:
            self.bus.write16(self._control_addr, word & 0xFFFF)
        except BusError as err:
            raise self._bus_error(err) from err

    def _hold_mask(self, channels: tuple[int, ...]) -> int:
        chans = channels or tuple(range(N_CHANNELS))
        mask = 0
        for ch in chans:
            mask |= 1 << self._check_channel(ch)
        return mask

    def hold(self, *channels: int) -> None:
        """Freeze the reading of the given channels (all when none given)."""
        self._modify_control(0, self._hold_mask(channels))

    def release(self, *channels: int) -> None:
        """Let the given channels (all when none given) track again."""
        self._modify_control(self._hold_mask(channels), 0)

    def set_fail_led(self, on: bool) -> None:
        """Switch the front-panel Fail LED (CONTROL b14 = 1 turns it off)."""
        led_off = 1 << CONTROL.field("led_off").lsb
        self._modify_control(led_off, 0 if on else led_off)
