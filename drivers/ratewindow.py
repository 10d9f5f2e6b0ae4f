"""Events per second over a sliding window of clock time (link statistics of the F/T and
hand-controller drivers)."""

from __future__ import annotations

from collections import deque


class RateWindow:
    """Marks event times; ``rate_hz(now)`` is (events - 1) / (last - first) over the
    events of the last ``window_s`` seconds, 0.0 with fewer than two.

    :param window_s: the sliding window
    """

    def __init__(self, window_s: float = 1.0) -> None:
        self.window_s = window_s
        self._times: deque[float] = deque()

    def mark(self, t: float) -> None:
        """One event at clock time ``t`` (times never go backwards)."""
        self._times.append(t)
        self._prune(t)

    def rate_hz(self, now: float) -> float:
        times = self._prune(now)
        return (len(times) - 1) / (times[-1] - times[0]) if len(times) >= 2 and times[-1] > times[0] else 0.0

    def clear(self) -> None:
        self._times.clear()

    def _prune(self, now: float) -> deque[float]:
        times = self._times
        while times and times[0] < now - self.window_s:  # out of the window for good
            times.popleft()
        return times
