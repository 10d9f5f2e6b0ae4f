"""The export's own Modbus TCP server: framing by the MBAP length, requests answered in
order (pipelined too), the limits of one export (:class:`ExportLimits`), the refusal log,
and the asyncio loop in its daemon thread. What a request means is the export's business
(:meth:`tools.modbus_export.export.ModbusExport.handle_pdu`).
"""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import struct
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from pfma.errors import ConfigError
from pfma.refusals import RefusalLog
from tools.modbus_export.map import ModbusExportError

if TYPE_CHECKING:
    from tools.modbus_export.export import ModbusExport

log = logging.getLogger("tools.modbus_export")  # one logger for the package: its records keep their name

#: Modbus exception codes the export answers (Modbus application protocol, section 7)
ILLEGAL_FUNCTION = 1
ILLEGAL_ADDRESS = 2
ILLEGAL_VALUE = 3
DEVICE_FAILURE = 4
#: MBAP length field: unit id + PDU; a PDU is at most 253 bytes (an ADU at most 260)
MBAP_MAX_LENGTH = 254
#: Modbus limit on registers per write (fc 16)
MAX_WRITE_REGISTERS = 123
#: kernel send and receive buffer asked for each connection (Linux doubles it for its
#: bookkeeping); without it a loopback connection autotunes to ~4 MB each way
SOCKET_BUFFER_BYTES = 65536
_MBAP = struct.Struct(">HHHB")
_READS = {3, 4}


@dataclass(frozen=True)
class ExportLimits:
    """What one export lets its clients use (flags of ``python -m tools.modbus_export``).

    Memory per connection is bounded by ``in_buffer_bytes`` (requests received, not yet
    answered) plus ``out_buffer_bytes`` (answers the client has not taken yet) plus one
    answer: when the answers pile up the export stops reading that connection (the
    client's sends then block in its own kernel buffers), and a connection that moves no
    byte either way for ``idle_timeout_s`` is closed.
    """

    max_connections: int = 16  #: clients at once; one more is accepted and closed at once
    in_buffer_bytes: int = 4096  #: per connection: received bytes not yet answered (>= 260)
    out_buffer_bytes: int = 16384  #: per connection: answers not yet taken by a slow reader
    idle_timeout_s: float = 60.0  #: a connection with no traffic (or a stalled reader) closed after
    summary_interval_s: float = 60.0  #: at most one line about refused requests per interval

    def __post_init__(self) -> None:
        if self.max_connections < 1:
            raise ConfigError(f"Modbus export: max_connections {self.max_connections}: at least 1")
        if self.in_buffer_bytes < 7 + MBAP_MAX_LENGTH - 1:
            raise ConfigError(f"Modbus export: in_buffer_bytes {self.in_buffer_bytes}: at least 260 "
                              f"(one whole Modbus TCP request)")
        if self.out_buffer_bytes < 260:
            raise ConfigError(f"Modbus export: out_buffer_bytes {self.out_buffer_bytes}: at least 260")
        if not self.idle_timeout_s > 0 or not self.summary_interval_s > 0:
            raise ConfigError("Modbus export: idle_timeout_s and summary_interval_s must be > 0")


def refusal_log(where: str, interval_s: float = 60.0, clock=time.monotonic,
                logger: logging.Logger | None = None) -> RefusalLog:
    """The export's :class:`pfma.refusals.RefusalLog`: refused requests and dropped
    connections counted, one warning line per ``interval_s`` at most, never a traceback."""
    lg = logger or log
    return RefusalLog(f"Modbus export {where}", lambda line: lg.warning("%s", line), interval_s, clock)


class _Connection(asyncio.BufferedProtocol):
    """One client: whole ADUs cut from a fixed receive buffer, answered in order
    (pipelined requests too), with the limits of :class:`ExportLimits`."""

    def __init__(self, server: "_Server") -> None:
        self.server = server
        self.transport: asyncio.Transport | None = None
        self._in = bytearray(server.limits.in_buffer_bytes)
        self._view = memoryview(self._in)
        self._n = 0  # bytes held in self._in
        self._paused = False  # answers piled up: not reading, not answering
        self._closing = False
        self.last_activity = server.loop.time()

    # -- asyncio callbacks -------------------------------------------------------------------
    def connection_made(self, transport) -> None:  # type: ignore[override]
        self.transport = transport
        srv = self.server
        if len(srv.connections) >= srv.limits.max_connections:
            srv.export.note(f"connections over the limit of {srv.limits.max_connections} (closed)")
            self._closing = True
            transport.abort()
            return
        srv.connections.add(self)
        srv.export.connections_total += 1
        transport.set_write_buffer_limits(high=srv.limits.out_buffer_bytes)
        sock = transport.get_extra_info("socket")
        if sock is not None:
            try:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                # the kernel's buffers for this client bounded too (Linux autotunes them to MBs)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER_BYTES)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER_BYTES)
            except OSError:
                pass

    def connection_lost(self, exc) -> None:
        self.server.connections.discard(self)
        self.transport = None

    def get_buffer(self, sizehint: int) -> memoryview:
        if self._n >= len(self._in):  # never while reading: a full buffer pauses reading
            return self._view[:1]  # pragma: no cover - defensive; asyncio needs a non-empty buffer
        return self._view[self._n:]

    def buffer_updated(self, nbytes: int) -> None:
        self._n += nbytes
        self.last_activity = self.server.loop.time()
        self._process()

    def pause_writing(self) -> None:
        self._paused = True
        if self.transport is not None and not self._closing:
            self.transport.pause_reading()

    def resume_writing(self) -> None:
        self._paused = False
        self.last_activity = self.server.loop.time()
        self._process()
        if self.transport is not None and not self._closing and not self._paused:
            self.transport.resume_reading()

    def eof_received(self) -> bool:
        return False  # close when the client half-closes (answers already written are sent)

    # -- framing ---------------------------------------------------------------------------
    def _process(self) -> None:
        buf, n, at = self._in, self._n, 0
        export = self.server.export
        while not self._paused and not self._closing and n - at >= 7:
            tid, proto, length, unit = _MBAP.unpack_from(buf, at)
            if length < 2 or length > MBAP_MAX_LENGTH:
                # the stream cannot be framed any further: nothing to answer, close
                export.note(f"malformed MBAP header (length {'< 2' if length < 2 else '> 254'}; "
                            f"connection closed)")
                self._close()
                break
            end = at + 6 + length
            if end > n:
                break  # the rest of this request has not arrived yet
            pdu = bytes(buf[at + 7:end])
            at = end
            export.requests += 1
            if proto != 0:
                export.note("requests with a protocol id other than 0 (not Modbus; not answered)")
                continue
            if export.device_id and unit != export.device_id:
                export.note("requests for another unit id (not answered)")
                continue
            answer = export.handle_pdu(pdu)
            if self.transport is not None:
                self.transport.write(_MBAP.pack(tid, 0, len(answer) + 1, unit) + answer)
        if at:
            rest = n - at
            buf[:rest] = buf[at:n]
            n = rest
        self._n = n
        if n >= len(buf) and self.transport is not None and not self._closing:
            self.transport.pause_reading()  # only while paused: resume_writing reads on

    def _close(self) -> None:
        self._closing = True
        if self.transport is not None:
            self.transport.close()

    def check_idle(self, now: float, timeout_s: float) -> None:
        """Close a connection that moved nothing for ``timeout_s`` (idle, or a reader that
        takes no answers: its write buffer then stays above the limit)."""
        if self._closing or now - self.last_activity < timeout_s:
            return
        why = "reader stalled" if self._paused else "idle"
        self.server.export.note(f"connections closed after {timeout_s:g} s {why}")
        self._closing = True
        if self.transport is not None:
            self.transport.abort()


class _Server:
    """The listening socket and its connections, on one asyncio loop."""

    def __init__(self, export: "ModbusExport", loop: asyncio.AbstractEventLoop, limits: ExportLimits) -> None:
        self.export = export
        self.loop = loop
        self.limits = limits
        self.connections: set[_Connection] = set()
        self.listener: asyncio.base_events.Server | None = None
        self._ticker: asyncio.Task | None = None

    async def start(self, host: str, port: int) -> int:
        self.listener = await self.loop.create_server(lambda: _Connection(self), host, port,
                                                      reuse_address=True, backlog=64)
        self._ticker = self.loop.create_task(self._tick())
        return self.listener.sockets[0].getsockname()[1]

    async def _tick(self) -> None:
        every = min(1.0, self.limits.idle_timeout_s / 4)
        while True:
            await asyncio.sleep(every)
            now = self.loop.time()
            for c in list(self.connections):
                c.check_idle(now, self.limits.idle_timeout_s)
            self.export.refusals.tick()

    async def stop(self) -> None:
        if self._ticker is not None:
            self._ticker.cancel()
        if self.listener is not None:
            self.listener.close()
        for c in list(self.connections):
            if c.transport is not None:
                c.transport.abort()
        if self.listener is not None:
            await self.listener.wait_closed()


class _ServerThread:
    """A :class:`_Server` on its own asyncio loop in a daemon thread."""

    def __init__(self, export: "ModbusExport", host: str, port: int, limits: ExportLimits) -> None:
        self.export = export
        self.host = host
        self.port = port
        self.limits = limits
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: _Server | None = None
        self._stopped: asyncio.Future | None = None
        self._error: BaseException | None = None

    def _run(self) -> None:
        loop = self._loop = asyncio.new_event_loop()

        async def main() -> None:
            self._server = _Server(self.export, loop, self.limits)
            self._stopped = loop.create_future()
            self.port = await self._server.start(self.host, self.port)
            self._ready.set()
            await self._stopped
            await self._server.stop()

        try:
            loop.run_until_complete(main())
        except BaseException as err:  # noqa: BLE001 - reported to start()
            self._error = err
            self._ready.set()
        finally:
            loop.close()

    def start(self, timeout_s: float) -> int:
        self._thread = threading.Thread(target=self._run, name=f"modbus-export-{self.export.buffer_name}",
                                        daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise ModbusExportError(f"Modbus export on {self.host}:{self.port} did not start within "
                                    f"{timeout_s:g} s")
        if self._error is not None:
            self._thread.join(timeout_s)
            self._thread = None
            err = self._error
            why = os.strerror(err.errno) if isinstance(err, OSError) and err.errno else str(err)
            raise ModbusExportError(f"Modbus export cannot listen on {self.host}:{self.port}: {why}") from err
        return self.port

    def stop(self, timeout_s: float) -> None:
        loop, stopped = self._loop, self._stopped
        if loop is not None and stopped is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(lambda: stopped.done() or stopped.set_result(None))
            except RuntimeError:  # loop already closed
                pass
        if self._thread is not None:
            self._thread.join(timeout_s)
        self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()
