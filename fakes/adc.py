"""Register-level fake of the Datel DVME-611B 32-channel 12-bit A/D board (model R3).

Conversions take ``conversion_time_s`` (4 us) of model time on ``self.clock``; a
driver polling CSR through a :class:`fakes.rack.FakeRack` (1 us per access) sees BUSY
for a few reads, then EOC. The scan mode (START with b0 = 1, R3 as assumed in the
register table) converts channels 0..31 in turn: channel k is sampled at
``t0 + k * 4 us`` and lands in SCAN[k] at ``t0 + (k+1) * 4 us``; BUSY until
``t0 + 128 us``, then EOC. Samples are taken lazily but at their own time: the physical
side's setters first settle every sample whose time has come, so a later input change
never reaches an earlier channel. Physical side: :meth:`FakeDvme611.set_input_volts`,
:meth:`set_inputs_volts`. Faults: ``busy_stuck``, ``stuck_bit`` and ``no_answer``.
Optional noise: ``noise_counts`` (standard deviation in counts, default 0) drawn from
a seeded generator (``seed_noise``).
"""

from __future__ import annotations

import math

import numpy as np

from collections.abc import Callable

from drivers.adc.registers import (AUTOINC, BOARD_ID, BUSY, CSR, DATA, DVME611, EOC, IE,
                                   N_CHANNELS, SCAN, SCAN_CMD, START)
from fakes.board import FakeBoard, NoAnswer
from fakes.testing import StuckBits

_FULL = DVME611.constants["full_scale_counts"]
_CSR_STORED = 0x1F | AUTOINC.mask | IE.mask  # gain bits read back 00 (no PGA, assumed)
_SCAN_END = SCAN.offset + 2 * N_CHANNELS


class FakeDvme611(FakeBoard):
    """Fake DVME-611B with a 4 us conversion on the board's clock."""

    description = DVME611
    FAULTS = ("busy_stuck", "stuck_bit")

    def __init__(self, name: str | None = None, clock=None) -> None:
        super().__init__(name, clock)
        self.range_volts = float(DVME611.constants["range_volts"])
        self.conversion_time_s = float(DVME611.constants["conversion_time_s"])
        self.noise_counts = 0.0
        self._rng = np.random.default_rng(0)
        self._inputs = np.zeros(N_CHANNELS)
        self._stuck = StuckBits(DVME611)
        self.conversions = 0  #: number of START strobes seen (a scan is one)
        self.scans = 0  #: number of scans started (START with b0 = 1)
        self.reset()

    def reset(self) -> None:
        """Board reset: CSR 0, no conversion, DATA and scan buffer 0. Inputs stay."""
        self.csr = 0  # stored CSR bits (channel, auto-increment, interrupt enable)
        self.data = 0
        self.eoc = False
        self._busy_until: float | None = None
        self._pending = (0, 0)  # (channel, code) of the conversion in progress
        self._scan = [0] * N_CHANNELS
        self._scan_t0: float | None = None  # start of the scan in progress
        self._scan_codes: list[int] = []  # codes sampled so far in the scan in progress

    def seed_noise(self, seed: int) -> None:
        """Restart the noise generator from ``seed`` (deterministic tests)."""
        self._rng = np.random.default_rng(seed)

    # -- physical side ---------------------------------------------------------------------
    def set_input_volts(self, channel: int, volts: float) -> None:
        """Voltage at one input (clipped to the range when converted)."""
        if not 0 <= channel < N_CHANNELS:
            raise ValueError(f"{self.name}: channel {channel} out of range 0..{N_CHANNELS - 1}")
        self._update()  # samples due before this change see the old input
        self._inputs[channel] = volts

    def set_inputs_volts(self, volts) -> None:
        """Voltages at all 32 inputs."""
        v = np.asarray(volts, dtype=float)
        if v.shape != (N_CHANNELS,):
            raise ValueError(f"{self.name}: need {N_CHANNELS} input voltages, got shape {v.shape}")
        self._update()  # samples due before this change see the old inputs
        self._inputs[:] = v

    @property
    def input_volts(self) -> np.ndarray:
        return self._inputs.copy()

    def code_for_volts(self, volts: float) -> int:
        """The converter's transfer function: clip to the range, offset binary, floor."""
        r = self.range_volts
        code = math.floor((min(max(volts, -r), r) + r) * (_FULL / (2.0 * r)))
        if self.noise_counts:
            code += int(round(self._rng.normal(0.0, self.noise_counts)))
        return min(max(code, 0), _FULL - 1)

    # -- faults --------------------------------------------------------------------------
    def inject(self, fault: str, **params) -> None:
        """``inject("busy_stuck")``: BUSY stays set, EOC never comes;
        ``inject("stuck_bit", register="DATA"|"CSR"|offset, bit=n, value=0|1)``;
        ``inject("no_answer")``."""
        if fault == "stuck_bit":
            self._stuck.add(**params)
        super().inject(fault, **params)

    def clear(self, fault: str | None = None) -> None:
        super().clear(fault)
        if fault in (None, "stuck_bit"):
            self._stuck.clear()

    # -- conversion state --------------------------------------------------------------------
    @property
    def busy(self) -> bool:
        self._update()
        return self._busy_until is not None or "busy_stuck" in self.faults

    def _update(self) -> None:
        """Take the samples and finish the conversions whose time has come."""
        if self._busy_until is None or "busy_stuck" in self.faults:
            return
        now = self.clock.now()
        if self._scan_t0 is not None:
            self._scan_progress(now)
            return
        if now >= self._busy_until:
            ch, code = self._pending
            self.data = code
            self._scan[ch] = code
            self.eoc = True
            self._busy_until = None

    def _scan_progress(self, now: float) -> None:
        """A scan: sample channel k at t0 + k*T, land it in SCAN[k] at t0 + (k+1)*T."""
        t0, tc, codes = self._scan_t0, self.conversion_time_s, self._scan_codes
        assert t0 is not None
        done = min(N_CHANNELS, int((now - t0) / tc + 1e-9))  # conversions finished
        sampled = min(N_CHANNELS, done + 1)  # the one in progress has its sample too
        while len(codes) < sampled:
            codes.append(self.code_for_volts(float(self._inputs[len(codes)])))
        self._scan[:done] = codes[:done]
        if done == N_CHANNELS:
            self.data = codes[-1]
            self.eoc = True
            self._busy_until = None
            self._scan_t0 = None

    def _start(self, value: int = 0) -> None:
        self._update()
        self.eoc = False
        self.conversions += 1
        if value & SCAN_CMD.mask:
            self.scans += 1
            self._scan_t0 = self.clock.now()
            self._scan_codes = []
            self._busy_until = self._scan_t0 + N_CHANNELS * self.conversion_time_s
            self._scan_progress(self._scan_t0)  # channel 0 is sampled now
            return
        self._scan_t0 = None
        ch = self.csr & 0x1F
        self._pending = (ch, self.code_for_volts(float(self._inputs[ch])))
        self._busy_until = self.clock.now() + self.conversion_time_s

    # -- bus side -----------------------------------------------------------------------------
    def _read16(self, offset: int) -> int:
        if offset == CSR.offset:
            busy = self.busy
            word = self.csr | (BUSY.mask if busy else 0) | (EOC.mask if self.eoc and not busy else 0)
        elif offset == DATA.offset:
            busy = self.busy  # finishes a conversion whose time is up
            word = self.data
            if not busy:
                self.eoc = False
                if self.csr & AUTOINC.mask:
                    self.csr = (self.csr & ~0x1F) | ((self.csr + 1) & 0x1F)
        elif offset == START.offset:
            word = 0  # write-only strobe (assumed: reads 0)
        elif offset == BOARD_ID.offset:
            word = BOARD_ID.reset
        elif SCAN.offset <= offset < _SCAN_END:
            self._update()  # a scan in progress lands its finished channels
            word = self._scan[(offset - SCAN.offset) >> 1]
        else:
            raise NoAnswer("offset not decoded by the DVME-611 (assumed map R3)")
        return self._stuck.apply(offset, word) if self._stuck else word

    def _write16(self, offset: int, value: int) -> None:
        if offset == CSR.offset:
            self._update()
            self.csr = value & _CSR_STORED
        elif offset == START.offset:
            self._start(value)
        elif offset in (DATA.offset, BOARD_ID.offset) or SCAN.offset <= offset < _SCAN_END:
            return  # read-only: writes ignored (assumed)
        else:
            raise NoAnswer("offset not decoded by the DVME-611 (assumed map R3)")

    def read_block16(self, offset: int, n: int, tick: Callable[[], None] | None = None) -> list[int]:
        """A block wholly inside SCAN while no conversion runs is a slice of the buffer
        (SCAN reads have no side effects and nothing changes it between the words); any
        other block is word by word (FakeBoard)."""
        end = offset + 2 * n
        if (SCAN.offset <= offset and end <= _SCAN_END and not self.faults and not self._stuck
                and self._busy_until is None):
            if tick is not None:
                for _ in range(n):
                    tick()
            i = (offset - SCAN.offset) >> 1
            words = self._scan[i:i + n]
            if self.log_traffic:
                self.traffic.extend(("r", 16, offset + 2 * k, w) for k, w in enumerate(words))
            return list(words)
        return super().read_block16(offset, n, tick)
