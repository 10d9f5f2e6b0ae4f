"""A fake Modbus TCP gateway that serves any RegisterBus (normally the fake rack).

It is a real pymodbus ``ModbusTcpServer`` on 127.0.0.1 (ephemeral port by
default), run in a background thread with its own event loop, so a real
``ModbusTcpBus`` (or any Modbus tool) talks to it over loopback TCP.

Mapping, the same as ``drivers.bus.modbus``: holding register N is the 16-bit word
at A16 address 2N. The registers of a request are forwarded to the hosted bus as ONE
block transfer (``read_block16``/``write_block16`` at 2N; a hosted bus without them gets
``read16``/``write16`` one at a time), only the requested ones and in address order,
because reads of real registers have side effects. A ``BusError`` from the hosted bus
answers Modbus exception 2 (ILLEGAL_ADDRESS, "no board answered"); any other error
answers exception 4 (DEVICE_FAILURE). Input registers (fc 4) read the same words.
Function code 23 (read/write multiple registers) is served too: pymodbus's
``SimDevice`` runs its write half, then its read half, through the same action.
Function codes other than 3, 4, 6, 16 and 23 answer exception 1 (ILLEGAL_FUNCTION);
the echo of a write (pymodbus reads the written block back for fc 6) never reaches the
hosted bus.

``silent = True`` makes the gateway stop answering: requests are received and counted
but get no reply until ``silent`` is cleared or the gateway stops (a gateway whose VME
side hangs).

pymodbus 3.16: the supported way to serve live objects is ``SimDevice(action=...)``
(legacy datablock subclasses are deep-copied and silently ignored); ``id=0`` is the
catch-all device so any unit id is answered.
"""

from __future__ import annotations

import asyncio
import threading

from pymodbus.constants import ExcCodes
from pymodbus.simulator import DataType, SimData, SimDevice

from pfma.errors import BusError
from fakes.modbus_server import ModbusServerThread

__all__ = ["ModbusGateway"]

_READS = {3, 4}
_WRITES = {6, 16}
_READ_WRITE = 23  # write half (values given), then read half (no values)


class ModbusGateway:
    """Serve ``bus`` (any RegisterBus) as Modbus holding registers on ``host:port``.

    :param bus: the hosted RegisterBus; accessed only under :attr:`lock`
    :param host: address to listen on (loopback by default)
    :param port: TCP port, 0 for an ephemeral one (see :attr:`port` after start)
    :param reply_delay_s: answer each request this late (simulates a slow gateway)
    :param log_function_codes: keep every request's function code in :attr:`function_codes`
        (tests count them); a long-running gateway (``pfma gateway``) turns it off, or the
        list would grow without bound
    """

    def __init__(self, bus, host: str = "127.0.0.1", port: int = 0, *,
                 reply_delay_s: float = 0.0, log_function_codes: bool = True) -> None:
        self.bus = bus
        self.host = host
        self.port = port
        self.reply_delay_s = reply_delay_s
        #: held while the hosted bus is accessed; take it to touch the bus from another thread
        self.lock = threading.Lock()
        self.requests = 0  #: register requests received (fc 6 and fc 23 count once)
        self.function_codes: list[int] = []  #: function code of each request, in order (if logged)
        self._log_codes = log_function_codes
        self.silent = False  #: received requests get no reply while set
        self._counted = threading.Condition()
        self._stopping = threading.Event()
        self._server: ModbusServerThread | None = None

    # -- the action pymodbus calls for every register request --------------------------
    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      current_registers: list[int], set_values) -> ExcCodes | None:
        # one count per request: not the echo read-back of fc 6, not the read half of fc 23
        second_call = set_values is None and (function_code in _WRITES or function_code == _READ_WRITE)
        if not second_call:
            with self._counted:
                self.requests += 1
                if self._log_codes:
                    self.function_codes.append(function_code)
                self._counted.notify_all()
        while self.silent and not self._stopping.is_set():
            await asyncio.sleep(0.005)  # a hung gateway: no reply (the client times out)
        if self.reply_delay_s:
            await asyncio.sleep(self.reply_delay_s)
        if function_code not in _READS | _WRITES | {_READ_WRITE}:
            return ExcCodes.ILLEGAL_FUNCTION
        if function_code in _WRITES and set_values is None:
            # pymodbus reads the block back to echo a write (fc 6); never read the hosted
            # bus for that: a read has side effects and VME writes do not read back.
            return None
        off = address - start_address
        try:
            with self.lock:
                if set_values is None:  # fc 3, 4 and the read half of fc 23
                    words = self._read(2 * address, count)
                    current_registers[off:off + count] = [w & 0xFFFF for w in words]
                else:
                    self._write(2 * address, [int(v) & 0xFFFF for v in set_values])
        except BusError:
            return ExcCodes.ILLEGAL_ADDRESS
        except Exception:  # noqa: BLE001 - any other failure of the hosted bus is a device failure
            return ExcCodes.DEVICE_FAILURE
        return None

    def wait_requests(self, n: int, timeout_s: float = 5.0) -> int:
        """Block until the server thread has received at least ``n`` requests (or
        ``timeout_s`` passed); returns the count. For tests: a client that timed out has
        sent its request, but the server thread may not have counted it yet."""
        with self._counted:
            self._counted.wait_for(lambda: self.requests >= n, timeout_s)
            return self.requests

    def _read(self, addr: int, count: int) -> list[int]:
        block = getattr(self.bus, "read_block16", None)
        if block is not None:
            return block(addr, count)
        return [self.bus.read16(addr + 2 * i) for i in range(count)]

    def _write(self, addr: int, words: list[int]) -> None:
        block = getattr(self.bus, "write_block16", None)
        if block is not None:
            block(addr, words)
        else:
            for i, w in enumerate(words):
                self.bus.write16(addr + 2 * i, w)

    # -- server thread -----------------------------------------------------------------------
    def _device(self) -> SimDevice:
        return SimDevice(id=0,  # catch-all unit id
                         simdata=[SimData(address=0, count=32768, values=0, datatype=DataType.REGISTERS)],
                         action=self._action)

    def start(self, timeout_s: float = 5.0) -> "ModbusGateway":
        """Start listening; returns once the port is bound."""
        if self._server is not None:
            raise RuntimeError("gateway already started")
        self._stopping.clear()
        server = ModbusServerThread(self._device, self.host, self.port,
                                    name=f"modbus-gateway-{self.port}", error=RuntimeError)
        self.port = server.start(timeout_s)
        self._server = server
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Shut the server down and join its thread (the port can be re-bound at once)."""
        if self._server is not None:
            self._stopping.set()  # release requests held by ``silent``
            self._server.stop(timeout_s)
            self._server = None

    @property
    def url(self) -> str:
        """The ``open_bus`` URL of this gateway."""
        return f"modbus://{self.host}:{self.port}"

    def __enter__(self) -> "ModbusGateway":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
