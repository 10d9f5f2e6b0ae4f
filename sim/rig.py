"""The simulated rack and the I/O service in one process, on one simulated clock.

``SimRig`` is the one place that assembles :class:`fakes.world.FakeWorld` (fake
boards, arm model, F/T and CRL fakes), an :class:`ioservice.service.IoService` on a
private Bit3 buffer and a read-only client, stepped deterministically in
simulated time. Tests, ``pfma checkout --rack fake``, ``pfma calibrate --rack fake``
and the controller's system simulator all build on it.

Callables in :attr:`SimRig.on_frame` run just before each service frame (a test's
or a tool's "controller"), those in :attr:`SimRig.after_frame` right after it (the
controller runtime, its minor frame locked to the service's), on the same clock.
"""

from __future__ import annotations

import uuid
from typing import Any, Callable

from fakes.world import FakeWorld
from bit3.client import Client
from bit3.layout import build_layout
from ioservice.service import IoService
from bit3.buffer import Bit3Buffer
from bit3.ring import FrameRing
from ioservice.ticking import TickingClock
from pfma.clock import SimClock
from pfma.rack import RackConfig


class SimRig:
    """Fake world + service + reader on one SimClock.

    :param rack: rack configuration (default: the IRSS rack)
    :param name: Bit3 shared-memory name (default: a private random one)
    :param prefix: prefix of the random name
    :param service_kw: extra ``IoService`` arguments (``calibration=``, ``schedule=`` ...)
    :param ring: also keep the frame history ring ``/dev/shm/NAME.ring`` (bit3/ring.py), as
        ``pfma serve`` does, for a recorder reading the rig from another process
    :param world_kw: extra ``FakeWorld`` arguments (``errors=``, ``environment=`` ...)
    """

    def __init__(self, rack: RackConfig | None = None, *, name: str | None = None,
                 prefix: str = "pfma-sim-", service_kw: dict | None = None, ring: bool = False,
                 **world_kw: Any) -> None:
        self.name = name or prefix + uuid.uuid4().hex[:8]
        self.clock = SimClock()
        self.world = FakeWorld(rack, clock=self.clock, **world_kw)
        self.rack = self.world.rack_config
        self.layout = build_layout(self.rack)
        self.tclock = TickingClock(self.clock)
        self.tclock.hooks.append(self.world.tick)
        self.buf = Bit3Buffer.create(self.name, self.layout)
        self.svc = None
        self.reader = None
        self.ctl: Client | None = None
        self.ring: FrameRing | None = None
        try:
            self.svc = IoService(self.rack, self.world.bus, self.buf, self.tclock, **(service_kw or {}))
            if ring:
                self.ring = self.svc.ring = FrameRing.create(self.name, self.layout.area("inputs").body_size,
                                                             self.layout.hash)
            self.tclock.hooks.append(self.svc.serial_tick)
            self.reader = Client.attach(self.name, layout=self.layout, clock_now=self.clock.now)
        except BaseException:
            self.close()
            raise
        self.on_frame: list[Callable] = []  #: run before each service frame
        self.after_frame: list[Callable] = []  #: run after each service frame (a locked controller)
        body = self.svc.frame

        def frame(info) -> None:
            for f in self.on_frame:
                f(info)
            body(info)
            for f in self.after_frame:
                f(info)
        self.svc.loop.body = frame

    def controller(self, owner: str = "sim-controller") -> Client:
        """Claim the command area (one per rig) on the simulated clock."""
        if self.ctl is None:
            self.ctl = Client.attach(self.name, writer="commands", owner=owner, layout=self.layout,
                                     clock_now=self.clock.now)
        return self.ctl

    def run(self, seconds: float):
        """Run the service for ``seconds`` of simulated time (whole frames)."""
        return self.svc.loop.run(frames=int(round(seconds * self.svc.schedule.frame_rate_hz)),
                                 freeze_gc=False)

    def run_frames(self, frames: int):
        return self.svc.loop.run(frames=frames, freeze_gc=False)

    def close(self) -> None:
        """Stop the service (outputs safe), close every attachment, remove the buffer."""
        if self.ctl is not None:
            self.ctl.close()
            self.ctl = None
        if self.reader is not None:
            self.reader.close()
            self.reader = None
        if self.svc is not None:
            self.svc.stop()
            self.svc = None
        self.buf.close()
        Bit3Buffer.unlink(self.name)
        if self.ring is not None:
            self.ring.close()
            self.ring = None
            FrameRing.unlink(self.name)

    def __enter__(self) -> "SimRig":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
