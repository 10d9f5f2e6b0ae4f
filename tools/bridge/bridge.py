"""The bridge: a local Bit3 buffer's areas on Zenoh, and the command area back from one
remote writer (docs/bridge.md).

It runs in its own process (``pfma bridge``), outside the service's frame loop: it polls
each area's sequence number and, when it changed, takes a consistent copy through the
area's seqlock reader and publishes the body bytes as they are in shared memory. Rates
follow the areas: inputs and commands every frame, message queues when they change,
the statistics areas at most once a second.

With a command writer (``--commands``) it claims the Bit3 command area as a controller
does, and writes the body the holder of the remote writer's liveliness token publishes,
stamping its own claim, heartbeat and time. No body received -> no new heartbeat -> the
service's watchdog (unchanged) drives 0 V.
"""

from __future__ import annotations

import json
import struct
from typing import Any, Callable

from bit3.buffer import AreaReader
from bit3.client import Client
from bit3.layout import Layout, Severity
from pfma.refusals import RefusalLog
from tools.bridge.session import key

#: areas published (header: host-local pids and locks, its service state is in inputs;
#: spare: reserved zero)
AREAS = ("inputs", "stats", "commands", "service_messages", "controller_messages",
         "controller_stats")
#: the smallest interval between two publications of an area, s (others: on every change).
#: Assumption: 1 s for the statistics, which the service refreshes about that often.
MIN_PERIOD_S = {"stats": 1.0, "controller_stats": 1.0}
#: command fields the bridge stamps itself (the remote's values are not copied)
STAMPED = ("heartbeat", "t_s", "writer_pid", "writer_token", "inputs_frame")
#: remote command writers the bridge keeps track of (liveliness tokens, in order); tokens
#: beyond are counted and ignored, so a peer declaring thousands cannot grow the list.
#: Assumption: a lab has a handful of remote controllers and tools; 16 leaves room.
MAX_WRITERS = 16
#: senders named in their own "refused" message and counted by name in :attr:`Bridge.refused`;
#: later ones are counted together under :data:`OTHER_SENDERS` (a peer that sends under a new
#: name each time cannot flood the message queue or grow the counts)
MAX_NAMED_SENDERS = 8
OTHER_SENDERS = "(other senders)"
#: a sender's name (the command body's Zenoh attachment) as the bridge keeps it, at most
#: this many characters
MAX_SENDER_CHARS = 64
#: a remote writer's identity is its name, this separator and a nonce of its own
#: (``RemoteCommander``: ``ops-laptop~1f2e3d4c``), in its liveliness token's last chunk and in
#: every body's attachment. Names hold no ``~`` (``session.check_name``), so the split is
#: unambiguous; a writer without a nonce (an older client) is its name alone.
#: Why: Zenoh may deliver a writer's token withdrawal before its last bodies (the kill
#: matrix's far end started again under the same name met it: "controller_frame 4 after
#: 1046"); with the nonce such a late body is never taken for the next writer's.
NONCE_SEP = "~"
#: a nonce as the bridge keeps it, at most this many characters
MAX_NONCE_CHARS = 16


def writer_ident(text: str) -> str:
    """A token chunk or body attachment as the bridge keeps it: the name cut at
    :data:`MAX_SENDER_CHARS`, the nonce at :data:`MAX_NONCE_CHARS`."""
    name, sep, nonce = text.partition(NONCE_SEP)
    return name[:MAX_SENDER_CHARS] + sep + nonce[:MAX_NONCE_CHARS]


def writer_name(ident: str) -> str:
    """The name of a writer identity (what messages and counts show)."""
    return ident.partition(NONCE_SEP)[0]
#: refused remote traffic is said in one service message per this interval at most
#: (:class:`pfma.refusals.RefusalLog`), with the counts by reason
REFUSAL_INTERVAL_S = 60.0
#: polls between two looks whether the frame ring was replaced (one ``stat``; ~0.5 s at
#: the CLI's 0.5 ms poll)
RING_CHECK_POLLS = 1000
#: service frames between the safe start written for a new remote writer and the writer's first
#: body (Bridge._safe_start): the frame under way at the write may have read the command area
#: before it, the next one reads it
SAFE_START_FRAMES = 2
#: every published body carries, as its Zenoh attachment, the area's sequence counter at
#: the copy (8 bytes, little-endian): the service bumps it by 2 per publish, so a far side
#: that sees a jump of more than 2 knows publishes were lost on the way (at the bridge or
#: on the link) and a frame-number jump with a step of 2 is a frame the service skipped
SEQ = struct.Struct("<Q")
#: after the sequence number, the attachment carries the bridge's writer identity: its Zenoh
#: session id (ASCII hex), which is also the last chunk of the liveliness token
#: ``pfma/<buffer>/publisher/<id>`` it declares; readers take only bodies of the first live
#: publisher token they saw (tools/bridge/consistency.py, issue 28 item 6)
MAX_WRITER_ID = 64


def seq_of(sample: Any) -> int | None:
    """The area sequence number a bridge attached to ``sample`` (None: none attached)."""
    a = sample.attachment
    if a is None:
        return None
    b = a.to_bytes()
    return SEQ.unpack_from(b)[0] if SEQ.size <= len(b) <= SEQ.size + MAX_WRITER_ID else None


def writer_of(sample: Any) -> str | None:
    """The writer identity a bridge attached after the sequence number (None: none)."""
    a = sample.attachment
    if a is None:
        return None
    b = a.to_bytes()
    if not SEQ.size < len(b) <= SEQ.size + MAX_WRITER_ID:
        return None
    return b[SEQ.size:].decode("ascii", "replace")


def layout_document(layout: Layout) -> bytes:
    """What ``pfma/<buffer>/layout`` answers: the layout JSON (with its hash)."""
    return json.dumps(layout.as_json(), sort_keys=True).encode()


class Bridge:
    """Publishes ``reader``'s buffer on ``session``; with ``commander`` (a :class:`Client`
    holding the command area) takes remote commands.

    :param now: the clock of the statistics' rate cap (the buffer's clock by default)
    :param ring: the service's frame ring (``bit3.ring.FrameRing``, which ``pfma serve``
        keeps): the inputs are then published from it, every frame in order, and the bridge
        may be descheduled for up to ``n_slots - 1`` frames (0.8 s at 320 Hz) without losing
        one; each body's sequence number is the ring's stamp of frame k, 2k + 2 (the area's
        number for the same publish). Without it the inputs area is polled: a poll later
        than the next frame misses that frame (counted in :attr:`missed`).
    """

    def __init__(self, session: Any, name: str, reader: Client, *, commander: Client | None = None,
                 now: Callable[[], float] | None = None, ring: Any = None) -> None:
        self.session = session
        self.name = name
        self.client = reader
        self.layout = reader.layout
        self.commander = commander
        self._now = now or reader.buffer.clock_now
        self._readers: dict[str, AreaReader] = {a: reader.buffer.reader(a) for a in AREAS}
        self._pubs = {a: session.declare_publisher(key(name, a)) for a in AREAS}
        #: this bridge's writer identity (attached to every body after its sequence number)
        #: and its liveliness token, by which readers know it is the publisher
        self.writer_id = str(session.zid())
        self._id = self.writer_id.encode("ascii")
        self._publisher_token = session.liveliness().declare_token(key(name, "publisher", self.writer_id))
        self._last_pub = {a: -float("inf") for a in AREAS}
        self.published = {a: 0 for a in AREAS}  #: bodies published, by area
        #: publishes of the inputs area this bridge did not see (its poll came after the
        #: next one: sequence jumps; the far side sees them as a gap too)
        self.missed = 0
        self.ring = None
        self._ring_k = 0  # the next ring frame to publish
        self._polls = 0
        #: the newest body of each area and its sequence number, answered to a late
        #: joiner's query (a message queue may not change for hours)
        self._last: dict[str, tuple[bytes, int]] = {}
        for a, r in self._readers.items():
            seq = r.read()
            self._last[a] = (bytes(r.raw), seq)
        if ring is not None:
            self.attach_ring(ring)
        self._entities: list[Any] = []
        #: remote writers' identities (:func:`writer_ident`) by the order their tokens
        #: appeared; the first is the holder
        self.writers: list[str] = []
        #: newest (sender, body, holder tokens withdrawn when it came) not yet written
        self._pending: tuple[str, bytes, int] | None = None
        self.applied = 0  #: remote bodies written to the command area
        #: remote command bodies not written, by sender (the first MAX_NAMED_SENDERS; the
        #: rest under OTHER_SENDERS)
        self.refused: dict[str, int] = {}
        #: refused remote traffic by reason, said in one message a minute at most
        self.refusals = RefusalLog(f"bridge {name}", lambda line: self._post(line, Severity.WARNING),
                                   REFUSAL_INTERVAL_S, self._now)
        self._said: set[str] = set()
        self._holder_said = ""
        #: holder tokens withdrawn (Zenoh's thread counts): a remote writer is its name and this
        #: count, so a controller started again under the same name is a new writer
        self._holder_lost = 0
        self._writing: tuple[str, int] | None = None  # the remote writer whose bodies are written
        #: the safe start written and not yet read: (the writer it is for, the service frame then)
        self._safe: tuple[tuple[str, int], int] | None = None
        self._tokens_over = 0  # writer tokens beyond MAX_WRITERS, counted by Zenoh's thread
        self._tokens_said = 0
        self._closed = False
        if commander is not None:
            self._body_size = self.layout.area("commands").body_size
            self._entities.append(session.declare_subscriber(key(name, "commands", "set"), self._on_set))
            self._entities.append(session.liveliness().declare_subscriber(
                key(name, "writer", "commands", "*"), self._on_token, history=True))
            # who holds the command area, as this bridge sees it: a new writer asks first
            # (peers connected only to the bridge do not see each other's tokens)
            self._entities.append(session.declare_queryable(
                key(name, "writer", "commands"),
                lambda q: q.reply(q.key_expr, json.dumps({"holder": self.holder,
                                                          "writers": [writer_name(w) for w in self.writers]
                                                          }).encode())))
        # the areas and then the layout last: a peer that has the layout also gets the writer
        # key (a new remote writer asks it right after the layout; declared after it, a
        # bridge descheduled in between was once taken as one that "takes no commands")
        self._area_q = [session.declare_queryable(key(name, a), self._on_query) for a in AREAS]
        doc = layout_document(self.layout)
        self._layout_q = session.declare_queryable(key(name, "layout"),
                                                   lambda q: q.reply(q.key_expr, doc))
        session.put(key(name, "layout"), doc)

    # --- callbacks (Zenoh's threads): never block, only note -----------------------------

    def _on_set(self, sample: Any) -> None:
        a = sample.attachment
        sender = writer_ident(a.to_bytes()[:4 * (MAX_SENDER_CHARS + MAX_NONCE_CHARS + 1)]
                              .decode("utf-8", "replace")) if a else ""
        # tagged with the holder tokens withdrawn so far: a body that came before its writer's
        # token went is that writer's, never written for a writer after it under the same name
        # (assumption: Zenoh delivers a writer's last body before its token's withdrawal)
        self._pending = (sender, sample.payload.to_bytes(), self._holder_lost)

    def _on_query(self, query: Any) -> None:
        area = str(query.key_expr).rsplit("/", 1)[-1]
        last = self._last.get(area)  # one read: the body and its number together
        if last is not None:
            query.reply(query.key_expr, last[0], attachment=SEQ.pack(last[1]) + self._id)

    def _on_token(self, sample: Any) -> None:
        owner = writer_ident(str(sample.key_expr).rsplit("/", 1)[-1])
        writers = list(self.writers)
        if str(sample.kind).endswith("PUT"):
            if owner not in writers:
                if len(writers) >= MAX_WRITERS:
                    self._tokens_over += 1  # counted; said by the poller (not from Zenoh's thread)
                    return
                writers.append(owner)
        elif owner in writers:
            if writers[0] == owner:
                self._holder_lost += 1  # a writer with the same name later is a new writer
            writers.remove(owner)
        self.writers = writers  # one assignment: the poller sees the old or the new list

    # --- the poll --------------------------------------------------------------------------

    @property
    def holder(self) -> str | None:
        """The name of the remote writer whose commands are written (the first live token)."""
        w = self.writers
        return writer_name(w[0]) if w else None

    def poll(self) -> int:
        """Write a pending remote command body, then publish every area that changed
        (stats at their cap). Returns the number of bodies published."""
        if self.commander is not None:
            self._apply_commands()
            over = self._tokens_over
            if over != self._tokens_said:
                self.refusals.note(f"writer tokens over the limit of {MAX_WRITERS} (ignored)",
                                   over - self._tokens_said)
                self._tokens_said = over
            self.refusals.tick()
        n = self._publish_ring() if self.ring is not None else 0
        t = self._now()
        for area, r in self._readers.items():
            if area == "inputs" and self.ring is not None:
                continue
            if not r.changed() or t - self._last_pub[area] < MIN_PERIOD_S.get(area, 0.0):
                continue
            prev = self._last[area][1]
            seq = r.read()
            if area == "inputs" and prev > 0 and seq - prev > 2:
                self.missed += (seq - prev) // 2 - 1
            body = bytes(r.raw)
            self._last[area] = (body, seq)
            self._pubs[area].put(body, attachment=SEQ.pack(seq) + self._id)
            self._last_pub[area] = t
            self.published[area] += 1
            n += 1
        return n

    def attach_ring(self, ring: Any) -> None:
        """Publish the inputs from ``ring`` from now on, going on after the last frame
        published from the area (the ring's stamp 2k + 2 is the area's sequence number of
        frame k's publish: the numbering goes on without a gap or a repeat)."""
        last_seq = self._last["inputs"][1]
        self._ring_k = max(last_seq // 2, ring.count() - (ring.n_slots - 1), 0)
        self.ring = ring

    def _publish_ring(self) -> int:
        """Publish every whole frame the ring holds beyond the last one published."""
        ring, k = self.ring, self._ring_k
        self._polls += 1
        if self._polls % RING_CHECK_POLLS == 0 and ring.replaced():
            # a restarted service made a new ring (and a new buffer, which this bridge's
            # reader does not follow): from here on, the inputs area as without a ring
            ring.close()
            self.ring = None
            return 0
        count = ring.count()
        if count - k >= ring.n_slots:  # fell a whole ring behind: those frames are gone
            self.missed += count - k - (ring.n_slots - 1)
            k = count - (ring.n_slots - 1)
        n = 0
        pub = self._pubs["inputs"]
        while k < count:
            body = ring.read(k)
            k += 1
            if body is None:  # overwritten while we were reading
                self.missed += 1
                continue
            data = bytes(body)
            self._last["inputs"] = (data, 2 * k)  # k is already the next frame: stamp 2(k-1)+2
            pub.put(data, attachment=SEQ.pack(2 * k) + self._id)
            self.published["inputs"] += 1
            n += 1
        self._ring_k = k
        return n

    def _apply_commands(self) -> None:
        assert self.commander is not None
        w = self.writers
        ident = w[0] if w else None
        holder = writer_name(ident) if ident is not None else None
        self._say_holder(holder)
        got, self._pending = self._pending, None
        if got is None:
            return
        sender, body, gen = got
        if gen != self._holder_lost:
            return  # its writer's token was withdrawn since: a lost writer's last word
        if holder is None:
            # no token seen yet: a writer's first body may overtake its token; keep the
            # newest body until a token decides (a body without a token is never written)
            if self._pending is None:
                self._pending = got
            return
        if sender != ident:
            self._refuse_sender(writer_name(sender), holder)
            return
        if len(body) != self._body_size:
            self._count_refused(holder)
            self.refusals.note(f"command bodies {'shorter' if len(body) < self._body_size else 'longer'} "
                               f"than the layout's {self._body_size} bytes")
            return
        import numpy as np
        rec = self.commander.command
        who = (sender, gen)
        if who != self._writing and not self._safe_start(rec, got, who):
            return
        remote = np.frombuffer(body, dtype=rec.dtype, count=1)[0]
        for f in rec.dtype.names or ():
            if f not in STAMPED:
                rec[f] = remote[f]
        # the remote said which inputs it used; the service judges their age (unchanged)
        self.commander.write_commands(inputs_frame=int(remote["inputs_frame"]))
        self.applied += 1

    def _say_holder(self, holder: str | None) -> None:
        """A message once per change of the command area's remote holder."""
        if (holder or "") != self._holder_said:
            left, self._holder_said = self._holder_said, holder or ""
            self._post(f"bridge: remote command writer {holder!r} holds the command area"
                       if holder else f"bridge: remote command writer {left!r} gone (token "
                       f"withdrawn or its link lost); no remote command writer", Severity.INFO)

    def _refuse_sender(self, name: str, holder: str) -> None:
        """A body from writer ``name``, not the holder: never written; counted, and named in
        a message the first time (up to :data:`MAX_NAMED_SENDERS` names)."""
        if name == holder:  # never written, and not the holder's refusal either
            self.refusals.note("command bodies under the holder's name from another writer (an earlier "
                               "writer's last word after its token went, or a forger)")
            return
        self._count_refused(name)
        if name not in self._said and len(self._said) < MAX_NAMED_SENDERS:
            self._said.add(name)
            self._post(f"bridge: commands from {name!r} refused: the command area is held "
                       f"by remote writer {holder!r}", Severity.WARNING)
        else:
            self.refusals.note("command bodies from a writer that does not hold the command area")

    def _safe_start(self, rec, got: tuple[str, bytes, int], who: tuple[str, int]) -> bool:
        """A new remote writer's first body: first the safe command a Data Acquisition layer
        writes when it starts (0 rates, 0 limits, gripper 0, no arm request,
        ``controller_frame`` 0), published by the bridge and held until the service has read
        it (its frame number moved on by :data:`SAFE_START_FRAMES`), the writer's body kept
        pending meanwhile. Returns True once the writer's bodies may be written.

        Why: the writer's first bodies may have been lost before its token came (its frame 0
        among them), and the service's claim check takes a ``controller_frame`` step back to a
        non-zero value for a second writer, a step back to 0 for a writer started again
        (ioservice/commandcheck.py); the service sees only the bodies it reads, so the safe
        start must be read before the writer's next body replaces it."""
        c = self.commander
        assert c is not None
        frame = c.service_frame
        if self._safe is None or self._safe[0] != who:
            c.write_commands(joint_rate_rad_s=0.0 * rec["joint_rate_rad_s"], current_limit_a=0.0 * rec["current_limit_a"],
                             gripper=0.0, arm_request=0, controller_frame=0)
            self._safe = (who, frame)
        if frame - self._safe[1] < SAFE_START_FRAMES:
            if self._pending is None:  # a newer body that came meanwhile wins
                self._pending = got
            return False
        self._writing, self._safe = who, None
        return True

    def _count_refused(self, sender: str) -> None:
        who = sender if sender in self.refused or len(self.refused) < MAX_NAMED_SENDERS else OTHER_SENDERS
        self.refused[who] = self.refused.get(who, 0) + 1

    def _post(self, text: str, severity: Severity) -> None:
        if self.commander is not None:
            self.commander.post_message(text, severity)

    def close(self) -> None:
        """Say what was refused and not said yet; undeclare everything (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if self.commander is not None:
            self.refusals.flush()
        for e in self._entities:
            e.undeclare()
        self._entities.clear()
        for p in self._pubs.values():
            p.undeclare()
        self._pubs.clear()
        self._layout_q.undeclare()
        self._publisher_token.undeclare()
        for q in self._area_q:
            q.undeclare()
        self._area_q.clear()
