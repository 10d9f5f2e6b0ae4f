"""A board's start-up transactions are tried again after a bus error (a gateway's time-out on
a loaded host), up to ``INIT_ATTEMPTS`` in all; an unreachable gateway is not. The bus is the
fake rack's, with transient bus errors on one board's address range (what a time-out looks
like to the service: ``BusError`` from the bus)."""

from __future__ import annotations

import uuid

import pytest

from bit3.buffer import Bit3Buffer
from bit3.layout import BOARD_FAULT, BOARD_INIT, BOARD_OK, build_layout
from fakes.world import FakeWorld
from ioservice.service import INIT_ATTEMPTS, IoService
from ioservice.ticking import TickingClock
from pfma.clock import SimClock
from pfma.errors import BusError


class FlakyBus:
    """The fake rack's bus; the first ``failures`` accesses in [lo, hi) raise BusError(reason)."""

    def __init__(self, bus, lo: int, hi: int, failures: int, reason: str = "time-out") -> None:
        self.bus, self.lo, self.hi, self.left, self.reason = bus, lo, hi, failures, reason
        self.failed = 0

    def _check(self, addr: int, width: int, op: str) -> None:
        if self.left > 0 and self.lo <= addr < self.hi:
            self.left -= 1
            self.failed += 1
            raise BusError(addr, width, op, reason=self.reason)

    def read8(self, addr):
        self._check(addr, 8, "read")
        return self.bus.read8(addr)

    def read16(self, addr):
        self._check(addr, 16, "read")
        return self.bus.read16(addr)

    def write8(self, addr, value):
        self._check(addr, 8, "write")
        self.bus.write8(addr, value)

    def write16(self, addr, value):
        self._check(addr, 16, "write")
        self.bus.write16(addr, value)

    def read_block16(self, addr, n):
        self._check(addr, 16, "read")
        return self.bus.read_block16(addr, n)

    def write_block16(self, addr, words):
        self._check(addr, 16, "write")
        self.bus.write_block16(addr, words)


def _service(failures: int, reason: str = "time-out"):
    clock = SimClock()
    world = FakeWorld(clock=clock)
    rtd1 = world.rack_config.board("rtd1")
    bus = FlakyBus(world.bus, rtd1.base, rtd1.base + 0x100, failures, reason)
    name = "pfma-test-retry-" + uuid.uuid4().hex[:8]
    layout = build_layout(world.rack_config)
    buf = Bit3Buffer.create(name, layout)
    tclock = TickingClock(clock)
    tclock.hooks.append(world.tick)
    svc = IoService(world.rack_config, bus, buf, tclock)
    status = int(svc._v["board_status"][layout.slot("board", "rtd1")])
    return svc, buf, name, bus, status


@pytest.fixture
def made():
    out = []
    yield out
    for svc, buf, name in out:
        svc.stop()
        buf.close()
        Bit3Buffer.unlink(name)


def test_a_board_that_times_out_once_at_start_is_initialised_and_named(made):
    svc, buf, name, bus, status = _service(failures=INIT_ATTEMPTS - 1)
    made.append((svc, buf, name))
    assert status == BOARD_OK | BOARD_INIT
    assert bus.failed == INIT_ATTEMPTS - 1
    assert any(n.startswith("rtd1: answered its start-up on attempt 3") and "time-out" in n for n in svc.notes)


def test_a_board_that_never_answers_is_a_fault_after_every_attempt(made):
    svc, buf, name, bus, status = _service(failures=100)
    made.append((svc, buf, name))
    assert status & BOARD_FAULT
    assert bus.failed == INIT_ATTEMPTS


def test_an_unreachable_gateway_is_not_tried_again(made):
    svc, buf, name, bus, status = _service(failures=100, reason="gateway 127.0.0.1:1 unreachable")
    made.append((svc, buf, name))
    assert status & BOARD_FAULT
    assert bus.failed == 1
