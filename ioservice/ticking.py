"""A clock whose waits do useful work in small ticks.

The frame loop sleeps between frames. ``TickingClock.sleep_until`` splits that
sleep into ticks of at most ``tick_s`` and runs the registered hooks between
them. The service uses it to drain the serial boards' 3-character receive FIFOs
often enough (at 19200 baud a FIFO fills in 1.56 ms, shorter than a 3.125 ms
frame) without a reader thread competing for the GIL, and the simulated rack
uses it to advance the arm between frames. No hook runs at the deadline itself,
so a frame starts as soon as its deadline passes.

``pre_deadline_hooks`` run once per sleep, at the first tick within ``pre_deadline_s`` of
its end (or at once when the sleep is shorter): work needed once per frame, just before
it, such as stepping the simulated arm so the frame reads its state at most about
``pre_deadline_s`` old (``pfma serve`` on the simulated rack). The ordinary hooks run
right after them (the service's serial drain, so a long step does not overrun a FIFO).

Works the same over the real monotonic clock and a ``SimClock`` (deterministic).

``timers`` (each with a ``due`` clock time and ``fire(now)``) run at their due time within a
sleep, before the sleep's end when due earlier; one due at the sleep's end itself runs after
the frame, in the next sleep. The system simulator runs a controller on its own frame clock
this way (sim/system.py); the live service has none.
"""

from __future__ import annotations

from typing import Callable

from pfma.clock import Clock


class TickingClock:
    """Wraps a clock; ``hooks`` are called as ``hook(now)`` at each intermediate tick.

    :param base: the clock that really waits (monotonic) or jumps (simulated)
    :param tick_s: longest stretch between hook calls while sleeping
    """

    def __init__(self, base: Clock, tick_s: float = 0.0007, pre_deadline_s: float | None = None) -> None:
        if tick_s <= 0:
            raise ValueError("tick_s must be positive")
        self.base = base
        self.tick_s = tick_s
        self.hooks: list[Callable[[float], None]] = []
        self.pre_deadline_hooks: list[Callable[[float], None]] = []
        #: objects with ``due`` (clock time) and ``fire(now)``, which sets the next ``due``
        self.timers: list = []
        #: how long before a sleep's end its pre-deadline hooks run (default: two ticks,
        #: so a hook of up to about one tick does not make the frame late)
        self.pre_deadline_s = 2 * tick_s if pre_deadline_s is None else pre_deadline_s
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
        pre_due = bool(self.pre_deadline_hooks)
        inf = float("inf")
        while True:
            now = base.now()
            due = self._fire_timers(now) if self.timers else inf
            if pre_due and t - now <= self.pre_deadline_s:
                pre_due = False  # once per sleep
                for hook in self.pre_deadline_hooks:
                    hook(now)
                self.tick()  # the ordinary hooks right after (a serial drain after a long step)
                continue
            if due < t and due < now + tick:  # a timer before the next tick: sleep to it exactly
                base.sleep_until(due)
                continue
            if now + tick >= t:
                base.sleep_until(t)
                return
            base.sleep_until(now + tick)
            self.tick()

    def _fire_timers(self, now: float) -> float:
        """Fire the timers due by ``now``; the earliest due time left."""
        nxt = float("inf")
        for tm in self.timers:
            if tm.due <= now:
                tm.fire(now)
            nxt = min(nxt, tm.due)
        return nxt
