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


#: lines a :class:`LivePrinter` says per second before it counts the rest (assumed: 10 a
#: second is what a person at the terminal can follow; a cascade of seven layers fits)
LIVE_PER_SECOND = 10
#: lines one :meth:`LivePrinter.flush` says at most (it runs after a frame: bounded work)
LIVE_PER_FLUSH = 4
#: messages queued for the printer at most (the newest kept; the others counted)
LIVE_QUEUE = 64


def live_line(m: Message) -> str:
    """One message on one line: time since start, source, level, text (newlines folded)."""
    text = m.text.replace("\r", " ").replace("\n", " | ")
    return f"{m.t_s:10.3f} s  {m.source:<10} {m.level.name:<7} {text}"


def is_always_said(m: Message) -> bool:
    """Said even over the rate limit (they are few: one per status change of one layer, one
    per ERROR episode): System Up/Down's status changes and the runtime's first-cause line."""
    return (m.source == "updown" and "(row " in m.text) or (m.source == "runtime" and m.text.startswith("first cause: "))


def is_live_worthy(m: Message) -> bool:
    """What a live controller says as it happens: every WARNING and ERROR, and System
    Up/Down's status changes (its decision-table lines, "A -> B (row N: ...)")."""
    return m.level >= Level.WARNING or (m.source == "updown" and "(row " in m.text)


class LivePrinter:
    """Says messages as they happen, outside the frame's work.

    As a :class:`MessageBoard` listener it only queues the message (a bounded deque append,
    in the frame); :meth:`flush`, called after the frame, writes at most ``per_flush`` lines
    and at most ``per_second`` a second (System Up/Down's changes and the first cause are
    said over it), then one "... K more" line when the second is over.

    :param write: takes one line (e.g. ``print``)
    :param clock: monotonic seconds (a fake one in tests)
    :param wanted: which messages are said (default :func:`is_live_worthy`)
    :param fmt: a message's line (default :func:`live_line`; ``pfma serve`` says the Bit3
        queue's messages with its own)
    :param always: messages said even over the rate (default :func:`is_always_said`)
    """

    def __init__(self, write, clock, *, per_second: int = LIVE_PER_SECOND, per_flush: int = LIVE_PER_FLUSH,
                 keep: int = LIVE_QUEUE, wanted=is_live_worthy, fmt=live_line,
                 always=is_always_said) -> None:
        self.write = write
        self.always = always
        self.fmt = fmt
        self.clock = clock
        self.per_second = per_second
        self.per_flush = per_flush
        self.wanted = wanted
        self.queue: deque = deque(maxlen=keep)
        self.said = 0  #: lines written (messages)
        self.held = 0  #: messages not said (over the rate, or the queue full), all told
        self._window_t = -float("inf")
        self._in_window = 0
        self._untold = 0  # messages not said in this window (the "... K more" line)

    def __call__(self, m) -> None:
        if self.wanted(m):
            if len(self.queue) == self.queue.maxlen:
                self._untold += 1
                self.held += 1
            self.queue.append(m)

    def flush(self) -> None:
        if not self.queue and not self._untold:
            return
        now = self.clock()
        if now - self._window_t >= 1.0:
            if self._untold:
                self.write(self._more())
            self._window_t, self._in_window, self._untold = now, 0, 0
        n = 0
        while self.queue and n < self.per_flush:
            m = self.queue.popleft()
            if self._in_window < self.per_second or self.always(m):
                self.write(self.fmt(m))
                self._in_window += 1
                self.said += 1
                n += 1
            else:
                self._untold += 1
                self.held += 1

    def drain(self) -> None:
        """Say what is still queued, within the rate (at exit, before the summary)."""
        while self.queue:
            self.flush()  # over the rate, a flush counts the rest of the queue as not shown
        if self._untold:
            self.write(self._more())
            self._untold = 0

    def _more(self) -> str:
        return (f"... {self._untold} more message{'s' if self._untold != 1 else ''} not shown "
                f"(at most {self.per_second} lines a second)")
