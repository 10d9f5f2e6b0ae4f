"""Register-level fake of the VMIC VMIVME-4100 16-channel analog output board (model R2).

Bus side: a word with D15 = 1 loads the control register (D14..D8) at any offset; a
word with D15 = 0 loads DAC[offset/2] from D11..D0; a read of any offset returns the
control bits 14..8. Physical side: :meth:`FakeVmivme4100.output_volts`,
:meth:`output_volts_all`, :attr:`outputs_connected`. Faults: ``stuck_bit`` (a DAC
latch bit, e.g. ``register="DAC[3]", bit=11, value=1``) and ``no_answer``.
"""

from __future__ import annotations

import numpy as np

from drivers.dac.registers import (CTRL_MASK, DATA_MASK, LED_OFF, N_CHANNELS, P3_ENABLE,
                                   SELECT_CTRL, VMIVME4100)
from fakes.board import FakeBoard
from fakes.testing import StuckBits

_RESET_CODE = VMIVME4100.reg("DAC").reset  # 0x800 = 0 V at +-10 V (R2, assumed)


class FakeVmivme4100(FakeBoard):
    """Fake VMIVME-4100. ``range_volts`` is the board's bipolar range jumper (+-10 V)."""

    description = VMIVME4100
    FAULTS = ("stuck_bit",)

    def __init__(self, name: str | None = None, clock=None) -> None:
        super().__init__(name, clock)
        self.range_volts = float(VMIVME4100.constants["range_volts"])
        self._latch = np.full(N_CHANNELS, _RESET_CODE, dtype=np.int64)
        self._stuck = StuckBits(VMIVME4100)
        self.control = 0
        self.reset()

    def reset(self) -> None:
        """Power-up/reset state: every DAC 0x800, control 0 (Fail LED on, P3 disconnected)."""
        self._latch[:] = _RESET_CODE
        self.control = 0

    # -- faults --------------------------------------------------------------------------
    def inject(self, fault: str, **params) -> None:
        """``inject("stuck_bit", register="DAC[n]"|offset, bit=0..11, value=0|1)`` forces a bit
        of that channel's DAC latch; ``inject("no_answer")``."""
        if fault == "stuck_bit":
            self._stuck.add(**params)
        super().inject(fault, **params)

    def clear(self, fault: str | None = None) -> None:
        super().clear(fault)
        if fault in (None, "stuck_bit"):
            self._stuck.clear()

    @staticmethod
    def access_name(op: str, offset: int, value: int) -> str:
        """Register an access reached: reads and D15 = 1 writes reach CTRL, others DAC[n]."""
        if op == "r" or value & SELECT_CTRL:
            return "CTRL"
        return f"DAC[{offset >> 1}]"

    # -- bus side ----------------------------------------------------------------------------
    def _read16(self, offset: int) -> int:
        return self.control  # status = control bits 14..8 (R2); DACs are never readable

    def _write16(self, offset: int, value: int) -> None:
        if value & SELECT_CTRL:
            self.control = value & CTRL_MASK
        else:
            self._latch[offset >> 1] = value & DATA_MASK

    # -- physical side ---------------------------------------------------------------------
    @property
    def codes(self) -> np.ndarray:
        """What the 16 DAC registers hold (with any stuck bits), a copy."""
        out = self._latch.copy()
        if self._stuck:
            for ch in range(N_CHANNELS):
                out[ch] = self._stuck.apply(2 * ch, int(out[ch])) & DATA_MASK
        return out

    @property
    def outputs_connected(self) -> bool:
        """True while control b8 connects the outputs to P3."""
        return bool(self.control & P3_ENABLE)

    @property
    def fail_led_on(self) -> bool:
        return not self.control & LED_OFF

    def output_volts_all(self) -> np.ndarray:
        """Field voltages of the 16 outputs (all 0.0 while P3 is disconnected)."""
        if not self.control & P3_ENABLE:
            return np.zeros(N_CHANNELS)
        r = self.range_volts
        return self.codes * (2.0 * r / 4096) - r

    def output_volts(self, channel: int) -> float:
        """Field voltage of one output (0.0 while P3 is disconnected)."""
        if not 0 <= channel < N_CHANNELS:
            raise ValueError(f"{self.name}: channel {channel} out of range 0..{N_CHANNELS - 1}")
        return float(self.output_volts_all()[channel])
