"""Driver of the Motorola MVME410 parallel I/O board: two MC6821 PIAs, four 8-bit ports.

Ports 0..3 = PIA1 A, PIA1 B, PIA2 A, PIA2 B (``drivers.pio.registers.PORTS``). The
PFMA rack uses two of these boards (IRSS report, section 3.4.2):

- ``pio_user`` (0x0040): 16 inputs from the user I/F box on ports 0 and 1,
  :meth:`Mvme410.read_user_inputs`;
- ``pio_video`` (0x0020): the matrix switcher route byte on port 0 with a strobe on CA2
  and an acknowledge on CA1, :meth:`Mvme410.write_matrix_route`. The bit assignment
  and handshake are ASSUMED, in one table: ``drivers.pio.registers.MATRIX_SWITCHER``.
"""

from __future__ import annotations

from collections.abc import Sequence

from drivers.bus import RegisterBus
from drivers.pio.pia6821 import Pia6821
from drivers.pio.registers import MATRIX_SWITCHER, MVME410, PORTS
from pfma.errors import BoardError


class Mvme410:
    """One MVME410 board.

    :param bus: any RegisterBus
    :param base: board base address (A16), e.g. 0x0020
    :param name: board name for messages (default ``"mvme410@0xNNNN"``)
    """

    description = MVME410

    def __init__(self, bus: RegisterBus, base: int, name: str | None = None) -> None:
        self.bus = bus
        self.base = base
        self.name = name or f"mvme410@0x{base:04X}"
        p1 = base + MVME410.reg("PIA1_PRA").offset
        p2 = base + MVME410.reg("PIA2_PRA").offset
        self.pia1 = Pia6821(bus, p1, p1 + 2, p1 + 4, p1 + 6, name=f"{self.name}.PIA1")
        self.pia2 = Pia6821(bus, p2, p2 + 2, p2 + 4, p2 + 6, name=f"{self.name}.PIA2")
        self._directions: list[int | None] = [None, None, None, None]

    def _port(self, port: int) -> tuple[Pia6821, str]:
        if port not in PORTS:
            raise ValueError(f"{self.name}: port {port} not in 0..3 (at A16 0x{self.base:04X})")
        pia, side = PORTS[port]
        return (self.pia1, self.pia2)[pia], side

    def configure(self, port_directions: Sequence[str | int]) -> None:
        """Set the direction of the four ports.

        Each entry is ``"in"`` (0x00), ``"out"`` (0xFF) or an 8-bit DDR mask. A port with
        any output bit gets C2 as a set/reset output held high (an idle strobe line) and
        C1 active on the falling edge (an acknowledge); an input port gets C2 as an input.
        No PIA interrupts are enabled (the project polls).

        :raises ValueError: for a list that is not 4 long or a bad direction
        """
        if len(port_directions) != 4:
            raise ValueError(f"{self.name}: need 4 port directions, got {len(port_directions)}")
        masks = []
        for port, d in enumerate(port_directions):
            if d == "in":
                masks.append(0x00)
            elif d == "out":
                masks.append(0xFF)
            elif isinstance(d, int) and 0 <= d <= 0xFF:
                masks.append(d)
            else:
                raise ValueError(f"{self.name}: port {port} direction {d!r} is not 'in', 'out' or a mask")
        for port, mask in enumerate(masks):
            pia, side = self._port(port)
            pia.configure(side, mask, "high" if mask else "in_falling")
            self._directions[port] = mask

    def read_port(self, port: int) -> int:
        """Read port 0..3 (input pins; output bits read back the latch/pin)."""
        pia, side = self._port(port)
        return pia.read_port(side)

    def write_port(self, port: int, value: int) -> None:
        """Write port 0..3's output latch.

        :raises BoardError: if the port was not configured with output bits
        :raises ValueError: if ``value`` is not 8 bits
        """
        pia, side = self._port(port)
        if not self._directions[port]:
            raise BoardError(f"{self.name}: port {port} is not configured as an output "
                             f"(call configure first; board at A16 0x{self.base:04X})")
        pia.write_port(side, value)

    # -- the rack's two uses ------------------------------------------------------------
    def read_user_inputs(self) -> int:
        """The user I/F box's 16 inputs: port 0 = bits 0..7, port 1 = bits 8..15.

        Ports 0 and 1 must be inputs (``configure(["in", "in", ...])``).
        """
        return self.read_port(0) | (self.read_port(1) << 8)

    def write_matrix_route(self, value: int, *, wait_ack: bool = True,
                           max_polls: int | None = None) -> None:
        """Send a route byte to the matrix switcher on port 0 with the strobe handshake.

        Data on PIA1 port A; dummy read of PRA to clear a stale acknowledge flag; CA2
        pulsed low then high in set/reset mode (CRA 0x34, 0x3C, as ``bios.c`` strobes a
        printer); then optionally poll CRA b7 (set by the switcher's CA1 falling edge).
        Bit assignment: ``drivers.pio.registers.MATRIX_SWITCHER`` (ASSUMED); see
        ``encode_matrix_route``.

        :param value: route byte 0..255
        :param wait_ack: wait for the acknowledge on CA1
        :param max_polls: bound on CRA reads (default ``MATRIX_SWITCHER["ack_polls"]``)
        :raises BoardError: if port 0 is not an output or the acknowledge never comes
        :raises ValueError: if ``value`` is not 8 bits
        """
        port = MATRIX_SWITCHER["port"]
        if not 0 <= value <= 0xFF:
            raise ValueError(f"{self.name}: matrix route 0x{value:X} is not 8 bits")
        if self._directions[port] != 0xFF:
            raise BoardError(f"{self.name}: port {port} must be configured 'out' for the matrix switcher "
                             f"(board at A16 0x{self.base:04X})")
        pia, side = self._port(port)
        pia.write_port(side, value)
        pia.clear_flags(side)
        pia.pulse_c2(side)
        if not wait_ack:
            return
        polls = MATRIX_SWITCHER["ack_polls"] if max_polls is None else max_polls
        if not pia.wait_flag1(side, polls):
            raise BoardError(f"{self.name}: matrix switcher did not acknowledge route 0x{value:02X} "
                             f"on CA1 within {polls} polls of CRA at A16 0x{pia._ctrl[side]:04X}")
        pia.clear_flags(side)
