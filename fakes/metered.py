"""A RegisterBus wrapper that measures how much time the bus behind it takes.

Benchmarks use it to split a frame's work on the simulated rack into the service's own
cost (drivers, conversions, publish) and the register-level fakes' emulation, which a
real rack does in hardware. ``sim_s`` accumulates the wall-clock time spent inside the
wrapped bus. The wrapper's own cost per access (its call, two timer reads, counters) is
not in ``sim_s``; :func:`overhead_per_access_s` measures it so a benchmark can take it
out of the service's share.
"""

from __future__ import annotations

import time


class _NullBus:
    def read16(self, addr: int) -> int:
        return 0


def overhead_per_access_s(n: int = 20000) -> float:
    """What a MeteredBus adds to one access, beyond calling the bus directly (median of
    five runs of ``n`` reads on a bus that does nothing)."""
    null = _NullBus()
    metered = MeteredBus(null)
    runs = []
    for _ in range(5):
        r = null.read16
        t0 = time.perf_counter()
        for _ in range(n):
            r(0)
        direct = time.perf_counter() - t0
        r = metered.read16
        t0 = time.perf_counter()
        for _ in range(n):
            r(0)
        runs.append((time.perf_counter() - t0 - direct) / n)
    runs.sort()
    return max(0.0, runs[2])


def _metered(op: str):
    """A MeteredBus method that forwards ``op`` to the wrapped bus and times it."""
    def call(self, *args):
        t0 = time.perf_counter()
        try:
            return getattr(self.bus, op)(*args)
        finally:
            self.sim_s += time.perf_counter() - t0
            self.accesses += 1
    call.__name__ = op
    return call


class MeteredBus:
    """Forwards ``read8/read16/write8/write16`` and the block transfers to ``bus`` and sums
    the time they take (a block is one access in :attr:`accesses`).

    :param bus: the bus to measure (a ``FakeRack``); other attributes pass through
    """

    def __init__(self, bus) -> None:
        self.bus = bus
        self.sim_s = 0.0  #: seconds spent inside the wrapped bus since creation
        self.accesses = 0  #: bus calls forwarded (a block transfer counts once)

    def __getattr__(self, name):
        return getattr(self.bus, name)

    def __getitem__(self, name):
        return self.bus[name]

    read8 = _metered("read8")
    read16 = _metered("read16")
    write8 = _metered("write8")
    write16 = _metered("write16")
    read_block16 = _metered("read_block16")
    write_block16 = _metered("write_block16")
