"""Driver for the VMIC VMIVME-4100 16-channel 12-bit analog output board.

Register model: ``drivers.dac.registers.VMIVME4100`` (R2). The board cannot be read
back, so the driver keeps a shadow of every code it wrote. Outputs stay disconnected
from the field (P3) until :meth:`Vmivme4100.enable_outputs`; construction touches
nothing on the bus.
"""

from __future__ import annotations

import math
import operator

import numpy as np

from drivers.dac.registers import (CTRL_MASK, DATA_MASK, DISABLE_WORD, ENABLE_WORD, N_CHANNELS,
                                   P3_ENABLE, VMIVME4100)
from drivers.bus import RegisterBus
from drivers.registers import check_channel
from pfma.errors import BusError

_MAX_CODE = DATA_MASK
_RANGE_VOLTS = VMIVME4100.constants["range_volts"]  #: default bipolar range (assumed +-10 V, R2)


class Vmivme4100:
    """One VMIVME-4100 board at A16 ``base``.

    :param bus: any object with ``read16``/``write16`` on absolute A16 addresses
    :param base: board base address (0xD000 in the PFMA rack)
    :param name: board name for messages (default ``vmivme4100@0xBASE``)
    :param range_volts: the board's bipolar range jumper, +-range_volts offset binary
        (default: the register table's ``range_volts``)
    """

    description = VMIVME4100
    n_channels = N_CHANNELS

    def __init__(self, bus: RegisterBus, base: int, name: str | None = None, *, range_volts: float = _RANGE_VOLTS) -> None:
        if not range_volts > 0:
            raise ValueError(f"range_volts must be positive, not {range_volts!r}")
        self.bus = bus
        self.base = base
        self.name = name or f"{VMIVME4100.kind}@0x{base:04X}"
        self.range_volts = float(range_volts)
        full = VMIVME4100.constants["full_scale_counts"]
        self.lsb_volts = 2.0 * self.range_volts / full
        self._counts_per_volt = full / (2.0 * self.range_volts)
        self.zero_code = full // 2  # 0 V in offset binary
        self._addr = tuple(base + VMIVME4100.reg("DAC").addr(n) for n in range(N_CHANNELS))
        self._ctrl_addr = base + VMIVME4100.reg("CTRL").offset
        # Assumed board reset state (R2): every DAC 0x800, P3 disconnected.
        self._shadow = np.full(N_CHANNELS, self.zero_code, dtype=np.int64)
        self._enabled = False

    # -- errors / validation --------------------------------------------------------
    def _bus_error(self, err: BusError, channel: int | None) -> BusError:
        reg = "CTRL" if channel is None else f"DAC[{channel}]"
        return err.with_context(self.name, reg)

    def _check_channel(self, channel: int) -> int:
        return check_channel(self.name, self.base, channel, N_CHANNELS)

    # -- scaling -------------------------------------------------------------------------
    def code_from_volts(self, volts: float, *, clamp: bool = False) -> int:
        """The nearest DAC code for ``volts`` (offset binary; +range maps to 4095).

        :raises ValueError: if volts is NaN, or outside +-range_volts and ``clamp`` is False
        """
        r = self.range_volts
        if not -r <= volts <= r:
            if clamp and not math.isnan(volts):
                volts = r if volts > r else -r
            else:
                raise ValueError(f"{self.name}: {volts!r} V is outside the +-{r:g} V range")
        code = int(round((volts + r) * self._counts_per_volt))
        return _MAX_CODE if code > _MAX_CODE else code

    def volts_from_code(self, code: int) -> float:
        """The output voltage of a DAC code (V = -range + code * LSB)."""
        return code * self.lsb_volts - self.range_volts

    # -- writes ------------------------------------------------------------------------------
    def write_counts(self, channel: int, code: int) -> None:
        """Write a raw 12-bit code (0..4095) to one channel.

        :raises ValueError: for a bad channel or code; BusError naming board and DAC[n]
        """
        ch = self._check_channel(channel)
        try:
            c = operator.index(code)
        except TypeError:
            c = -1
        if not 0 <= c <= _MAX_CODE:
            raise ValueError(f"{self.name} (A16 0x{self._addr[ch]:04X}) channel {ch}: code {code!r} "
                             f"out of range 0..{_MAX_CODE}")
        try:
            self.bus.write16(self._addr[ch], c)  # D15 = 0: a DAC write
        except BusError as err:
            raise self._bus_error(err, ch) from err
        self._shadow[ch] = c

    def write_volts(self, channel: int, volts: float, *, clamp: bool = False) -> None:
        """Write ``volts`` to one channel (nearest code).

        :param clamp: saturate out-of-range values at +-range_volts instead of refusing them
        :raises ValueError: for a bad channel, NaN, or an out-of-range value without ``clamp``
        """
        ch = self._check_channel(channel)
        try:
            code = self.code_from_volts(volts, clamp=clamp)
        except ValueError as err:
            raise ValueError(f"{err} (channel {ch}, A16 0x{self._addr[ch]:04X})") from None
        try:
            self.bus.write16(self._addr[ch], code)
        except BusError as err:
            raise self._bus_error(err, ch) from err
        self._shadow[ch] = code

    def write_volts_all(self, volts, *, clamp: bool = False) -> None:
        """Write 16 voltages, channel 0 first (all validated before anything is written)."""
        if len(volts) != N_CHANNELS:
            raise ValueError(f"{self.name}: need {N_CHANNELS} voltages, got {len(volts)}")
        # code_from_volts inlined for the in-range values (this runs every frame); anything
        # else (out of range, NaN, not a number) goes through it for its clamp or its error
        r, cpv = self.range_volts, self._counts_per_volt
        codes = []
        for ch in range(N_CHANNELS):
            try:
                x = volts[ch]
                if type(x) is not float:
                    x = float(x)
                if -r <= x <= r:
                    c = int(round((x + r) * cpv))
                    codes.append(_MAX_CODE if c > _MAX_CODE else c)
                else:
                    codes.append(self.code_from_volts(x, clamp=clamp))
            except ValueError as err:
                raise ValueError(f"{err} (channel {ch}, A16 0x{self._addr[ch]:04X})") from None
        self._write_codes(codes)

    def _write_codes(self, codes: list[int]) -> None:
        """Write every channel as ONE block write of DAC[0..15] (consecutive words at
        offsets 0x00-0x1E, D15 = 0: R2).

        Fail safe on a bus error: the words before the failing one went out (the block
        contract), so the channels after it are written as a further block, and so on; every
        channel that answers gets its code, then the first error is raised. Only when no
        word of this write has reached the board yet does a failure end it: the bus or the
        board is gone, and sixteen more attempts (over a gateway that stopped answering,
        sixteen more timeouts) would change nothing.
        """
        first: BusError | None = None
        written = [False] * N_CHANNELS
        start = 0
        while start < N_CHANNELS:
            try:
                self.bus.write_block16(self._addr[start], codes[start:])
            except BusError as err:
                failed = (err.addr - self._addr[0]) // 2
                if not start <= failed < N_CHANNELS:
                    failed = start
                written[start:failed] = [True] * (failed - start)
                first = first or self._bus_error(err, failed)
                if not any(written):
                    break
                start = failed + 1
            else:
                written[start:] = [True] * (N_CHANNELS - start)
                break
        if first is None:
            self._shadow[:] = codes
            return
        for ch in range(N_CHANNELS):
            if written[ch]:
                self._shadow[ch] = codes[ch]
        raise first

    def zero_all(self) -> None:
        """Drive every channel to 0 V."""
        self._write_codes([self.zero_code] * N_CHANNELS)

    # -- control ------------------------------------------------------------------------------
    def _write_control(self, word: int) -> None:
        try:
            self.bus.write16(self._ctrl_addr, word)
        except BusError as err:
            raise self._bus_error(err, None) from err

    def enable_outputs(self) -> None:
        """Connect the outputs to the field: rewrite every channel from the shadow (0 V unless
        written since construction), then write 0xC100 once, as EPICS drvVmi4100 does."""
        self._write_codes(self._shadow.tolist())
        self._write_control(ENABLE_WORD)
        self._enabled = True

    def disable_outputs(self) -> None:
        """Drive every channel to 0 V, then disconnect P3 (control 0xC000: LED off).

        The control word is written even if a channel write failed; the first error is
        raised afterwards.
        """
        self._enabled = False
        try:
            self.zero_all()
        finally:
            self._write_control(DISABLE_WORD)

    @property
    def outputs_enabled(self) -> bool:
        """True after enable_outputs() and until disable_outputs() (the board cannot say)."""
        return self._enabled

    def read_control(self) -> int:
        """The control bits as the board returns them on a read (bits 14..8)."""
        try:
            return self.bus.read16(self._ctrl_addr) & CTRL_MASK
        except BusError as err:
            raise self._bus_error(err, None) from err

    def outputs_connected(self) -> bool:
        """Ask the board whether P3 is connected (reads the control bits)."""
        return bool(self.read_control() & P3_ENABLE)

    # -- shadow ------------------------------------------------------------------------------
    @property
    def shadow_counts(self) -> np.ndarray:
        """Codes last written per channel (board reset value 0x800 until written)."""
        return self._shadow.copy()

    @property
    def shadow_volts(self) -> np.ndarray:
        """Voltages last written per channel."""
        return self._shadow * self.lsb_volts - self.range_volts
