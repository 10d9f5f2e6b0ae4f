"""Register-level fake of the MVME410: two FakePia6821 at +0x01 and +0x09, plus peers.

Register map and every assumption: ``drivers.pio.registers.MVME410`` (R5). The board
also carries a model of the **matrix switcher** on port 0 (PIA1 port A, CA2 strobe,
CA1 acknowledge; ASSUMED table ``MATRIX_SWITCHER``): when CA2 returns high after a
strobe, the switcher latches port A's output pins as the route and, ``ack_delay_s``
of model time later, pulses CA1 low then high.

Model time follows the board's clock: each bus access first runs events due by
``clock.now()``; ``step(dt_s)`` runs ``dt_s`` more (never double-counting a period the
clock also covered).

A board may also carry the **amplifier-enable charge-pump relay** on one output bit
(:meth:`FakeMvme410.attach_charge_pump`, the rack file's ``[amplifier_enable]``; ASSUMED
behaviour in one table, ``drivers.pio.registers.CHARGE_PUMP``): it holds the amplifiers
enabled while the bit keeps changing level and drops when it stops.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable

from drivers.pio.registers import CHARGE_PUMP, MATRIX_SWITCHER, MVME410, PORTS, decode_matrix_route
from fakes.board import FakeBoard, NoAnswer
from fakes.pia import FakePia6821, even_byte_reason
from pfma.clock import Clock


class EventQueue:
    """Tiny model-time scheduler shared by the 8-bit-chip fakes."""

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.t = clock.now()
        self._q: list[tuple[float, int, Callable[[], None]]] = []
        self._n = itertools.count()

    def at(self, t: float, action: Callable[[], None]) -> None:
        heapq.heappush(self._q, (t, next(self._n), action))

    def after(self, dt_s: float, action: Callable[[], None]) -> None:
        self.at(self.t + dt_s, action)

    def run_until(self, t: float) -> None:
        while self._q and self._q[0][0] <= t:
            te, _, action = heapq.heappop(self._q)
            self.t = max(self.t, te)
            action()
        self.t = max(self.t, t)

    def sync(self) -> None:
        """Catch model time up with the clock."""
        self.run_until(self.clock.now())


class MatrixSwitcher:
    """Peer on PIA1 port A: latches the route on the strobe, acknowledges on CA1.

    :param pia: the PIA whose port A / CA1 / CA2 the switcher is wired to
    :param events: model-time scheduler
    :param ack_delay_s: delay from strobe to the acknowledge pulse
    """

    def __init__(self, pia: FakePia6821, events: EventQueue,
                 ack_delay_s: float = MATRIX_SWITCHER["ack_delay_s"],
                 ack_width_s: float = 2e-6) -> None:
        self.pia = pia
        self.events = events
        self.ack_delay_s = ack_delay_s
        self.ack_width_s = ack_width_s
        self.route: int | None = None  #: last latched route byte (None = never strobed)
        self.strobes = 0  #: number of strobes seen
        self.acks = 0  #: acknowledges sent
        self.silent = False  #: when True the switcher latches but never acknowledges
        pia.on_strobe = self._strobe

    @property
    def monitors(self) -> tuple[int, int] | None:
        """(monitor 1 camera, monitor 2 camera), 0 = blank, from the latched route."""
        return None if self.route is None else decode_matrix_route(self.route)

    def _strobe(self, side: str) -> None:
        if side != "a":
            return
        self.strobes += 1
        self.route = self.pia.port_a_output()
        if not self.silent:
            self.events.after(self.ack_delay_s, self._ack_low)

    def _ack_low(self) -> None:
        self.pia.drive_ca1(False)
        self.events.after(self.ack_width_s, self._ack_high)

    def _ack_high(self) -> None:
        self.pia.drive_ca1(True)
        self.acks += 1


class ChargePumpRelay:
    """Peer on one output pin: a charge-pump watchdog relay (``CHARGE_PUMP``, assumed).

    Every change of the pin's level (latch AND DDR, what the board drives) is an edge, seen
    at the bus access that made it. The relay is pulled in while the last two edges came
    less than ``drop_s`` apart and the last one less than ``drop_s`` ago: one edge never pulls
    it in, and a pin held at either level drops it ``drop_s`` after its last edge.

    :param level: the pin as it is now (a function of nothing: the board's output)
    :param now: the board's clock
    """

    def __init__(self, level: Callable[[], int], now: Callable[[], float],
                 drop_s: float = CHARGE_PUMP["drop_s"]) -> None:
        self._level = level
        self._now = now
        self.drop_s = drop_s
        self.level = level()
        self.edges = 0  #: level changes seen
        self._last: float | None = None  # time of the last edge
        self._prev: float | None = None  # and of the one before

    def sample(self) -> None:
        """After a bus write to the board: an edge if the pin changed level."""
        lvl = self._level()
        if lvl != self.level:
            self.level = lvl
            self.edges += 1
            self._prev, self._last = self._last, self._now()

    def energized(self, t: float | None = None) -> bool:
        """Whether the relay holds the amplifiers enabled at ``t`` (default: now)."""
        if self._last is None or self._prev is None:
            return False
        t = self._now() if t is None else t
        return self._last - self._prev < self.drop_s and t - self._last < self.drop_s

    @property
    def drops_at(self) -> float | None:
        """When the relay drops (or dropped) if no edge comes: ``drop_s`` after the last one."""
        return None if self._last is None else self._last + self.drop_s


class FakeMvme410(FakeBoard):
    """Fake MVME410 (two PIAs) with a matrix switcher model on port 0.

    :param name: board name (rack)
    :param clock: shared clock (default SimClock)
    """

    description = MVME410
    FAULTS = ("switcher_silent",)  #: the matrix switcher latches but never acknowledges

    def __init__(self, name: str | None = None, clock: Clock | None = None) -> None:
        super().__init__(name, clock)
        self.events = EventQueue(self.clock)
        self.pia1 = FakePia6821(f"{self.name}.PIA1")
        self.pia2 = FakePia6821(f"{self.name}.PIA2")
        self.switcher = MatrixSwitcher(self.pia1, self.events)
        self.relay: ChargePumpRelay | None = None  #: the charge-pump relay, if one is wired
        self._pia_at = {}
        for idx, pia in enumerate((self.pia1, self.pia2)):
            first = MVME410.reg(f"PIA{idx + 1}_PRA").offset
            for rs in range(4):
                self._pia_at[first + 2 * rs] = (pia, rs)

    # -- faults ---------------------------------------------------------------------------
    def inject(self, fault: str, **params) -> None:
        super().inject(fault, **params)
        if fault == "switcher_silent":
            self.switcher.silent = True

    def clear(self, fault: str | None = None) -> None:
        super().clear(fault)
        if fault in (None, "switcher_silent"):
            self.switcher.silent = False

    # -- bus side -------------------------------------------------------------------------
    def _check(self, offset: int, width: int) -> None:
        if width == 8 and offset % 2 == 0 and 0 <= offset < self.description.window \
                and "no_answer" not in self.faults:
            raise NoAnswer(even_byte_reason(self.description, offset))
        super()._check(offset, width)

    def _locate(self, offset: int) -> tuple[FakePia6821, int]:
        try:
            return self._pia_at[offset]
        except KeyError:
            raise NoAnswer(f"offset +0x{offset:02X} is not decoded (registers at +0x01..+0x0F)") from None

    def _read8(self, offset: int) -> int:
        pia, rs = self._locate(offset)
        self.events.sync()
        return pia.read(rs)

    def _write8(self, offset: int, value: int) -> None:
        pia, rs = self._locate(offset)
        self.events.sync()
        pia.write(rs, value)
        if self.relay is not None:
            self.relay.sample()

    def step(self, dt_s: float) -> None:
        """Run ``dt_s`` of model time (switcher acknowledge pulses)."""
        self.events.run_until(max(self.events.t + dt_s, self.clock.now()))

    # -- physical side -----------------------------------------------------------------
    def _port(self, port: int) -> tuple[FakePia6821, str]:
        if port not in PORTS:
            raise ValueError(f"{self.name}: port {port} not in 0..3")
        pia, side = PORTS[port]
        return (self.pia1, self.pia2)[pia], side

    def drive_inputs(self, port: int, value: int | None, mask: int = 0xFF) -> None:
        """Drive port 0..3's pins from outside (``None`` releases them; they read high)."""
        pia, side = self._port(port)
        (pia.drive_port_a if side == "a" else pia.drive_port_b)(value, mask)

    def outputs(self, port: int) -> int:
        """Port 0..3's pins driven by the board (latch AND DDR; input bits read 0)."""
        pia, side = self._port(port)
        return pia.port_a_output() if side == "a" else pia.port_b_output()

    def attach_charge_pump(self, port: int, bit: int, drop_s: float = CHARGE_PUMP["drop_s"]) -> ChargePumpRelay:
        """Wire a charge-pump relay (``CHARGE_PUMP``) to output ``bit`` of ``port``."""
        if not 0 <= bit <= 7:
            raise ValueError(f"{self.name}: bit {bit} not in 0..7")
        self._port(port)
        self.relay = ChargePumpRelay(lambda: (self.outputs(port) >> bit) & 1, self.clock.now, drop_s)
        return self.relay

    @property
    def route(self) -> int | None:
        """The matrix switcher's latched route byte (None until the first strobe)."""
        return self.switcher.route
