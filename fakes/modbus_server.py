"""A pymodbus TCP server for one ``SimDevice`` in a background thread with its own loop.

The server of the fake Modbus gateway of the tests (``fakes.modbus_gateway``; the
service's Modbus export, ``tools.modbus_export``, has its own). pymodbus 3.16 pitfalls
(reference notes on the package): build ``ModbusTcpServer`` inside the running loop,
``serve_forever(background=True)`` returns once listening (or, when the bind fails,
with no transport), ``shutdown()`` resolves ``serving``.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Callable, cast

from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import SimDevice

from pfma.errors import PfmaError


class ModbusServerError(PfmaError):
    """The server could not start (port in use, bad address)."""


class ModbusServerThread:
    """A pymodbus ``ModbusTcpServer`` for one ``SimDevice`` in a background thread.

    :param make_device: called on the server thread to build the ``SimDevice``
    :param host: address to bind
    :param port: TCP port, 0 for an ephemeral one (:attr:`port` after :meth:`start`)
    :param error: exception class raised when the server cannot start
    """

    def __init__(self, make_device: Callable[[], SimDevice], host: str, port: int,
                 name: str = "modbus-server", error: type[Exception] = ModbusServerError) -> None:
        self.make_device = make_device
        self.error = error
        self.host = host
        self.port = port
        self.name = name
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: ModbusTcpServer | None = None
        self._error: BaseException | None = None

    def _run(self) -> None:
        self._loop = asyncio.new_event_loop()
        asyncio.set_event_loop(self._loop)

        async def main() -> None:
            self._server = ModbusTcpServer(self.make_device(), address=(self.host, self.port))
            await self._server.serve_forever(background=True)
            if self._server.transport is None:  # pymodbus logs the bind error and returns
                raise OSError(f"could not listen on {self.host}:{self.port}")
            # pymodbus types transport as BaseTransport; a listening TCP server holds the
            # asyncio.Server that loop.create_server returned
            listener = cast(asyncio.Server, self._server.transport)
            self.port = listener.sockets[0].getsockname()[1]
            self._ready.set()
            await self._server.serving  # resolved by shutdown()

        try:
            self._loop.run_until_complete(main())
        except BaseException as err:  # noqa: BLE001 - reported to start()
            self._error = err
            self._ready.set()
        finally:
            self._loop.close()

    def start(self, timeout_s: float = 5.0) -> int:
        """Start listening; returns the bound port once it is bound."""
        if self._thread is not None:
            raise RuntimeError(f"{self.name} already started")
        self._error = None
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise self.error(f"{self.name} did not start within {timeout_s} s")
        if self._error is not None:
            self._thread.join(timeout_s)
            self._thread = None
            raise self.error(f"{self.name} on {self.host}:{self.port} failed to start: "
                                    f"{self._error}") from self._error
        return self.port

    def stop(self, timeout_s: float = 5.0) -> None:
        """Shut the server down and join its thread (the port can be re-bound at once)."""
        if self._thread is None:
            return
        if self._server is not None and self._loop is not None and not self._loop.is_closed():
            try:
                asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop).result(timeout_s)
            except RuntimeError:  # loop already finished
                pass
        self._thread.join(timeout_s)
        self._thread = None
        self._server = None
        self._ready.clear()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()
