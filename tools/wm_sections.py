"""A distributed controller's world-model sections over Zenoh (across hosts).

``controller/distributed.py`` imports the other processes' sections at each communications
segment. On one host it reads their world models in shared memory; across hosts (a
distribution file with ``transport = "zenoh"`` or ``listen``/``connect`` endpoints) each
process publishes its section after its frame and subscribes to the others':

* key ``pfma/wm/<BASE>/<process>``; payload ``controller.distributed.PAYLOAD_HEADER`` (the
  world model's layout signature, the owner's communications-segment count) then the
  section's bytes (``Section.pack``: the owned variables' ranges of the body, in body order);
* a subscriber keeps the newest whole payload (one reference, replaced whole by Zenoh's
  callback thread), which the importer takes at its next communications segment; a
  payload of another layout is refused with a message naming the process;
* the session is the bridge's (``tools.bridge.session``): peer mode, explicit endpoints,
  multicast scouting off, a 1 s lease; with no endpoints in the file the first process
  listens on ``tcp/127.0.0.1:DEFAULT_ZENOH_PORT`` and the others connect to it (loopback).
"""

from __future__ import annotations

from typing import Any

from controller.distributed import PAYLOAD_HEADER, DistributedConfig, DistributedProcess
from tools.bridge.session import check_name, open_session


def section_key(base: str, process: str) -> str:
    return f"pfma/wm/{base}/{process}"


class ZenohSource:
    """The newest section of one remote process received over Zenoh."""

    packed = True

    def __init__(self, session: Any, base: str, process: str, signature: bytes, size: int) -> None:
        self.process = process
        self.key = section_key(base, process)
        self._sig = signature
        self._size = size
        self._newest: bytes | None = None  # replaced whole by the callback
        self.received = 0  #: payloads received
        self._problem: str | None = None
        self._told = ""
        self._sub = session.declare_subscriber(self.key, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        self._newest = sample.payload.to_bytes()
        self.received += 1

    def newest_frame(self) -> int | None:
        """The communications-segment count of the newest payload (None: none yet)."""
        p = self._newest
        if p is None or len(p) < PAYLOAD_HEADER.size:
            return None
        return PAYLOAD_HEADER.unpack_from(p)[1]

    def read(self, into: bytearray) -> int | None:
        p = self._newest
        if p is None:
            return None
        if len(p) != PAYLOAD_HEADER.size + self._size or p[:8] != self._sig:
            self._problem = (f"its section on {self.key} has another variable layout ({len(p)} bytes, signature "
                             f"{p[:8].hex()}; here {PAYLOAD_HEADER.size + self._size} bytes, {self._sig.hex()}): "
                             f"not imported")
            return None
        memoryview(into)[:] = memoryview(p)[PAYLOAD_HEADER.size:]
        return PAYLOAD_HEADER.unpack_from(p)[1]

    def problem(self) -> str | None:
        p = self._problem
        if p is not None and p != self._told:
            self._told = p
            return p
        return None

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:  # noqa: BLE001 - the session may be closed already
            pass


class ZenohLink:
    """One process's Zenoh link: its publisher and a :class:`ZenohSource` per other process.

    Give :meth:`sources` to :class:`DistributedProcess` (``sources=link.sources``), then
    call :meth:`publish` after each of its frames (the runtime's ``on_frame``).

    :param session: an open Zenoh session (tests); default: one opened on ``listen`` /
        ``connect`` (the distribution file's, :meth:`DistributedConfig.endpoints`) and closed
        by :meth:`close`
    """

    def __init__(self, config: DistributedConfig, process: str, base: str, *, session: Any = None,
                 listen: tuple[str, ...] | list[str] = (), connect: tuple[str, ...] | list[str] = ()) -> None:
        self.config = config
        self.process = config.process(process).name
        self.base = check_name(base, "world-model base name")
        self._own = session is None
        self.session = open_session(list(listen), list(connect)) if session is None else session
        self._pub: Any = None
        self._dp: DistributedProcess | None = None
        self.remote: dict[str, ZenohSource] = {}
        self.published = 0
        self.last_frame = -1  #: the communications-segment count of the last payload published

    def sources(self, dp: DistributedProcess) -> dict[str, ZenohSource]:
        self._dp = dp
        self._pub = self.session.declare_publisher(section_key(self.base, self.process))
        self.remote = {q: ZenohSource(self.session, self.base, q, dp.signature, dp.sections[q].size)
                       for q in self.config.names if q != self.process}
        return dict(self.remote)

    def publish(self, _rec: Any = None) -> None:
        """Put this process's section (after its frame: both communications segments done)."""
        assert self._dp is not None and self._pub is not None, "sources() first"
        payload = self._dp.payload()
        self.last_frame = PAYLOAD_HEADER.unpack_from(payload)[1]
        self._pub.put(payload)
        self.published += 1

    def close(self) -> None:
        for s in self.remote.values():
            s.close()
        if self._pub is not None:
            try:
                self._pub.undeclare()
            except Exception:  # noqa: BLE001
                pass
            self._pub = None
        if self._own:
            self.session.close()


__all__ = ["ZenohLink", "ZenohSource", "section_key"]
