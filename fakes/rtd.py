"""Register-level fake of the VMIC VMIVME-4940 resolver-to-digital board (model R1).

Physical side: :meth:`FakeVmivme4940.set_angle_rad`, :meth:`set_angles_rad`,
:meth:`set_counts`, :meth:`set_reference`. Faults: ``loss_of_signal`` (per channel),
``stuck_bit`` and the common ``no_answer``.
"""

from __future__ import annotations

import math

from drivers.rtd.registers import ANGLE, CONTROL, N_CHANNELS, STATUS, VMIVME4940
from fakes.board import FakeBoard, NoAnswer
from fakes.testing import StuckBits

_COUNTS = 1 << ANGLE.bits
_TWO_PI = 2.0 * math.pi
_HOLD_MASK = (1 << N_CHANNELS) - 1
_CONTROL_BITS = _HOLD_MASK | CONTROL.field("led_off").mask
_STATUS = STATUS.offset
_CONTROL = CONTROL.offset
_CH_END = 2 * N_CHANNELS


class FakeVmivme4940(FakeBoard):
    """Fake VMIVME-4940: four tracking converters returning the instantaneous angle."""

    description = VMIVME4940
    FAULTS = ("loss_of_signal", "stuck_bit")

    def __init__(self, name: str | None = None, clock=None) -> None:
        super().__init__(name, clock)
        self._counts = [0] * N_CHANNELS  # what each converter tracks
        self._held = [0] * N_CHANNELS  # reading frozen by a hold bit
        self._los_frozen: dict[int, int] = {}  # channel -> its reading while loss of signal
        self._ref_frozen: list[int] | None = None  # all readings while the reference is lost
        self._stuck = StuckBits(VMIVME4940)
        self.reset()

    def reset(self) -> None:
        """Board reset: CONTROL = 0 (no holds, Fail LED on). Angles and faults stay."""
        self.control = 0

    # -- physical side ------------------------------------------------------------------
    def set_angle_rad(self, channel: int, angle_rad: float) -> None:
        """Set a resolver's shaft angle (any real value; wrapped into 0..2*pi, truncated)."""
        self._check_channel(channel)
        if not math.isfinite(angle_rad):
            raise ValueError(f"{self.name}: channel {channel} angle {angle_rad!r} is not finite")
        counts = math.floor((angle_rad % _TWO_PI) * (_COUNTS / _TWO_PI))
        self._counts[channel] = counts & (_COUNTS - 1)

    def set_angles_rad(self, angles_rad) -> None:
        """Set all four shaft angles."""
        for ch in range(N_CHANNELS):
            self.set_angle_rad(ch, float(angles_rad[ch]))

    def set_counts(self, channel: int, counts: int) -> None:
        """Set a converter's output directly (wrapped modulo counts_per_rev)."""
        self._check_channel(channel)
        self._counts[channel] = int(counts) % _COUNTS

    def counts(self, channel: int) -> int:
        """What a converter currently tracks (ignoring holds and faults)."""
        return self._counts[channel]

    def set_reference(self, present: bool) -> None:
        """Connect or lose the 400 Hz reference (lost: every channel faults and freezes)."""
        if present:
            self._ref_frozen = None
        elif self._ref_frozen is None:
            self._ref_frozen = [self._reading(ch) for ch in range(N_CHANNELS)]

    @property
    def reference_present(self) -> bool:
        return self._ref_frozen is None

    @property
    def fail_led_on(self) -> bool:
        return not self.control & CONTROL.field("led_off").mask

    def _check_channel(self, channel: int) -> None:
        if not 0 <= channel < N_CHANNELS:
            raise ValueError(f"{self.name}: channel {channel} out of range 0..{N_CHANNELS - 1}")

    # -- faults -----------------------------------------------------------------------------
    def inject(self, fault: str, **params) -> None:
        """``inject("loss_of_signal", channel=n, mode="freeze"|"zero")`` (repeat per channel);
        ``inject("stuck_bit", register="CH0"|offset, bit=n, value=0|1)``; ``inject("no_answer")``."""
        if fault == "loss_of_signal":
            ch = params.get("channel")
            if ch is None:
                raise ValueError(f"{self.name}: loss_of_signal needs channel=0..{N_CHANNELS - 1}")
            self._check_channel(ch)
            mode = params.get("mode", "freeze")
            if mode not in ("freeze", "zero"):
                raise ValueError(f"{self.name}: loss_of_signal mode must be 'freeze' or 'zero'")
            self._los_frozen[ch] = self._reading(ch) if mode == "freeze" else 0
            super().inject(fault, channels=sorted(self._los_frozen))
        else:
            if fault == "stuck_bit":
                self._stuck.add(**params)
            super().inject(fault, **params)

    def clear(self, fault: str | None = None, channel: int | None = None) -> None:
        """Clear one fault (all its channels/bits), or every fault; ``clear("loss_of_signal",
        channel=n)`` restores one channel's signal (the others stay frozen)."""
        if fault == "loss_of_signal" and channel is not None:
            self._check_channel(channel)
            self._los_frozen.pop(channel, None)
            if self._los_frozen:
                self.faults[fault] = {"channels": sorted(self._los_frozen)}
                return
        super().clear(fault)
        if fault in (None, "stuck_bit"):
            self._stuck.clear()
        if fault in (None, "loss_of_signal"):
            self._los_frozen.clear()

    # -- bus side ----------------------------------------------------------------------------
    def _reading(self, ch: int) -> int:
        """The channel's output counts: frozen by a fault, held, or tracking."""
        if ch in self._los_frozen:
            return self._los_frozen[ch]
        if self._ref_frozen is not None:
            return self._ref_frozen[ch]
        if self.control >> ch & 1:
            return self._held[ch]
        return self._counts[ch]

    def _status(self) -> int:
        if self._ref_frozen is not None:
            return _HOLD_MASK  # every channel faulted, reference bit clear
        word = 1 << 4  # reference present
        for ch in self._los_frozen:
            word |= 1 << ch
        return word

    def _read16(self, offset: int) -> int:
        if offset < _CH_END:
            word = ANGLE.put(0, self._reading(offset >> 1))
        elif offset == _STATUS:
            word = self._status()
        elif offset == _CONTROL:
            word = self.control
        else:
            raise NoAnswer("offset not decoded by the VMIVME-4940 (assumed map R1)")
        return self._stuck.apply(offset, word) if self._stuck else word

    def _write16(self, offset: int, value: int) -> None:
        if offset < _CH_END or offset == _STATUS:
            return  # read-only registers: writes ignored (R1)
        if offset != _CONTROL:
            raise NoAnswer("offset not decoded by the VMIVME-4940 (assumed map R1)")
        new = value & _CONTROL_BITS
        rising = new & ~self.control & _HOLD_MASK
        for ch in range(N_CHANNELS):
            if rising >> ch & 1:
                self._held[ch] = self._reading(ch)
        self.control = new
