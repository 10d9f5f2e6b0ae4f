"""The far side of the bridge: :class:`RemoteBuffer` reads the areas a bridge publishes
with the read API of :class:`bit3.client.Client`, :class:`RemoteCommander` writes the
command area through it (one remote writer, docs/bridge.md).

Reads are the newest body received: ``read_inputs()`` refreshes and returns the same
:class:`Snapshot` each call, like a local client's. Zenoh's callbacks only store the
bytes; decoding happens in the caller's thread.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from types import SimpleNamespace

from bit3.buffer import HeaderInfo, Message, decode_messages
from bit3.client import QUEUES, Snapshot
from bit3.layout import MAGIC, Layout, ServiceState, build_layout, default_layout
from bit3.seqlock import Bit3Error, LayoutMismatchError, OwnershipError
from pfma.rack import load_rack
from tools.bridge.bridge import AREAS, STAMPED
from tools.bridge.session import check_name, key

#: how long a first body or the layout is waited for, s (bounded: then a clear error)
DEFAULT_TIMEOUT_S = 5.0
_POLL_S = 0.002


def _local_layout(rack: str | Path | None) -> Layout:
    return build_layout(load_rack(rack)) if rack not in (None, "fake", "default") else default_layout()


class RemoteBuffer:
    """The areas of buffer ``name`` as a bridge publishes them on ``session``.

    The bridge's published layout (``pfma/<name>/layout``) decides: its hash must be the
    one this side builds from ``rack`` (the same rack file), or :class:`LayoutMismatchError`.
    """

    def __init__(self, session: Any, name: str, *, rack: str | Path | None = None,
                 timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
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
        self._bodies: dict[str, bytes] = {}
        self._counts: dict[str, int] = {a: 0 for a in AREAS}
        self._snaps: dict[str, Snapshot] = {}
        self._seen: dict[str, int] = {a: 0 for a in AREAS}
        self._cursor = {q: 0 for q in QUEUES.values()}
        self._own_session = False
        #: what tools print as the buffer's name (``client.buffer.name``)
        self.buffer = SimpleNamespace(name=name)
        self._sub = session.declare_subscriber(key(name, "*"), self._on_body)

    @classmethod
    def connect(cls, endpoint: str, name: str, *, rack: str | Path | None = None,
                timeout_s: float = DEFAULT_TIMEOUT_S) -> "RemoteBuffer":
        """Open a peer session connected to ``endpoint`` (``tcp/HOST:PORT``) that this
        object owns and closes. Close it (``with``) before the interpreter exits: with
        zenoh 1.10.2 a process that exits with a connected session and a subscriber
        still open does not terminate (seen here)."""
        from tools.bridge.session import open_session
        session = open_session(connect=[endpoint])
        try:
            r = cls(session, name, rack=rack, timeout_s=timeout_s)
        except BaseException:
            session.close()
            raise
        r._own_session = True
        return r

    def _fetch_layout(self) -> dict:
        """The bridge's layout, asked again until ``timeout_s`` (a bridge or a link that
        comes up a little later is waited for, bounded)."""
        end = time.monotonic() + self.timeout_s
        while True:
            left = end - time.monotonic()
            for reply in self.session.get(key(self.name, "layout"), timeout=max(0.05, min(0.5, left))):
                if reply.ok is not None:
                    return json.loads(reply.ok.payload.to_bytes())
            if time.monotonic() >= end:
                raise Bit3Error(f"no bridge publishes buffer {self.name!r} (no answer on "
                                f"{key(self.name, 'layout')} within {self.timeout_s:g} s)")
            time.sleep(0.05)

    def _on_body(self, sample: Any) -> None:
        area = str(sample.key_expr).rsplit("/", 1)[-1]
        if area in self._counts:
            self._bodies[area] = sample.payload.to_bytes()
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
                self._bodies[area] = reply.ok.payload.to_bytes()
                self._counts[area] += 1

    def read(self, area: str) -> Snapshot:
        """The newest body received (the first one asked of the bridge, bounded)."""
        if area not in self._counts:
            raise Bit3Error(f"area {area!r} is not published by the bridge; areas: {', '.join(AREAS)}")
        if not self._counts[area]:
            self._ask(area)
        if not self._counts[area]:
            self.wait(area)
        snap = self._snaps.get(area)
        if snap is None:
            spec = self.layout.area(area)
            assert spec.body_dtype is not None
            snap = self._snaps[area] = Snapshot(np.zeros((), spec.body_dtype), area, self.layout)
        n = self._counts[area]
        body = self._bodies[area]
        snap.record[...] = np.frombuffer(body, dtype=snap.record.dtype, count=1)[0]
        snap.seq = 2 * n
        self._seen[area] = n
        return snap

    def read_inputs(self) -> Snapshot:
        return self.read("inputs")

    def read_stats(self) -> Snapshot:
        return self.read("stats")

    def read_commands(self) -> Snapshot:
        return self.read("commands")

    def changed(self, area: str = "inputs") -> bool:
        """A body newer than the last ``read(area)`` has arrived."""
        return self._counts[area] != self._seen[area]

    @property
    def service_state(self) -> int:
        return int(self.read_inputs().service_state)

    def header(self) -> HeaderInfo:
        """The header as far as the bridge publishes it: layout, rack, and the service
        state and frame from the newest inputs body; owners, calibration hash and
        creation time are not published (empty, 0)."""
        snap = self.read_inputs()
        pub = self.published_layout
        return HeaderInfo(MAGIC, int(pub.get("version", 0)), int(pub.get("size", 0)),
                          bytes.fromhex(pub.get("hash", "")), b"", 0,
                          ServiceState(snap.service_state), int(snap.frame), float(snap.t_s),
                          str(pub.get("rack", "")), ())

    def owners(self) -> dict:
        """Owner slots are host-local (pids): not published; empty."""
        return {}

    def messages(self, since_seq: int = 0, queue: str = "service") -> list[Message]:
        area = QUEUES.get(queue, queue)
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
    (``.../<owner>``), which dies with its session (lost link: after the lease).
    ``write_commands`` takes the keys of :meth:`bit3.client.Client.write_commands`; every
    write is a new heartbeat at the bridge. Without ``inputs_frame`` a write says it used
    the newest inputs this side has received (an open-loop writer).
    """

    def __init__(self, remote: RemoteBuffer, owner: str) -> None:
        self.remote = remote
        self.owner = check_name(owner, "writer name")
        s = remote.session
        name = remote.name
        holder: str | None = None
        asked = False
        for reply in s.get(key(name, "writer", "commands"), timeout=remote.timeout_s):
            if reply.ok is not None:
                asked = True
                holder = json.loads(reply.ok.payload.to_bytes()).get("holder")
        if not asked:
            raise Bit3Error(f"the bridge of {name} takes no commands (start it with --commands)")
        for reply in s.liveliness().get(key(name, "writer", "commands", "*"), timeout=remote.timeout_s):
            if reply.ok is not None and holder is None:
                holder = str(reply.ok.key_expr).rsplit("/", 1)[-1]
        if holder is not None:
            raise OwnershipError(f"the command area of {name} is held by remote writer "
                                 f"{holder!r}; one writer at a time")
        self._token = s.liveliness().declare_token(key(name, "writer", "commands", self.owner))
        self._pub = s.declare_publisher(key(name, "commands", "set"))
        spec = remote.layout.area("commands")
        assert spec.body_dtype is not None
        self.raw = bytearray(spec.body_size)
        self.command: np.ndarray = np.ndarray((), spec.body_dtype, buffer=self.raw)
        self._heartbeat = 0

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
            rec["inputs_frame"] = self.remote.read_inputs().frame if self.remote.received("inputs") else 0
        self._heartbeat += 1
        rec["heartbeat"] = self._heartbeat
        rec["t_s"] = time.time()
        self._pub.put(bytes(self.raw), attachment=self.owner.encode())
        return self._heartbeat

    def close(self) -> None:
        """Stop writing and give the token back (the bridge then writes nothing more)."""
        if self._token is not None:
            self._token.undeclare()
            self._pub.undeclare()
            self._token = None
