"""Register-level fake of one Motorola MC6821 PIA (a chip, not a board).

Semantics follow ``mamedev/mame: src/devices/machine/6821pia.cpp`` as summarised in
the hardware-registers reference notes section 5 and R5:

- RS0/RS2 reach DDRx when CRx b2 = 0, the peripheral data register when b2 = 1;
- CRx b7 (IRQx1) is set by the active C1 edge (CRx b1: 1 rising, 0 falling), CRx b6
  (IRQx2) by the active C2 edge while C2 is an input (CRx b4); reading PRx clears both;
  writes to b7..b6 are ignored; IRQx2 reads 0 while C2 is an output;
- C2 output: set/reset mode (b5 = b4 = 1) drives C2 = b3; strobe mode (b5 = 1, b4 = 0):
  CA2 goes low on a read of PRA, CB2 on a write of PRB, and returns high after one E
  cycle (b3 = 1) or on the next active C1 edge (b3 = 0). MAME detail kept: CB2 in that
  "restore on CB1" mode returns high only when the port-B read clears IRQB1;
- port A reads the pins: input pins float high unless driven; port B reads the output
  latch for output bits and the pins for input bits (undriven: 1, assumed pull-ups).

Bus side: :meth:`read` / :meth:`write` by register select RS (0..3). Physical side:
``drive_port_a/b``, ``drive_ca1/cb1/ca2/cb2``, ``port_a_output/port_b_output``,
``ca2_level/cb2_level``, listener ``on_strobe(side)`` and ``on_c2(side, level)``.
"""

from __future__ import annotations

from collections.abc import Callable

from drivers.registers import BoardDescription
from drivers.pio.registers import (
    CR_C1_IRQ_EN, CR_C1_RISING, CR_C2_B3, CR_C2_B4, CR_C2_OUTPUT, CR_DATA, CR_IRQ1, CR_IRQ2,
    CR_WRITABLE,
)


def even_byte_reason(description: BoardDescription, offset: int) -> str:
    """NoAnswer reason for an even-byte access to an odd-byte board, naming the neighbour."""
    near = description.register_at(offset + 1)
    what = f"fill byte before {near.name} (+0x{offset + 1:02X})" if near else "fill byte"
    return f"even byte not decoded ({what}); the 8-bit registers sit on odd bytes"


class _Side:
    """State of one side (A or B) of the PIA."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.cr = 0x00  # b5..b0 as written
        self.irq1 = False
        self.irq2 = False
        self.ddr = 0x00
        self.latch = 0x00
        self.ext_value = 0xFF  # externally driven pin values
        self.ext_mask = 0x00  # which pins are externally driven
        self.c1 = True  # C1 input level (pulled high)
        self.c2_in = True  # C2 level driven from outside (when C2 is an input)
        self.c2_out = True  # C2 level driven by the PIA (when C2 is an output)
        self.cb2_wait_read = False  # MAME CB2 detail

    @property
    def c2_is_output(self) -> bool:
        return bool(self.cr & CR_C2_OUTPUT)

    @property
    def set_reset(self) -> bool:
        return self.c2_is_output and bool(self.cr & CR_C2_B4)

    @property
    def strobe_mode(self) -> bool:
        return self.c2_is_output and not self.cr & CR_C2_B4

    def pins_in(self) -> int:
        """Input pin levels: driven where driven, else 1 (pull-ups)."""
        return (self.ext_value & self.ext_mask) | (0xFF & ~self.ext_mask)


class FakePia6821:
    """One MC6821. ``name`` is used in messages only."""

    def __init__(self, name: str = "pia") -> None:
        self.name = name
        self._s = {"a": _Side("a"), "b": _Side("b")}
        #: called with (side) when a C2 output returns high after being low (end of a strobe)
        self.on_strobe: Callable[[str], None] | None = None
        #: called with (side, level) on every C2 output level change
        self.on_c2: Callable[[str, bool], None] | None = None
        #: called with (side, value) after a write to a peripheral data register
        self.on_port_write: Callable[[str, int], None] | None = None

    def reset(self) -> None:
        """Hardware reset: registers 0 (DDRs selected, all inputs, no IRQs); pins keep their drive."""
        for s in self._s.values():
            s.cr = 0
            s.irq1 = s.irq2 = False
            s.ddr = 0
            s.latch = 0
            s.cb2_wait_read = False
            s.c2_out = True

    # -- helpers ------------------------------------------------------------------------
    def _side(self, side: str) -> _Side:
        try:
            return self._s[side.lower()]
        except (KeyError, AttributeError):
            raise ValueError(f"{self.name}: PIA side must be 'a' or 'b', not {side!r}") from None

    def _set_c2_out(self, s: _Side, level: bool) -> None:
        if level == s.c2_out:
            return
        s.c2_out = level
        if self.on_c2:
            self.on_c2(s.name, level)
        if level and self.on_strobe:
            self.on_strobe(s.name)

    def _control_read(self, s: _Side) -> int:
        v = s.cr
        if s.irq1:
            v |= CR_IRQ1
        if s.irq2 and not s.c2_is_output:
            v |= CR_IRQ2
        return v

    @staticmethod
    def _port_read(s: _Side) -> int:
        # A: output pins read back the pin (= latch, no overload modelled); B: the latch.
        return ((s.latch & s.ddr) | (s.pins_in() & ~s.ddr)) & 0xFF

    # -- bus side ---------------------------------------------------------------------
    def read(self, rs: int) -> int:
        """Read the register selected by RS1:RS0 = ``rs`` (0..3)."""
        s = self._s["a" if rs < 2 else "b"]
        if rs in (1, 3):
            return self._control_read(s)
        if not s.cr & CR_DATA:
            return s.ddr
        value = self._port_read(s)
        had_irq1 = s.irq1
        s.irq1 = s.irq2 = False
        if s.name == "a" and s.strobe_mode:
            # CA2 read strobe: low now; with b3 = 1 high again after one E cycle
            self._set_c2_out(s, False)
            if s.cr & CR_C2_B3:
                self._set_c2_out(s, True)
        if s.name == "b" and s.cb2_wait_read and had_irq1:
            s.cb2_wait_read = False
            self._set_c2_out(s, True)
        return value

    def write(self, rs: int, value: int) -> None:
        """Write the register selected by RS1:RS0 = ``rs`` (0..3)."""
        value &= 0xFF
        s = self._s["a" if rs < 2 else "b"]
        if rs in (1, 3):
            self._write_cr(s, value)
            return
        if not s.cr & CR_DATA:
            s.ddr = value
            return
        s.latch = value
        if self.on_port_write:
            self.on_port_write(s.name, value)
        if s.name == "b" and s.strobe_mode:
            # CB2 write strobe
            self._set_c2_out(s, False)
            if s.cr & CR_C2_B3:
                self._set_c2_out(s, True)
            else:
                s.cb2_wait_read = True

    def _write_cr(self, s: _Side, value: int) -> None:
        s.cr = value & CR_WRITABLE
        if s.c2_is_output:
            s.irq2 = False
            if s.set_reset:
                self._set_c2_out(s, bool(s.cr & CR_C2_B3))
            else:
                # entering/staying in strobe mode: the line idles high
                if not s.cb2_wait_read:
                    self._set_c2_out(s, True)

    # -- physical side ------------------------------------------------------------------
    def drive_port_a(self, value: int | None, mask: int = 0xFF) -> None:
        """Drive port A input pins ``mask`` to ``value``; ``None`` releases them (read high)."""
        self._drive(self._s["a"], value, mask)

    def drive_port_b(self, value: int | None, mask: int = 0xFF) -> None:
        """Drive port B input pins ``mask`` to ``value``; ``None`` releases them."""
        self._drive(self._s["b"], value, mask)

    @staticmethod
    def _drive(s: _Side, value: int | None, mask: int) -> None:
        if value is None:
            s.ext_mask &= ~mask & 0xFF
            return
        s.ext_mask |= mask & 0xFF
        s.ext_value = (s.ext_value & ~mask) | (value & mask)

    def _drive_c1(self, s: _Side, level: bool) -> None:
        level = bool(level)
        old, s.c1 = s.c1, level
        if old == level:
            return
        rising = level and not old
        if rising == bool(s.cr & CR_C1_RISING):
            s.irq1 = True
            # strobe mode restored by the active C1 edge: side A at once, side B (MAME) on PRB read
            if s.strobe_mode and not s.cr & CR_C2_B3 and s.name == "a":
                self._set_c2_out(s, True)

    def _drive_c2(self, s: _Side, level: bool) -> None:
        level = bool(level)
        old, s.c2_in = s.c2_in, level
        if old == level or s.c2_is_output:
            return
        rising = level and not old
        if rising == bool(s.cr & CR_C2_B4):
            s.irq2 = True

    def drive_ca1(self, level: bool) -> None:
        """Set the CA1 input level; the active edge sets IRQA1 (CRA b7)."""
        self._drive_c1(self._s["a"], level)

    def drive_cb1(self, level: bool) -> None:
        """Set the CB1 input level; the active edge sets IRQB1 (CRB b7)."""
        self._drive_c1(self._s["b"], level)

    def drive_ca2(self, level: bool) -> None:
        """Set the CA2 level from outside (only has an effect while CA2 is an input)."""
        self._drive_c2(self._s["a"], level)

    def drive_cb2(self, level: bool) -> None:
        """Set the CB2 level from outside (only has an effect while CB2 is an input)."""
        self._drive_c2(self._s["b"], level)

    def port_a_output(self) -> int:
        """Port A pins driven by the PIA: output latch AND DDRA (input bits read 0 here)."""
        s = self._s["a"]
        return s.latch & s.ddr

    def port_b_output(self) -> int:
        """Port B pins driven by the PIA: output latch AND DDRB (input bits read 0 here)."""
        s = self._s["b"]
        return s.latch & s.ddr

    def ddr(self, side: str) -> int:
        """The data direction register of ``side`` (1 = output pin)."""
        return self._side(side).ddr

    def control(self, side: str) -> int:
        """The control register as the bus would read it (no side effects)."""
        return self._control_read(self._side(side))

    def _c2_level(self, s: _Side) -> bool:
        return s.c2_out if s.c2_is_output else s.c2_in

    @property
    def ca2_level(self) -> bool:
        """CA2 line level (PIA output when CA2 is an output, else the external level)."""
        return self._c2_level(self._s["a"])

    @property
    def cb2_level(self) -> bool:
        """CB2 line level."""
        return self._c2_level(self._s["b"])

    @property
    def irq_a(self) -> bool:
        """IRQA output: (IRQA1 and CRA b0) or (IRQA2 and CRA b3 and CA2 input)."""
        return self._irq(self._s["a"])

    @property
    def irq_b(self) -> bool:
        """IRQB output."""
        return self._irq(self._s["b"])

    @staticmethod
    def _irq(s: _Side) -> bool:
        return (s.irq1 and bool(s.cr & CR_C1_IRQ_EN)) or (
            s.irq2 and not s.c2_is_output and bool(s.cr & CR_C2_B3))
