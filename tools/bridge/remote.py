"""The far side of the bridge: :class:`RemoteBuffer` reads the areas a bridge publishes
with the read API of :class:`bit3.client.Client`, :class:`RemoteCommander` writes the
command area through it (one remote writer, docs/bridge.md).

Reads are the newest body received: ``read_inputs()`` refreshes and returns the same
:class:`Snapshot` each call, like a local client's. Zenoh's callbacks only store the
bytes; decoding happens in the caller's thread.
"""

from __future__ import annotations

import json
import secrets
import time
from collections import deque
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from bit3.buffer import HeaderInfo, Message, decode_messages
from bit3.client import QUEUES, Snapshot
from bit3.layout import MAGIC, Layout, ServiceState, build_layout, default_layout
from bit3.seqlock import Bit3Error, LayoutMismatchError, OwnershipError
from pfma.rack import load_rack
from tools.bridge.bridge import AREAS, NONCE_SEP, STAMPED, seq_of, writer_name, writer_of
from tools.bridge.consistency import BodyCheck
from tools.bridge.session import CREDENTIALS_ENV, check_name, key

#: how long a first body or the layout is waited for, s (bounded: then a clear error)
DEFAULT_TIMEOUT_S = 5.0
#: inputs bodies a ``queue_inputs`` reader may fall behind (about 25 s at 320 Hz)
MAX_QUEUE = 8192
_POLL_S = 0.002
#: how long a new remote writer asks a bridge whose layout answered for its writer key before
#: it says the bridge takes no commands, s (assumption: a bridge declares both within
#: milliseconds of each other; 2 s also covers a loaded host)
WRITER_QUERY_WAIT_S = 2.0


def _local_layout(rack: str | Path | None) -> Layout:
    return build_layout(load_rack(rack)) if rack not in (None, "fake", "default") else default_layout()


class RemoteBuffer:
    """The areas of buffer ``name`` as a bridge publishes them on ``session``.

    The bridge's published layout (``pfma/<name>/layout``) decides: its hash must be the
    one this side builds from ``rack`` (the same rack file), or :class:`LayoutMismatchError`.

    :param queue_inputs: keep every inputs body received, in order (at most ``max_queue``),
        and let ``changed("inputs")``/``read_inputs()`` step through them one by one, as a
        local reader polling fast enough sees every publish; each snapshot's ``seq`` is the
        service's sequence number the bridge attached, so a gap in it is a lost publish.
        Without it (the default) a read is the newest body.
    """

    def __init__(self, session: Any, name: str, *, rack: str | Path | None = None,
                 timeout_s: float = DEFAULT_TIMEOUT_S, queue_inputs: bool = False,
                 max_queue: int = MAX_QUEUE) -> None:
        self.session = session
        self.name = check_name(name)
        self.timeout_s = timeout_s
        self.published_layout = self._fetch_layout()
        self.layout = _local_layout(rack)
        if self.published_layout.get("hash") != self.layout.hash_hex:
            raise LayoutMismatchError(
                f"the bridge of {name} publishes layout {self.published_layout.get('hash')} "
                f"(rack {self.published_layout.get('rack')}); this side builds "
                f"{self.layout.hash_hex} (rack {self.layout.rack_name}): give the same --rack")
        #: the newest body of each area and the sequence number the bridge attached to it
        #: (None from a bridge that attaches none): one tuple, replaced whole by the callback
        self._bodies: dict[str, tuple[bytes, int | None]] = {}
        self._counts: dict[str, int] = {a: 0 for a in AREAS}
        self._sizes = {a: self.layout.area(a).body_size for a in AREAS}
        #: bodies received on an area's key that are not of its size (truncated, oversized,
        #: or not this layout's), by area: dropped, never decoded
        self.rejected: dict[str, int] = {}
        self._snaps: dict[str, Snapshot] = {}
        self._seen: dict[str, int] = {a: 0 for a in AREAS}
        #: the sequence number the bridge attached to the body each area's last read
        #: returned (None: none attached; the snapshot's ``seq`` then counts bodies)
        self.read_seq: dict[str, int | None] = {a: None for a in AREAS}
        self._cursor = {q: 0 for q in QUEUES.values()}
        self._own_session = False
        #: every inputs body in arrival order, for a tool that must see each frame (the
        #: recorder, the scope): ``changed("inputs")``/``read_inputs()`` then step through it
        self._queue: deque[tuple[bytes, int | None]] | None = deque() if queue_inputs else None
        self.max_queue = max_queue
        self.queue_dropped = 0  #: inputs bodies not queued (the reader fell max_queue behind)
        #: what tools print as the buffer's name (``client.buffer.name``), the message
        #: queues' newest sequence numbers (``client.buffer.queue(area).head_seq``, the
        #: recorder) and, once connected by :meth:`connect`, ``url``: the
        #: ``zenoh://HOST:PORT/NAME`` another tool would be given to read the same buffer
        self.buffer = SimpleNamespace(name=name, queue=self._queue_head, url=None)
        #: bodies of the right size whose writer or sequence is not the bridge's: rejected,
        #: counted (``check.rejected``) and said once per episode (``check.notes``)
        self.check = BodyCheck(name)
        self._publishers = session.liveliness().declare_subscriber(
            key(name, "publisher", "*"), self._on_publisher, history=True)
        self._sub = session.declare_subscriber(key(name, "*"), self._on_body)

    @classmethod
    def connect(cls, endpoint: str, name: str, *, rack: str | Path | None = None,
                timeout_s: float = DEFAULT_TIMEOUT_S, queue_inputs: bool = False) -> "RemoteBuffer":
        """Open a peer session connected to ``endpoint`` (``tcp/HOST:PORT``) that this
        object owns and closes. Close it (``with``) before the interpreter exits: with
        zenoh 1.10.2 a process that exits with a connected session and a subscriber
        still open does not terminate (seen here)."""
        from tools.bridge.session import open_session
        session = open_session(connect=[endpoint])
        try:
            r = cls(session, name, rack=rack, timeout_s=timeout_s, queue_inputs=queue_inputs)
        except BaseException:
            session.close()
            raise
        r._own_session = True
        r.buffer.url = f"zenoh://{endpoint[len('tcp/'):]}/{name}"
        return r

    def _fetch_layout(self) -> dict:
        """The bridge's layout, asked again until ``timeout_s`` (a bridge or a link that
        comes up a little later is waited for, bounded)."""
        end = time.monotonic() + self.timeout_s
        while True:
            left = end - time.monotonic()
            for reply in self.session.get(key(self.name, "layout"), timeout=max(0.05, min(0.5, left))):
                if reply.ok is not None:
                    return self._layout_document(reply.ok.payload.to_bytes())
            if time.monotonic() >= end:
                raise Bit3Error(f"no bridge publishes buffer {self.name!r} (no answer on "
                                f"{key(self.name, 'layout')} within {self.timeout_s:g} s; a bridge "
                                f"started with --users takes only peers with its credentials: "
                                f"${CREDENTIALS_ENV})")
            time.sleep(0.05)

    def _layout_document(self, data: bytes) -> dict:
        """The layout a bridge answered, or a one-line Bit3Error (anything on the network
        may answer on the layout's key)."""
        try:
            doc = json.loads(data)
        except ValueError as err:
            raise Bit3Error(f"the answer on {key(self.name, 'layout')} is not a layout document "
                            f"({len(data)} bytes, not JSON: {err})") from None
        if not isinstance(doc, dict) or not isinstance(doc.get("hash"), str):
            raise Bit3Error(f"the answer on {key(self.name, 'layout')} is not a layout document "
                            f"(no layout hash in it)")
        return doc

    def _on_publisher(self, sample: Any) -> None:
        import zenoh
        self.check.token(str(sample.key_expr).rsplit("/", 1)[-1], sample.kind == zenoh.SampleKind.PUT)

    def _on_body(self, sample: Any) -> None:
        area = str(sample.key_expr).rsplit("/", 1)[-1]
        if area in self._counts:
            if len(sample.payload) != self._sizes[area]:
                # not a body of this layout (any peer may publish on the key): never decoded
                self.rejected[area] = self.rejected.get(area, 0) + 1
                return
            got = (sample.payload.to_bytes(), seq_of(sample))
            if not self.check.take(area, got[1], writer_of(sample), got[0]):
                return  # not the bridge's writer, or a sequence number it cannot have sent
            self._bodies[area] = got
            if area == "inputs" and self._queue is not None:
                if len(self._queue) < self.max_queue:
                    self._queue.append(got)
                else:
                    self.queue_dropped += 1
            self._counts[area] += 1

    # --- the read API of bit3.client.Client ----------------------------------------------

    def received(self, area: str) -> int:
        """Bodies of ``area`` received so far."""
        return self._counts[area]

    def wait(self, area: str = "inputs", count: int = 1, timeout_s: float | None = None) -> None:
        """Wait (bounded) until ``count`` bodies of ``area`` have been received in all."""
        end = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while self._counts[area] < count:
            if time.monotonic() > end:
                raise Bit3Error(f"no {area} body from the bridge of {self.name!r} within "
                                f"{self.timeout_s if timeout_s is None else timeout_s:g} s")
            time.sleep(_POLL_S)

    def _ask(self, area: str) -> None:
        """Ask the bridge for the newest body of ``area`` (a late joiner: the area may not
        change again for a long time)."""
        for reply in self.session.get(key(self.name, area), timeout=self.timeout_s):
            if reply.ok is not None and not self._counts[area]:
                if len(reply.ok.payload) != self._sizes[area]:
                    self.rejected[area] = self.rejected.get(area, 0) + 1
                    continue
                body, seq = reply.ok.payload.to_bytes(), seq_of(reply.ok)
                if not self.check.take(area, seq, writer_of(reply.ok), body):
                    continue
                self._bodies[area] = (body, seq)
                self._counts[area] += 1

    def read(self, area: str) -> Snapshot:
        """The newest body received (the first one asked of the bridge, bounded); with
        ``queue_inputs``, the oldest inputs body not read yet while there is one."""
        if area not in self._counts:
            raise Bit3Error(f"area {area!r} is not published by the bridge; areas: {', '.join(AREAS)}")
        if area == "inputs" and self._queue:
            body, seq = self._queue.popleft()
            n = self._counts[area] - len(self._queue)
        else:
            body, seq = self._newest(area)
            n = self._counts[area]
        snap = self._snap(area)
        snap.record[...] = np.frombuffer(body, dtype=snap.record.dtype, count=1)[0]
        snap.seq = 2 * n if seq is None else seq
        self.read_seq[area] = seq
        self._seen[area] = n
        return snap

    def _newest(self, area: str) -> tuple[bytes, int | None]:
        if not self._counts[area]:
            self._ask(area)
        if not self._counts[area]:
            self.wait(area)
        return self._bodies[area]

    def _snap(self, area: str, name: str | None = None) -> Snapshot:
        key_ = name or area
        snap = self._snaps.get(key_)
        if snap is None:
            spec = self.layout.area(area)
            assert spec.body_dtype is not None
            snap = self._snaps[key_] = Snapshot(np.zeros((), spec.body_dtype), area, self.layout)
        return snap

    def _peek(self, area: str) -> Snapshot:
        """The newest body, decoded into a snapshot of its own (a queued inputs reader's
        place in the queue does not move)."""
        body, _ = self._newest(area)
        snap = self._snap(area, area + "/peek")
        snap.record[...] = np.frombuffer(body, dtype=snap.record.dtype, count=1)[0]
        return snap

    def _queue_head(self, area: str) -> SimpleNamespace:
        """``buffer.queue(area).head_seq``: the newest message's sequence number."""
        return SimpleNamespace(head_seq=int(self._peek(area).record["head_seq"]))

    def read_inputs(self) -> Snapshot:
        return self.read("inputs")

    def read_stats(self) -> Snapshot:
        return self.read("stats")

    def read_commands(self) -> Snapshot:
        return self.read("commands")

    def changed(self, area: str = "inputs") -> bool:
        """A body newer than the last ``read(area)`` has arrived (with ``queue_inputs``:
        an inputs body is waiting in the queue)."""
        if area == "inputs" and self._queue is not None:
            return bool(self._queue)
        return self._counts[area] != self._seen[area]

    @property
    def service_state(self) -> int:
        return int(self._peek("inputs").record["service_state"])

    def header(self) -> HeaderInfo:
        """The header as far as the bridge publishes it: layout, rack, and the service
        state and frame from the newest inputs body; owners, calibration hash and
        creation time are not published (empty, 0)."""
        snap = self._peek("inputs")
        pub = self.published_layout
        return HeaderInfo(MAGIC, int(pub.get("version", 0)), int(pub.get("size", 0)),
                          bytes.fromhex(pub.get("hash", "")), b"", 0,
                          ServiceState(snap.service_state), int(snap.frame), float(snap.t_s),
                          str(pub.get("rack", "")), ())

    def owners(self) -> dict:
        """Owner slots are host-local (pids): not published; empty."""
        return {}

    def messages(self, since_seq: int = 0, queue: str = "service", *, wait: bool = True) -> list[Message]:
        """The messages of ``queue`` after ``since_seq``. With ``wait`` (a tool's first look)
        a queue not received yet is asked of the bridge and waited for, bounded by
        ``timeout_s`` twice over (then :class:`Bit3Error`); without it (a control loop's
        look, :class:`RemoteClient`) such a queue is [] at once: nothing received yet."""
        area = QUEUES.get(queue, queue)
        if not wait and area in self._counts and not self._counts[area]:
            return []
        return decode_messages(area, self.read(area).record, since_seq)

    def new_messages(self) -> list[Message]:
        out: list[Message] = []
        for q in QUEUES.values():
            if not self._counts[q]:
                continue
            got = decode_messages(q, self.read(q).record, self._cursor[q])
            if got:
                self._cursor[q] = got[-1].seq
            out += got
        out.sort(key=lambda m: (m.t_s, m.queue, m.seq))
        return out

    def close(self) -> None:
        if self._sub is not None:
            self._sub.undeclare()
            self._sub = None
            self._publishers.undeclare()
            if self._own_session:
                self.session.close()

    def __enter__(self) -> "RemoteBuffer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RemoteCommander:
    """The one remote writer of buffer ``name``'s command area, through a bridge started
    with ``--commands``.

    On creation it asks the bridge (``pfma/<name>/writer/commands``) and the liveliness
    tokens ``pfma/<name>/writer/commands/*`` who holds the command area: someone does ->
    :class:`OwnershipError` naming them; else it declares its own token
    (``.../<owner>~<nonce>``: its name and a nonce of its own, also in every body's attachment;
    ``tools.bridge.bridge.NONCE_SEP``), which dies with its session (lost link: after the lease).
    ``write_commands`` takes the keys of :meth:`bit3.client.Client.write_commands`; every
    write is a new heartbeat at the bridge. Without ``inputs_frame`` a write says it used
    the newest inputs this side has received (an open-loop writer).
    """

    def __init__(self, remote: RemoteBuffer, owner: str) -> None:
        self.remote = remote
        self.owner = check_name(owner, "writer name")
        #: this writer's identity at the bridge: a body is written only while it matches the token
        self.ident = f"{self.owner}{NONCE_SEP}{secrets.token_hex(4)}"
        s = remote.session
        name = remote.name
        holder: str | None = None
        asked = False
        # asked again for a while: a bridge that has just started answers its layout a moment
        # before its writer key (the kill matrix met that window once in 100 bridge restarts)
        end = time.monotonic() + min(remote.timeout_s, WRITER_QUERY_WAIT_S)
        while not asked:
            left = end - time.monotonic()
            for reply in s.get(key(name, "writer", "commands"), timeout=max(0.05, min(0.5, left))):
                if reply.ok is not None:
                    try:
                        said = json.loads(reply.ok.payload.to_bytes())
                    except ValueError:
                        said = None
                    if not isinstance(said, dict):
                        raise Bit3Error(f"the answer on {key(name, 'writer', 'commands')} is not the "
                                        f"bridge's (not a JSON object): is something else publishing there?")
                    asked = True
                    h = said.get("holder")
                    holder = h if isinstance(h, str) else None
            if asked or time.monotonic() >= end:
                break
            time.sleep(0.05)
        if not asked:
            raise Bit3Error(f"the bridge of {name} answered its layout but not its command writer key "
                            f"within {min(remote.timeout_s, WRITER_QUERY_WAIT_S):g} s: it takes no "
                            f"commands (start it with --commands), or it stalled (try again)")
        for reply in s.liveliness().get(key(name, "writer", "commands", "*"), timeout=remote.timeout_s):
            if reply.ok is not None and holder is None:
                holder = writer_name(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        if holder is not None:
            raise OwnershipError(f"the command area of {name} is held by remote writer "
                                 f"{holder!r}; one writer at a time")
        self._token = s.liveliness().declare_token(key(name, "writer", "commands", self.ident))
        self._pub = s.declare_publisher(key(name, "commands", "set"))
        spec = remote.layout.area("commands")
        assert spec.body_dtype is not None
        self.raw = bytearray(spec.body_size)
        self.command: np.ndarray = np.ndarray((), spec.body_dtype, buffer=self.raw)
        # carry on from what the command area holds, as a local writer does: above all its
        # re-arm counter, which the service takes once only (a second writer starting from
        # zero could never arm again), and the heartbeat
        try:
            body, _ = remote._newest("commands")
            self.raw[:] = body[:len(self.raw)]
        except Bit3Error:  # the bridge has published no command body (no controller yet)
            pass
        self._heartbeat = int(self.command["heartbeat"])

    def write_commands(self, **fields: Any) -> int:
        """Set command fields (others keep their values) and publish the body."""
        rec = self.command
        names = rec.dtype.names or ()
        for k, v in fields.items():
            if k in STAMPED and k != "inputs_frame":
                raise Bit3Error(f"command field {k!r} is stamped at the bridge")
            if k in names:
                rec[k] = v
                continue
            try:
                c = self.remote.layout.channel(k, "commands")
            except KeyError:
                raise Bit3Error(f"no command field or DAC command channel {k!r}") from None
            rec[c.fields[0][0]][c.fields[0][1]] = v
        if "inputs_frame" not in fields:
            rec["inputs_frame"] = int(self.remote._peek("inputs").frame) if self.remote.received("inputs") else 0
        self._heartbeat += 1
        rec["heartbeat"] = self._heartbeat
        rec["t_s"] = time.time()
        self._pub.put(bytes(self.raw), attachment=self.ident.encode())
        return self._heartbeat

    def close(self) -> None:
        """Stop writing and give the token back (the bridge then writes nothing more)."""
        if self._token is not None:
            self._token.undeclare()
            self._pub.undeclare()
            self._token = None


class RemoteClient:
    """The :class:`bit3.client.Client` API a controller uses, over a bridge started with
    ``--commands``: reads from a :class:`RemoteBuffer` (the newest bodies), command writes
    through a :class:`RemoteCommander` (the one remote writer). So
    ``ControllerRuntime(RemoteClient.connect("tcp/rack:7447", "pfma", "ops-ctl"), ...)`` runs
    the controller on another host, the service's watchdog and limits unchanged.

    ``role`` is ``"remote"``: the controller then neither claims the Bit3 controller
    statistics area nor posts to the controller message queue (both are the bridge's on
    the rack; its own messages stay in its world model and log).

    A real-time controller connects first and then calls ``ioservice.loop.realtime_setup``
    (which sets the calling thread only): zenoh's threads, started by the connect, then keep
    SCHED_OTHER and every CPU instead of inheriting SCHED_FIFO on the loop's one CPU. In the
    100-trial kill matrix, a far end set up the other way round once did not end within 15 s
    of SIGTERM (its session close hung); whether the inherited policy was the cause is not
    proven.
    """

    role = "remote"

    def __init__(self, remote: RemoteBuffer, commander: RemoteCommander) -> None:
        self.remote = remote
        self.commander = commander
        self.layout = remote.layout
        self.buffer = remote.buffer

    @classmethod
    def connect(cls, endpoint: str, name: str, owner: str, *, rack: str | Path | None = None,
                timeout_s: float = DEFAULT_TIMEOUT_S) -> "RemoteClient":
        """Its own session to ``endpoint``; refused (:class:`OwnershipError`) while another
        remote writer holds the command area."""
        remote = RemoteBuffer.connect(endpoint, name, rack=rack, timeout_s=timeout_s)
        try:
            return cls(remote, RemoteCommander(remote, owner))
        except BaseException:
            remote.close()
            raise

    @property
    def command(self) -> np.ndarray:
        """The command record this side writes (``Client.command``)."""
        return self.commander.command

    def write_commands(self, **fields: Any) -> int:
        return self.commander.write_commands(**fields)

    def read_inputs(self) -> Snapshot:
        return self.remote.read_inputs()

    def read_stats(self) -> Snapshot:
        return self.remote.read_stats()

    def read_commands(self) -> Snapshot:
        return self.remote.read_commands()

    def changed(self, area: str = "inputs") -> bool:
        return self.remote.changed(area)

    def messages(self, since_seq: int = 0, queue: str = "service") -> list[Message]:
        """Never blocks (the controller reads it inside its frame): a queue the bridge has
        not sent yet is [] (a lost link once held a remote controller's frame here for
        twice the connect time-out, deaf to SIGTERM, in the kill matrix)."""
        return self.remote.messages(since_seq, queue, wait=False)

    def header(self) -> HeaderInfo:
        return self.remote.header()

    def close(self) -> None:
        self.commander.close()
        self.remote.close()

    def __enter__(self) -> "RemoteClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
