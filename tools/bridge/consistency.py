"""What a remote reader takes as the bridge's bodies (issue 28 item 6).

Any peer that reaches a reader's session may publish on ``pfma/<buffer>/inputs`` (a mesh,
a router, a reader that listens). Bodies of the wrong size are dropped already
(``RemoteBuffer.rejected``); this module rejects bodies of the right size whose **writer
identity** or **sequence** is not the bridge's:

- **writer**: a bridge attaches, after the area's 8-byte sequence number, its Zenoh
  session id (``bridge.WRITER_ID``) and declares the liveliness token
  ``pfma/<buffer>/publisher/<id>``. Once a reader has seen such a token, it takes only
  bodies whose attached id is the **first** live publisher token it saw (a second token,
  a body with another id or none: rejected). Before any token (an older bridge that
  declares none), bodies are taken on their sequence alone.
- **sequence**: per area, a body's sequence number must be above the last one taken
  (the service bumps it by 2 per publish; a repeat is taken only with the same bytes: the
  late joiner's query reply and the publication of one body), and at most
  ``2 * MAX_FRAME_RATE_HZ`` per second since that one, plus :data:`SEQ_SLACK`, ahead
  (a body claiming to be 10^12 publishes later is not the bridge's).
- **restart**: a service or bridge that starts again starts its numbers again. After
  :data:`RESYNC_BODIES` consecutive bodies of an area rejected for their sequence (none
  taken in between: nobody else's stream is being taken), the next is taken as the new
  start, and said.

Each kind of rejection is said once per episode (a log warning and :attr:`BodyCheck.notes`,
naming area, numbers and ids); an episode ends after :data:`EPISODE_QUIET_S` without that
kind. Every rejected body is counted (:attr:`BodyCheck.rejected`, by area and kind).

What it does not stop: a peer that copies the bridge's id (it is in the token's key) and
publishes numbers just above the bridge's is taken until the bridge's next bodies, which
then look old; that is what Zenoh's authentication and access control are for
(docs/bridge.md, "Authentication and access control").
"""

from __future__ import annotations

import logging
import time
from typing import Callable

__all__ = ["BodyCheck", "MAX_FRAME_RATE_HZ", "SEQ_SLACK", "RESYNC_BODIES", "EPISODE_QUIET_S"]

log = logging.getLogger("pfma.bridge.remote")

#: the fastest service frame rate (``pfma serve --frame-rate`` takes at most 5000 Hz): the
#: sequence number of the inputs area moves by at most twice that per second
MAX_FRAME_RATE_HZ = 5000.0
#: sequence steps always allowed on top (assumption: 2 x the frame ring's 1024 frames, so a
#: bridge catching up from its ring after a stall of the reader is never refused)
SEQ_SLACK = 2 * 1024
#: consecutive bodies of an area rejected for their sequence, none taken between, after
#: which the next is taken as a restarted stream (assumption: 64 bodies = 0.2 s at 320 Hz)
RESYNC_BODIES = 64
#: a kind of rejection is said again after this long without one, s
EPISODE_QUIET_S = 5.0
#: notes kept (the newest)
MAX_NOTES = 100
#: publisher tokens tracked; more are ignored (a token flood cannot grow the set)
MAX_PUBLISHERS = 16


class BodyCheck:
    """Decides, body by body, whether a reader takes what arrived on an area's key."""

    def __init__(self, name: str, now: Callable[[], float] = time.monotonic) -> None:
        self.name = name
        self._now = now
        #: live publisher tokens in the order they appeared; the first is the bridge
        self.publishers: list[str] = []
        self.publisher_seen = False
        self._last: dict[str, tuple[int, float, bytes]] = {}  # area -> (seq, time, body) taken
        self._run: dict[str, int] = {}  # area -> sequence rejections since the last body taken
        self._episode: dict[tuple[str, str], float] = {}  # (area, kind) -> last rejection time
        #: bodies rejected, by (area, kind): kind "writer", "backwards", "jump"
        self.rejected: dict[tuple[str, str], int] = {}
        #: what was said, one line per episode (the newest MAX_NOTES)
        self.notes: list[str] = []

    # --- liveliness (Zenoh's thread) -------------------------------------------------------

    def token(self, ident: str, alive: bool) -> None:
        if alive:
            self.publisher_seen = True
            if ident not in self.publishers and len(self.publishers) < MAX_PUBLISHERS:
                self.publishers.append(ident)
        elif ident in self.publishers:
            self.publishers.remove(ident)

    # --- bodies ----------------------------------------------------------------------------

    def take(self, area: str, seq: int | None, writer: str | None, body: bytes) -> bool:
        """True: the reader takes ``body``; False: rejected (counted, said once per episode)."""
        if self.publisher_seen:
            holder = self.publishers[0] if self.publishers else None
            if writer is None or writer != holder:
                self._reject(area, "writer", f"{self._key(area)}: body from writer {writer or '(none)'}, "
                                             f"not the bridge's liveliness token {holder or '(none live)'}")
                return False
        if seq is None:
            return True  # a bridge that attaches no numbers: nothing to check them against
        now = self._now()
        last = self._last.get(area)
        if last is not None:
            lseq, lt, lbody = last
            step = seq - lseq
            if step == 0 and body == lbody:
                return True  # the same body again (a query's reply and its publication)
            allowed = 2.0 * MAX_FRAME_RATE_HZ * max(0.0, now - lt) + SEQ_SLACK
            why = None
            if step <= 0:
                why = ("backwards", f"{self._key(area)}: seq {seq} after {lseq}")
            elif step > allowed:
                why = ("jump", f"{self._key(area)}: seq {seq} after {lseq}: +{step} in {now - lt:.3f} s "
                               f"(at most +{allowed:.0f})")
            if why is not None:
                run = self._run.get(area, 0) + 1
                if run < RESYNC_BODIES:
                    self._run[area] = run
                    self._reject(area, *why)
                    return False
                self._say(f"{self._key(area)}: sequence restarted at {seq} ({run - 1} bodies rejected "
                          f"before it, none taken)")
        self._run[area] = 0
        self._last[area] = (seq, now, body)
        return True

    def _key(self, area: str) -> str:
        return f"pfma/{self.name}/{area}"

    def _reject(self, area: str, kind: str, text: str) -> None:
        k = (area, kind)
        self.rejected[k] = self.rejected.get(k, 0) + 1
        now = self._now()
        last = self._episode.get(k)
        self._episode[k] = now
        if last is None or now - last > EPISODE_QUIET_S:
            self._say(f"rejected {text}")

    def _say(self, text: str) -> None:
        log.warning("%s", text)
        self.notes.append(text)
        del self.notes[:-MAX_NOTES]
