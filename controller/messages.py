"""Messages from every layer: bounded queues per source, the last 100 time-ordered.

IRSS report 2.2.8 / 2.3 (user interface): each processor had a message queue of "up
to 50 messages", a circular buffer; the user interface flushed them at every display
refresh and kept "up to 100 messages ... time/processor correlated". Here every layer
(and the runtime itself) is a source with its own 50-entry queue; :meth:`recent`
merges them by time (then frame, then order of posting) and returns the last 100.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass

#: messages kept per source (report: 50 per processor queue)
PER_SOURCE = 50
#: messages shown merged (report: 100 buffered in the user interface)
RECENT = 100


class Level(enum.IntEnum):
    DEBUG = 0
    INFO = 1
    WARNING = 2
    ERROR = 3


@dataclass(frozen=True)
class Message:
    seq: int  #: global posting order
    t_s: float  #: simulated or monotonic time
    frame: int  #: minor frame number
    source: str  #: layer key or "runtime"
    level: Level
    text: str

    def format(self) -> str:
        return (f"{self.t_s * 1e3:10.3f} ms  frame {self.frame:>6}  {self.source:<11} "
                f"{self.level.name:<7} {self.text}")


class MessageBoard:
    """Bounded per-source queues.

    :param per_source: capacity of each source's queue (oldest dropped first)
    """

    def __init__(self, per_source: int = PER_SOURCE) -> None:
        self.per_source = per_source
        self.queues: dict[str, deque[Message]] = {}
        self.dropped: dict[str, int] = {}
        self._seq = 0
        self.listeners: list = []  #: callables(Message), e.g. forwarding to the Bit3 queue

    def post(self, source: str, level: Level | int, text: str, t_s: float, frame: int) -> Message:
        q = self.queues.get(source)
        if q is None:
            q = self.queues[source] = deque(maxlen=self.per_source)
            self.dropped[source] = 0
        if len(q) == q.maxlen:
            self.dropped[source] += 1
        self._seq += 1
        m = Message(self._seq, t_s, frame, source, Level(level), text)
        q.append(m)
        for fn in self.listeners:
            fn(m)
        return m

    def recent(self, n: int = RECENT, source: str | None = None, min_level: int = Level.DEBUG) -> list[Message]:
        """The last ``n`` messages of every source (or one), in time order."""
        qs = [self.queues[source]] if source is not None else list(self.queues.values())
        msgs = [m for q in qs for m in q if m.level >= min_level]
        msgs.sort(key=lambda m: (m.t_s, m.frame, m.seq))
        return msgs[-n:]

    def format(self, n: int = RECENT, **kw) -> str:
        return "\n".join(m.format() for m in self.recent(n, **kw))

    def __len__(self) -> int:
        return sum(len(q) for q in self.queues.values())
