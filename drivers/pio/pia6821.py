"""Register-level driver of one Motorola MC6821 PIA on a RegisterBus.

The PIA has four registers selected by RS1:RS0; with CRx b2 = 0 the RS0/RS2 slots are
the data direction registers, with b2 = 1 the peripheral data registers
(``mamedev/mame: src/devices/machine/6821pia.cpp``, copied in ``drivers.pio.registers``).
The driver keeps a shadow of the writable control bits (b5..b0) it wrote, so it can
change C2 without reading the control register back (the VME/10 ``bios.c`` printer
driver writes constant control values the same way). Until the driver has written a
control register itself it does not know it: the first port access or C2 change then
reads CRx once (a control read has no side effects) and keeps every bit the board
already holds, so a checkout tool (``pfma read``) on a rack another program set up
does not reset C2 or the C1 edge.
"""

from __future__ import annotations

from drivers.bus import RegisterBus
from drivers.pio.registers import (
    C2_HIGH, C2_IN_FALLING, C2_LOW, C2_MASK, C2_STROBE_C1, C2_STROBE_E, CR_C1_IRQ_EN,
    CR_C1_RISING, CR_DATA, CR_IRQ1, CR_IRQ2, CR_WRITABLE,
)
from pfma.errors import BusError

SIDES = ("a", "b")

#: C2 mode names accepted by :meth:`Pia6821.configure` -> CR b5..b3
C2_MODES = {
    "in_falling": C2_IN_FALLING,
    "in_rising": 0x10,
    "strobe_c1": C2_STROBE_C1,  # A: low on PRA read; B: low on PRB write; high on next C1 edge
    "strobe_e": C2_STROBE_E,  # same, high again after one E cycle
    "low": C2_LOW,  # set/reset mode, held low
    "high": C2_HIGH,  # set/reset mode, held high
}


class Pia6821:
    """One MC6821 PIA.

    :param bus: any RegisterBus
    :param pra: absolute A16 address of PRA/DDRA (RS = 0)
    :param cra: absolute address of CRA (RS = 1)
    :param prb: absolute address of PRB/DDRB (RS = 2)
    :param crb: absolute address of CRB (RS = 3)
    :param name: used in error messages, e.g. ``"pio_video.PIA1"``
    """

    def __init__(self, bus: RegisterBus, pra: int, cra: int, prb: int, crb: int,
                 name: str = "pia") -> None:
        self.bus = bus
        self.name = name
        self._data = {"a": pra, "b": prb}
        self._ctrl = {"a": cra, "b": crb}
        self._cr = {"a": 0x00, "b": 0x00}  # shadow of CR b5..b0 as last written
        self._cr_known = {"a": False, "b": False}  # shadow valid (written or read back)
        self._ddr = {"a": 0x00, "b": 0x00}  # DDR as last configured (reset: all inputs)

    # -- bus helpers ------------------------------------------------------------------
    def _side(self, side: str) -> str:
        s = side.lower()
        if s not in SIDES:
            raise ValueError(f"{self.name}: PIA side must be 'a' or 'b', not {side!r}")
        return s

    def _reg_name(self, side: str, ctrl: bool) -> str:
        if ctrl:
            return f"CR{side.upper()}"
        return f"PR{side.upper()}" if self._cr[side] & CR_DATA else f"DDR{side.upper()}"

    def _read(self, addr: int, side: str, ctrl: bool) -> int:
        try:
            return self.bus.read8(addr) & 0xFF
        except BusError as err:
            if err.board:
                raise
            raise err.with_context(self.name, self._reg_name(side, ctrl)) from None

    def _write(self, addr: int, value: int, side: str, ctrl: bool) -> None:
        try:
            self.bus.write8(addr, value & 0xFF)
        except BusError as err:
            if err.board:
                raise
            raise err.with_context(self.name, self._reg_name(side, ctrl)) from None

    def _write_cr(self, side: str, value: int) -> None:
        value &= CR_WRITABLE
        self._write(self._ctrl[side], value, side, True)
        self._cr[side] = value
        self._cr_known[side] = True

    def _current_cr(self, s: str) -> int:
        """CR b5..b0: the shadow, or (first use, nothing written yet) read from the board."""
        if not self._cr_known[s]:
            self._cr[s] = self._read(self._ctrl[s], s, True) & CR_WRITABLE
            self._cr_known[s] = True
        return self._cr[s]

    # -- configuration ------------------------------------------------------------
    def configure(self, side: str, ddr: int, c2_mode: str = "in_falling", *,
                  c1_rising: bool = False, c1_irq: bool = False) -> None:
        """Set one side's data direction and C1/C2 modes, leaving the data register selected.

        Sequence (as ``bios.c``): CRx = mode with b2 = 0, DDRx = ``ddr``, CRx = mode | b2.

        :param side: ``"a"`` or ``"b"``
        :param ddr: 8-bit mask, 1 = output
        :param c2_mode: one of :data:`C2_MODES`
        :param c1_rising: C1 active edge low-to-high (default high-to-low)
        :param c1_irq: enable the C1 interrupt output (this project polls; default off)
        :raises ValueError: for a bad side, mask or mode
        """
        s = self._side(side)
        if not 0 <= ddr <= 0xFF:
            raise ValueError(f"{self.name}: DDR{s.upper()} mask 0x{ddr:X} is not 8 bits")
        try:
            c2 = C2_MODES[c2_mode]
        except KeyError:
            raise ValueError(f"{self.name}: unknown C2 mode {c2_mode!r}; known: {', '.join(C2_MODES)}") from None
        mode = c2 | (CR_C1_RISING if c1_rising else 0) | (CR_C1_IRQ_EN if c1_irq else 0)
        self._write_cr(s, mode)
        self._write(self._data[s], ddr, s, False)
        self._ddr[s] = ddr
        self._write_cr(s, mode | CR_DATA)

    def ddr(self, side: str) -> int:
        """The data direction mask last configured for ``side`` (1 = output)."""
        return self._ddr[self._side(side)]

    def _select_data(self, s: str) -> None:
        cr = self._current_cr(s)
        if not cr & CR_DATA:
            self._write_cr(s, cr | CR_DATA)

    # -- ports --------------------------------------------------------------------
    def read_port(self, side: str) -> int:
        """Read port A or B (clears that side's IRQ flags; in A read-strobe mode pulses CA2)."""
        s = self._side(side)
        self._select_data(s)
        return self._read(self._data[s], s, False)

    def write_port(self, side: str, value: int) -> None:
        """Write the output latch of port A or B (in B write-strobe mode pulses CB2).

        :raises ValueError: if ``value`` is not 8 bits
        """
        s = self._side(side)
        if not 0 <= value <= 0xFF:
            raise ValueError(f"{self.name}: port {s.upper()} value 0x{value:X} is not 8 bits")
        self._select_data(s)
        self._write(self._data[s], value, s, False)

    # -- control lines ------------------------------------------------------------------
    def read_control(self, side: str) -> int:
        """The control register as read (b7/b6 flags included; does not clear them)."""
        s = self._side(side)
        return self._read(self._ctrl[s], s, True)

    def flags(self, side: str) -> tuple[bool, bool]:
        """(IRQx1, IRQx2) flags of ``side``, without clearing them."""
        cr = self.read_control(side)
        return bool(cr & CR_IRQ1), bool(cr & CR_IRQ2)

    def clear_flags(self, side: str) -> None:
        """Clear IRQx1/IRQx2 by a dummy read of the data register (as ``bios.c`` does)."""
        self.read_port(side)

    def set_c2_mode(self, side: str, c2_mode: str) -> None:
        """Change only the C2 mode (CR b5..b3), keeping b2..b0."""
        s = self._side(side)
        try:
            c2 = C2_MODES[c2_mode]
        except KeyError:
            raise ValueError(f"{self.name}: unknown C2 mode {c2_mode!r}; known: {', '.join(C2_MODES)}") from None
        self._write_cr(s, (self._current_cr(s) & ~C2_MASK) | c2)

    def set_c2(self, side: str, level: bool) -> None:
        """Drive C2 to ``level`` in set/reset mode (CR b5 = b4 = 1, b3 = level)."""
        self.set_c2_mode(side, "high" if level else "low")

    def pulse_c2(self, side: str) -> None:
        """Manual strobe: C2 low then high in set/reset mode (``bios.c``: CRA 0x34 then 0x3C)."""
        self.set_c2(side, False)
        self.set_c2(side, True)

    def wait_flag1(self, side: str, max_polls: int) -> bool:
        """Poll CRx b7 (IRQx1, set by an active C1 edge) at most ``max_polls`` times.

        :returns: True if the flag was seen (it stays set until the port is read)
        """
        s = self._side(side)
        for _ in range(max(1, max_polls)):
            if self._read(self._ctrl[s], s, True) & CR_IRQ1:
                return True
        return False
