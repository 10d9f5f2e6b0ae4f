"""Clocks. Everything that waits or timestamps takes one of these.

``MonotonicClock`` is used in service; ``SimClock`` in tests and single-step mode,
where tests advance time explicitly and nothing sleeps.
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    def now(self) -> float:
        """Seconds on a monotonic time base."""
        ...

    def sleep_until(self, t: float) -> None:
        """Block (or, simulated, jump) until ``now() >= t``."""
        ...

    def advance(self, dt: float) -> None:
        """Simulated: move time on by ``dt``; real: nothing (time passes by itself)."""
        ...


class MonotonicClock:
    """The real monotonic clock (``time.monotonic``)."""

    simulated = False

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t: float) -> None:
        dt = t - time.monotonic()
        if dt > 0:
            time.sleep(dt)

    def advance(self, dt: float) -> None:  # real time passes by itself
        pass


class SimClock:
    """Simulated time: only ``advance``/``sleep_until`` move it.

    :param t0: starting time in seconds
    """

    simulated = True

    def __init__(self, t0: float = 0.0) -> None:
        self._t = float(t0)

    def now(self) -> float:
        return self._t

    def advance(self, dt: float) -> None:
        if dt < 0:
            raise ValueError(f"cannot advance a clock backwards (dt={dt})")
        self._t += dt

    def sleep_until(self, t: float) -> None:
        if t > self._t:
            self._t = t
