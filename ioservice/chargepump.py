"""The amplifier-enable charge pump (issue 28 item 5, docs/safety.md "Honest outputs").

Every safe action of the service (0 V, the safe stop, the output guardian) goes through
the DAC board. When that board itself stops answering, its latches keep the last codes
written and nothing in software can change them. A rack can carry a second way to stop
the arm: an output bit of a parallel-port board (rack file ``[amplifier_enable]``,
:class:`pfma.rack.AmplifierEnable`) wired to a charge-pump relay that holds the servo
amplifiers' enable only while the bit keeps toggling (``drivers.pio.registers.CHARGE_PUMP``:
it drops within ``drop_s``, 20 ms assumed, of the last edge), as LinuxCNC's ``charge-pump``
and ``amp-enable-out`` outputs.

When it toggles: in every frame in which the service is ARMED and that frame's DAC write
succeeded, and in no other (decided here, named once): the relay is an *amplifier* enable
(LinuxCNC's ``amp-enable-out``, on only while the machine is enabled), not a "service is
alive" signal. Outside ARMED the service holds 0 V and the brakes set, so dropping the
amplifiers loses nothing; and every way out of ARMED (a trip, a refusal, a disarm, a halt,
a stop, a host stall, a killed process, a DAC that does not answer) then drops them as
well, through hardware that does not depend on the DAC board. A re-arm pulls the relay in
again two edges (two frames) later; the commands are 0 at arming anyway. The output guardian
never toggles it (it only writes the DAC), so a dead or stopped service drops it too.

The pump's port is the pump's alone: its other bits are written 0.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from bit3.layout import FaultCode
from drivers.pio.registers import CHARGE_PUMP
from pfma.errors import PfmaError

if TYPE_CHECKING:
    from ioservice.host import TaskHost

#: how the messages name the relay's drop-out time
DROP_MS = CHARGE_PUMP["drop_s"] * 1e3


class ChargePump:
    """The charge-pump output of one service (inactive when the rack has none).

    :param svc: the service as its tasks see it (its rack, drivers, buffer views, a trip)
    """

    def __init__(self, svc: TaskHost) -> None:
        self.svc = svc
        self.cfg = svc.rack.amplifier_enable  #: ``pfma.rack.AmplifierEnable`` or None
        self.drv: Any = None
        self.level = 0  #: the bit as last written
        self.running = False  #: it toggled in the last frame
        self.toggles = 0  #: writes that changed the bit
        self.failed: str | None = None  #: the last write's error while it should run (None: fine)
        self._slot: int | None = None  # pio_port_bits slot of the pump's channel

    @property
    def present(self) -> bool:
        return self.cfg is not None

    def describe(self) -> str:
        return "none" if self.cfg is None else f"charge pump {self.cfg.describe()}"

    def wire(self) -> None:
        """The board's driver (``PioTask.wire`` has configured its ports from the rack)."""
        if self.cfg is None:
            return
        svc = self.svc
        board = svc.rack.board(self.cfg.board)
        self.drv = svc.io.driver(board)
        self._slot = svc.layout.slot("pio", board.signal(self.cfg.port).signal)

    def frame(self, run: bool) -> None:
        """Once per frame: toggle the bit if ``run`` (ARMED and the DAC answered), else leave
        it as it is (no edge: the relay drops ``drop_s`` after the last one)."""
        if self.drv is None:
            return
        self.running = False
        if not run:
            return
        cfg = self.cfg
        assert cfg is not None
        level = self.level ^ 1
        try:
            self.drv.write_port(cfg.port, level << cfg.bit)
        except PfmaError as err:
            # ARMED, and the amplifiers are about to drop: FAULT, said (once per arming: the
            # pump runs again only after a re-arm)
            svc = self.svc
            svc.board_error(cfg.board, err)
            self.failed = str(err)
            svc.fault(FaultCode.AMP_ENABLE, f"amplifier-enable charge pump ({cfg.describe()}) not written: "
                                            f"{err}; the amplifiers drop within {DROP_MS:.0f} ms")
            return
        self.failed = None
        if self.svc.faulted_boards:
            self.svc.board_answered(cfg.board)
        self.level = level
        self.toggles += 1
        self.running = True
        if self._slot is not None:
            self.svc.values["pio_port_bits"][self._slot] = level << cfg.bit

    def probe(self) -> None:
        """The pump's bus transaction, timed with the DAC's at start (``IoService.measure_bus``):
        its port written with the level it holds, so no edge (the relay stays as it is)."""
        if self.drv is None or self.cfg is None:
            return
        try:
            self.drv.write_port(self.cfg.port, self.level << self.cfg.bit)
        except PfmaError:
            pass

    def stopped_text(self) -> str:
        """For the DAC-not-answering message: what the amplifier enable does now."""
        if self.cfg is None:
            return ("this rack has no amplifier-enable output (rack file [amplifier_enable]): "
                    "only the hardware E-stop stops the arm")
        return (f"amplifier enable dropped: charge pump {self.cfg.describe()} stopped, its relay "
                f"opens within {DROP_MS:.0f} ms")
