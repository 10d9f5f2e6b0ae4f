"""Counting what a port refused, said in one line per interval at most.

A server facing traffic it does not control (the Modbus export, the Zenoh bridge) must
neither write a line per refused request (a flood of bad requests becomes a flood of log
lines or of queued messages that pushes out the ones an operator needs) nor keep silent.
:class:`RefusalLog` notes each refusal under a short reason from a bounded set (a reason
carries a function code or a size at most, never the sender's data), says the first one
after a quiet interval at once and sums the rest into one line when ``interval_s`` has
passed since the last line (:meth:`tick`); :meth:`flush` says what is left at stop.
Where the line goes is the caller's: a logger, or the service's message queue.
"""

from __future__ import annotations

import time
from typing import Callable


class RefusalLog:
    """Counts refusals by reason; one line per ``interval_s`` at most, through ``emit``.

    :param what: who refused, as the line starts ("Modbus export 127.0.0.1:5020")
    :param emit: called with each line
    :param clock: seconds, monotonic (injectable for tests)
    """

    #: reasons listed in one line; the rest are summed
    SHOWN = 6

    def __init__(self, what: str, emit: Callable[[str], None], interval_s: float = 60.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.what = what
        self.emit = emit
        self.interval_s = interval_s
        self.clock = clock
        self.total: dict[str, int] = {}  #: every reason since the start
        self.lines = 0  #: lines said
        self._pending: dict[str, int] = {}
        self._last_line: float | None = None
        self._since: float | None = None

    def note(self, reason: str, n: int = 1) -> None:
        self.total[reason] = self.total.get(reason, 0) + n
        self._pending[reason] = self._pending.get(reason, 0) + n
        if self._since is None:
            self._since = self.clock()
        self.tick()

    def tick(self) -> None:
        """Say the pending counts if the interval since the last line has passed."""
        if not self._pending:
            return
        now = self.clock()
        if self._last_line is None or now - self._last_line >= self.interval_s:
            self._say(now)

    def flush(self) -> None:
        """Say what is pending now (at stop)."""
        if self._pending:
            self._say(self.clock())

    def _say(self, now: float) -> None:
        items = sorted(self._pending.items(), key=lambda kv: (-kv[1], kv[0]))
        shown = ", ".join(f"{reason}: {n}" for reason, n in items[:self.SHOWN])
        rest = sum(n for _, n in items[self.SHOWN:])
        if rest:
            shown += f", and {rest} more of {len(items) - self.SHOWN} other kinds"
        span = now - (self._since if self._since is not None else now)
        self.lines += 1
        self._pending = {}
        self._last_line = now
        self._since = None
        self.emit(f"{self.what} refused in the last {span:.0f} s: {shown} "
                  f"(totals since start: {sum(self.total.values())})")


__all__ = ["RefusalLog"]
