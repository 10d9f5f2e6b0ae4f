"""A clock whose waits do useful work in small ticks.

The frame loop sleeps between frames. ``TickingClock.sleep_until`` splits that
sleep into ticks of at most ``tick_s`` and runs the registered hooks between
them. The service uses it to drain the serial boards' 3-character receive FIFOs
often enough (at 19200 baud a FIFO fills in 1.56 ms, shorter than a 3.125 ms
frame) without a reader thread competing for the GIL, and the simulated rack
uses it to advance the arm between frames. No hook runs at the deadline itself,
so a frame starts as soon as its deadline passes.

Works the same over the real monotonic clock and a ``SimClock`` (deterministic).
"""

from __future__ import annotations

from typing import Callable

from pfma.clock import Clock


class TickingClock:
    """Wraps a clock; ``hooks`` are called as ``hook(now)`` at each intermediate tick.

    :param base: the clock that really waits (monotonic) or jumps (simulated)
    :param tick_s: longest stretch between hook calls while sleeping
    """

    def __init__(self, base: Clock, tick_s: float = 0.0007) -> None:
        if tick_s <= 0:
            raise ValueError("tick_s must be positive")
        self.base = base
        self.tick_s = tick_s
        self.hooks: list[Callable[[float], None]] = []
        self.simulated = getattr(base, "simulated", False)

    def now(self) -> float:
        return self.base.now()

    def advance(self, dt: float) -> None:
        self.base.advance(dt)

    def tick(self) -> None:
        """Run the hooks once, now."""
        now = self.base.now()
        for hook in self.hooks:
            hook(now)

    def sleep_until(self, t: float) -> None:
        base, tick = self.base, self.tick_s
        while True:
            now = base.now()
            if now + tick >= t:
                base.sleep_until(t)
                return
            base.sleep_until(now + tick)
            self.tick()
