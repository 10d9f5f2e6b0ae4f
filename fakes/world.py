"""The whole simulated rack a service runs against: boards, arm, F/T sensor, CRL master.

``FakeWorld`` wires :class:`fakes.sim_rack.SimulatedRack` (fake boards + arm model)
to a :class:`fakes.ft_sensor.FakeFtController` on the MVME400's port A (the Lord
F/T sensor, loaded by the arm's contact forces and tool gravity) and a
:class:`fakes.crl.FakeCrlMaster` on port B (the CRL hand controller), exactly as the
IRSS report's I/O chassis wires them (section 3.4.2). Its :meth:`tick` is a clock
hook: each call advances the physical world to the clock's time.
"""

from __future__ import annotations

from fakes.crl import FakeCrlMaster
from fakes.ft_sensor import FakeFtController
from fakes.sim_rack import SimulatedRack
from pfma.clock import Clock, SimClock
from pfma.rack import RackConfig, load_rack


class FakeWorld:
    """The simulated rack and what is cabled to it.

    :param rack: rack configuration (default: the report's)
    :param clock: shared by the boards and the world (default: a new SimClock)
    :param max_step_s: longest single physics step when the world falls behind
    :param min_step_s: ticks closer together than this are skipped (bounds the cost)
    :param sim_kwargs: :class:`fakes.sim_rack.SimulatedRack` arguments: ``errors``,
        ``environment``, ``shoulder_roll_rad`` (where the arm's hand-indexed shoulder roll
        is pinned, pfma-model 8.1)
    """

    def __init__(self, rack: RackConfig | None = None, clock: Clock | None = None,
                 max_step_s: float = 0.005, min_step_s: float = 0.001, **sim_kwargs) -> None:
        self.rack_config = rack if rack is not None else load_rack()
        self.clock = clock if clock is not None else SimClock()
        self.sim = SimulatedRack(self.rack_config, clock=self.clock, **sim_kwargs)
        self.bus = self.sim.fake_rack
        for board in self.bus.boards.values():  # a long-running world keeps no traffic log
            board.log_traffic = False
        self.max_step_s = max_step_s
        self.min_step_s = min_step_s
        self.ft = FakeFtController()
        self.sim.attach_ft(self.ft)
        self.crl = FakeCrlMaster()
        serial = self.rack_config.boards_of("serial")
        if serial:
            sio = self.bus[serial[0].name]
            chans = {c.signal: c.channel for c in serial[0].channels}
            if "ft_sensor" in chans:
                sio.peer(chans["ft_sensor"]).attach(self.ft)
            if "crl_hand_controller" in chans:
                sio.peer(chans["crl_hand_controller"]).attach(self.crl)
        self._t = self.clock.now()

    def tick(self, now: float) -> None:
        """Advance the physical world to ``now`` (a TickingClock hook)."""
        dt = now - self._t
        if dt < self.min_step_s:
            return
        self._t = now
        while dt > 0:
            step = min(dt, self.max_step_s)
            self.sim.step(step, boards=False)  # the clock is already at ``now``
            dt -= step
        self.bus.step(0.0)  # boards that follow the clock catch up to ``now``

    # convenience for tests and demos
    def set_cae(self, axes_volts, discretes=(False, False, False)) -> None:
        self.sim.set_cae(axes_volts, discretes)

    def set_user_inputs(self, word: int) -> None:
        """Drive the 16 user I/F box input bits (MVME410 at 0x0040, ports 0 and 1)."""
        for b in self.rack_config.boards_of("pio"):
            if any(c.signal.startswith("user_if_box_inputs") for c in b.channels):
                board = self.bus[b.name]
                board.drive_inputs(0, word & 0xFF)
                board.drive_inputs(1, (word >> 8) & 0xFF)
