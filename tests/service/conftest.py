"""A simulated-time rig: FakeWorld + IoService + a commanding client on a private buffer."""

import uuid

import pytest

from fakes.world import FakeWorld
from ioservice.client import Client
from ioservice.service import IoService
from ioservice.shm import Bit3Buffer
from ioservice.ticking import TickingClock
from pfma.clock import SimClock


class Rig:
    def __init__(self, name: str, **service_kw) -> None:
        self.name = name
        self.clock = SimClock()
        self.world = FakeWorld(clock=self.clock)
        self.tclock = TickingClock(self.clock)
        self.tclock.hooks.append(self.world.tick)
        self.buf = Bit3Buffer.create(name)
        self.svc = IoService(self.world.rack_config, self.world.bus, self.buf, self.tclock, **service_kw)
        self.tclock.hooks.append(self.svc.serial_tick)
        self.reader = Client.attach(name)
        self.ctl = None
        self.on_frame = []  # callables(info) run before each service frame (the controller)
        body = self.svc.frame

        def frame(info):
            for f in self.on_frame:
                f(info)
            body(info)
        self.svc.loop.body = frame

    def controller(self) -> Client:
        self.ctl = Client.attach(self.name, writer="commands", owner="test-controller",
                                 clock_now=self.clock.now)
        return self.ctl

    def run(self, seconds: float):
        return self.svc.loop.run(frames=int(round(seconds * self.svc.schedule.frame_rate_hz)),
                                 freeze_gc=False)

    def close(self):
        if self.ctl is not None:
            self.ctl.close()
        self.reader.close()
        self.svc.stop()
        self.buf.close()
        Bit3Buffer.unlink(self.name)


@pytest.fixture
def rig():
    r = Rig("pfma-test-" + uuid.uuid4().hex[:8])
    yield r
    r.close()
