"""``pfma record --buffer zenoh://HOST:PORT/NAME``: a recording of a remote buffer through
its bridge (docs/bridge.md, docs/recording.md).

The same :class:`tools.recording.Recorder` writes the same file as a local recording
(``/pfma/inputs_raw`` byte for byte, the JSON channels, commands, statistics, messages);
only the source differs: a :class:`RemoteBuffer` that queues every inputs body the bridge
publishes. It is lossless when the link keeps up. When it does not, it says exactly which
frames it lost: each body carries the service's sequence number of the inputs area
(``bridge.SEQ``, +2 per publish), so

- a sequence step of 2 with a frame-number jump is a frame the **service** skipped (its
  own overrun, never published: counted as ``service_skipped``, as locally);
- a sequence step of more than 2 is publishes lost between the service and this
  recorder (the bridge polled too late, the link dropped them, or this side's queue was
  full): the missing frame numbers are the frame-number gap, written as ranges (a range
  may also hold frames the service skipped inside it: the count is of publishes, and the
  last line says how many of the range's numbers are such).

:class:`LinkLoss` keeps that account; it goes into the MCAP metadata ``pfma.link``
(``frames_lost``, ``lost_ranges`` as JSON ``[[first, last], ...]``) and the last lines
``pfma record`` prints. A bridge that attaches no sequence numbers (an older one) leaves
only the frame numbers: every frame-number gap then counts as lost (said in the metadata).
"""

from __future__ import annotations

import json
import logging
import sys
import time
from dataclasses import dataclass, field
from typing import Callable

from tools.bridge.remote import RemoteBuffer

log = logging.getLogger(__name__)

#: no inputs body for this long: say so once (the link or the service may be down); the
#: recorder keeps listening (Zenoh reconnects by itself)
STALE_S = 1.0
#: sleep between drains of the queue when it was empty (a 320 Hz frame is 3.125 ms; the
#: queue keeps every body, so this only sets the latency of writing, not what is kept)
DRAIN_S = 0.002
#: lost-frame ranges kept one by one; past this a new range is merged into the last one
#: (the ranges then cover every lost frame and some received ones, said in the metadata),
#: so a link that loses a frame every few frames for hours holds a bounded list. Assumption:
#: 10,000 ranges (~1 MB) is more than a recording worth reading range by range holds.
MAX_RANGES = 10_000


@dataclass
class LinkLoss:
    """Frames lost between the service and a remote reader, from the sequence numbers and
    frame counters of the inputs bodies received, in order (:meth:`feed`)."""

    received: int = 0         #: inputs bodies seen
    frames_lost: int = 0      #: publishes lost on the way (sequence jumps)
    service_skipped: int = 0  #: frame numbers the service itself skipped (not lost here)
    ranges: list[list[int]] = field(default_factory=list)  #: [first, last] frame numbers lost
    restarts: int = 0         #: the frame number went back (the service restarted)
    merged: int = 0           #: gaps merged into the last range past MAX_RANGES
    sequenced: bool = True    #: the bridge attached sequence numbers to every body

    _seq: int = -1
    _frame: int = -1

    def feed(self, seq: int | None, frame: int) -> None:
        self.received += 1
        if seq is None:
            self.sequenced = False
        ps, pf = self._seq, self._frame
        self._seq, self._frame = (-1 if seq is None else seq), frame
        if pf < 0:
            return
        if frame < pf or (seq is not None and ps >= 0 and seq < ps):
            self.restarts += 1  # a new service: its frames start again
            return
        gap = frame - pf - 1
        if seq is not None and ps >= 0:
            lost = (seq - ps) // 2 - 1
            if lost <= 0:
                self.service_skipped += max(gap, 0)
                return
            self.frames_lost += lost
        elif gap > 0:
            self.frames_lost += gap
        if gap > 0:
            self._add(pf + 1, frame - 1)

    def _add(self, first: int, last: int) -> None:
        if self.ranges and self.ranges[-1][1] == first - 1:
            self.ranges[-1][1] = last
        elif len(self.ranges) >= MAX_RANGES:
            self.ranges[-1][1] = last
            self.merged += 1
        else:
            self.ranges.append([first, last])

    def ranges_text(self, limit: int = 20) -> str:
        parts = [f"{a}" if a == b else f"{a}-{b}" for a, b in self.ranges[:limit]]
        more = len(self.ranges) - limit
        return ", ".join(parts) + (f" and {more} more ranges (pfma record info --json)" if more > 0 else "")

    def metadata(self, url: str) -> dict[str, str]:
        return {"source": url, "inputs_received": str(self.received), "frames_lost": str(self.frames_lost),
                "lost_ranges": json.dumps(self.ranges), "service_skipped": str(self.service_skipped),
                "service_restarts": str(self.restarts),
                **({"lost_ranges_merged": f"{self.merged} gaps past the first {MAX_RANGES} ranges merged into "
                                          f"the last range (it covers received frames too)"} if self.merged else {}),
                "counted_from": "sequence numbers and frame counters" if self.sequenced
                else "frame counters only (the bridge attached no sequence numbers)"}

    def line(self, url: str) -> str:
        if not self.frames_lost:
            return (f"pfma record: link from {url}: no frame lost ({self.received} inputs bodies; "
                    f"service skipped {self.service_skipped})")
        inside = sum(b - a + 1 for a, b in self.ranges) - self.frames_lost
        within = (f"; {inside} frame numbers within those ranges the service itself skipped"
                  if inside > 0 and not self.merged else
                  f"; past {MAX_RANGES} ranges the gaps are merged into the last one" if self.merged else "")
        return (f"pfma record: link from {url}: LOST {self.frames_lost} frames: frames "
                f"{self.ranges_text()} (service skipped {self.service_skipped} more{within})")


class RemoteRecording:
    """A :class:`Recorder` fed from a queued :class:`RemoteBuffer`, with its :class:`LinkLoss`.
    :meth:`pump` writes what has arrived (the CLI loop calls it; tests call it between
    simulated frames)."""

    def __init__(self, remote: RemoteBuffer, recorder, url: str) -> None:
        if remote._queue is None:
            raise ValueError("RemoteRecording needs a RemoteBuffer made with queue_inputs=True")
        self.remote = remote
        self.rec = recorder
        self.url = url
        self.loss = LinkLoss()

    def pump(self) -> int:
        """Write every queued inputs body, then commands, statistics and messages that
        changed; returns the inputs frames taken."""
        r, rec, loss = self.remote, self.rec, self.loss
        n = 0
        while r.changed("inputs"):
            snap = r.read_inputs()
            loss.feed(r.read_seq["inputs"], int(snap.frame))
            rec.feed_inputs(snap)
            n += 1
        rec.poll(inputs=False)
        return n

    def close(self):
        """Write ``pfma.link`` and close the recorder; returns its counters."""
        self.pump()
        self.rec.w.add_metadata("pfma.link", self.loss.metadata(self.url))
        return self.rec.close()


def record_remote(path: str, url: str, *, rack_arg: str = "fake", json_every: int = 1, flush_s: float = 0.25,
                  wait_s: float | None = None, done: Callable[[], bool], say: Callable[[str], None],
                  summary: Callable[[str, object], str]) -> int:
    """The remote recording loop of ``pfma record``; returns the exit code.

    :param done: true when the recording should end (Ctrl-C, SIGTERM, --duration)
    :param summary: the recorder's summary line (``pfma record``'s own)
    """
    from bit3.seqlock import Bit3Error, LayoutMismatchError
    from pfma.rack import load_rack
    from tools.bridge.address import remote_target
    from tools.recording import Recorder
    target = remote_target(url)
    assert target is not None
    endpoint, name = target
    rack = load_rack(rack_arg)
    t0 = time.monotonic()
    said = False
    remote = None
    while remote is None:
        left = None if wait_s is None else wait_s - (time.monotonic() - t0)
        try:
            remote = RemoteBuffer.connect(endpoint, name, rack=rack_arg, queue_inputs=True,
                                          timeout_s=max(0.1, round(min(5.0, left), 1)) if left is not None else 5.0)
        except LayoutMismatchError as err:
            log.error("%s; nothing recorded", err)
            return 1
        except Bit3Error as err:
            if done() or (wait_s is not None and time.monotonic() - t0 >= wait_s):
                log.error("%s; nothing recorded", err)
                return 1
            if not said:
                say(f"waiting for the bridge of {url} ({err}; Ctrl-C gives up)")
                said = True
    try:
        rec = Recorder(remote, path, rack=rack, json_every=json_every, flush_every_s=flush_s,
                       meta={"command": " ".join(sys.argv), "source": url})
    except BaseException:
        remote.close()
        raise
    run = RemoteRecording(remote, rec, url)
    say(f"recording {url} to {path} (Ctrl-C ends it)")
    idle_since = time.monotonic()
    warned = False
    try:
        while not done():
            if run.pump():
                idle_since = time.monotonic()
                if warned:
                    say(f"inputs from {url} again (frame {run.loss._frame})")
                warned = False
                continue
            if not warned and time.monotonic() - idle_since > STALE_S:
                say(f"no inputs from {url} for {STALE_S:g} s (link or service down?); still listening")
                warned = True
            time.sleep(DRAIN_S)
    finally:
        try:
            c = run.close()
        finally:
            remote.close()
        print(summary(path, c), flush=True)
        print(run.loss.line(url), flush=True)
    return 0
