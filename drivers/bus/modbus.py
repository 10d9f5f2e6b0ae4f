"""A RegisterBus through a Modbus TCP gateway to the VME A16 space.

Mapping (project convention, docs/architecture "RegisterBus"): **holding register N
is the 16-bit word at A16 address 2N**, big-endian as on VME. So ``read16(0xD000)``
reads holding register 0x6800 and ``write16`` writes it with function code 6.

8-bit accesses, which Modbus cannot express:

- ``read8(addr)`` reads the word at ``addr & ~1`` and returns its high byte for an
  even ``addr``, its low byte for an odd one. On an odd-byte board (MVME400/410)
  the gateway's D16 cycle reaches the chip on D7..D0, so the low byte is the
  register; the high byte is whatever the undriven lanes read.
- ``write8(addr, v)`` for an **odd** ``addr`` writes the word ``0x00 << 8 | v``.
  There is deliberately **no read-modify-write**: reading an 8-bit chip register
  has side effects (a 6821 data read clears its IRQ flags; a uPD7201 read moves
  the register pointer), and on an odd-byte board the even byte is not decoded, so
  writing 0x00 there is harmless. A word board answers 8-bit cycles with a bus
  error anyway, so nothing correct ever needs a byte write to it.
- ``write8`` to an **even** address cannot be represented (it would clobber the
  odd byte) and raises :class:`pfma.errors.AlignmentError` (a ``BusError`` and a
  ``ValueError``) without touching the network; so does any 16-bit access at an
  odd address.

Block transfers: ``read_block16`` is function code 3 and ``write_block16`` function
code 16, split into requests of at most :data:`MAX_READ_WORDS` (125) and
:data:`MAX_WRITE_WORDS` (123) registers, the Modbus limits; each request is one round
trip, the gateway makes one D16 cycle per word in address order. ``read_write_block16``
writes one block and reads another in ONE request (function code 23, at most 121 words
written and 125 read; the write happens first). A gateway answers a request as a
whole, so a bus error in a block names the first word of the failing request (the
words of earlier requests were transferred).

Timeout and connection: the bus keeps ONE TCP connection for all its accesses. The
per-request timeout defaults to :data:`DEFAULT_TIMEOUT_S`, one minor frame: a reply
later than that is useless to the frame that asked, and waiting longer stalls the
service (at the old 1 s default, a gateway that stopped answering turned a 3 s run into
80 s). After a timeout the connection is closed (so a late reply can never be taken for
the answer to the next request) and the next access reconnects once; there are no
retries (``retries=0``), so a gateway that stops answering costs at most one timeout
per access, and a block that fails stops at its first failing request.

Reconnecting while the gateway stays silent: the first :data:`FREE_RECONNECTS` failed
accesses in a row each open a new connection (one late reply on a loaded host costs one
reconnect, nothing more). After that a new connection is opened at most once per
:data:`RECONNECT_INTERVAL_S`; the accesses in between fail at once with the last error,
without touching the network. Why: a gateway that is stopped (SIGSTOP, a hung process, a
full CPU) still has its connections accepted by the kernel, each with a request in it; a
service opening one per access (~100 in a third of a second) leaves the gateway that many
dead connections to answer before it gets to the live one: measured on loopback, 131 ms
after a 330 ms stop of ``pfma gateway`` before the first answer, enough with a loaded host
to pass the service's 0.5 s bus-lost limit (the kill matrix's gateway trial). With the
interval, 20 connections queued in the same stop and the first answer came 47 ms after it
(the kill matrix's gateway trials check that the service rides through).

Errors: a gateway exception response (code 2 "illegal address" when no board
answered, 4 "device failure", 0x0B "gateway target did not respond", ...), a
timeout, or an unreachable gateway become :class:`BusError` ``(addr, width, op,
reason=...)`` raised ``from`` the pymodbus error. An unreachable gateway is a
BusError too (reason ``"gateway HOST:PORT unreachable"``), not a LinkError, so
drivers handle every failed access the same way; the client reconnects on the
next access. Construction never touches the network.

pymodbus 3.16 (see the project's pins): keyword-only client arguments,
``device_id=`` (not ``slave=``), ``retries=0`` (retries are the caller's policy).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Sequence
from typing import Callable
from urllib.parse import parse_qsl, urlsplit

from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException

from drivers.bus import check_block, check_words
from drivers.bus.base import WordBus
from pfma.errors import BusError

__all__ = ["ModbusTcpBus", "open_modbus_bus", "EXCEPTION_REASONS", "DEFAULT_TIMEOUT_S", "FREE_RECONNECTS",
           "RECONNECT_INTERVAL_S",
           "MAX_READ_WORDS", "MAX_WRITE_WORDS", "MAX_RW_WRITE_WORDS"]

#: Per-request timeout: one minor frame of the I/O service (1/320 Hz = 3.125 ms). A
#: reply later than the frame that asked for it is of no use to that frame, and a longer
#: wait only stalls the service; ``?timeout=S`` overrides it (a slow WAN link).
DEFAULT_TIMEOUT_S = 1.0 / 320.0
#: failed accesses in a row that may each open a new connection
FREE_RECONNECTS = 2
#: after FREE_RECONNECTS failed accesses in a row, a new connection at most this often, s.
#: Assumption: 20 ms (6 minor frames at 320 Hz) is a short wait to see a gateway back, and
#: keeps a silent gateway's queue of dead connections to ~50 per second
RECONNECT_INTERVAL_S = 0.020
#: Registers per request: function code 3 reads at most 125, function code 16 writes at
#: most 123 (Modbus Application Protocol v1.1b, 6.3 and 6.12).
MAX_READ_WORDS = 125
MAX_WRITE_WORDS = 123
#: Function code 23 writes at most 121 registers (and reads at most 125) (ibid. 6.17).
MAX_RW_WRITE_WORDS = 121

# pymodbus logs connection failures at error level; without a handler anywhere Python
# would print them to stderr on its own. Applications that configure logging still
# see them (this only stops the last-resort printer).
logging.getLogger("pymodbus").addHandler(logging.NullHandler())

#: Modbus exception code -> reason text (Modbus Application Protocol v1.1b, section 7)
EXCEPTION_REASONS: dict[int, str] = {
    1: "gateway exception 1 (illegal function)",
    2: "gateway exception 2 (illegal data address: no board answered)",
    3: "gateway exception 3 (illegal data value)",
    4: "gateway exception 4 (server device failure)",
    6: "gateway exception 6 (server device busy)",
    10: "gateway exception 10 (gateway path unavailable)",
    11: "gateway exception 11 (gateway target device failed to respond)",
}


class ModbusTcpBus(WordBus):
    """RegisterBus over a Modbus TCP gateway (holding register N = A16 word 2N).

    :param host: gateway host name or address
    :param port: gateway TCP port
    :param unit: Modbus unit (device) id the gateway answers to
    :param timeout: seconds to wait for connect and for each reply (default
        :data:`DEFAULT_TIMEOUT_S`, one minor frame)
    :param clock: monotonic seconds, for the reconnect interval (tests give a simulated one)
    """

    def __init__(self, host: str, port: int = 502, *, unit: int = 1,
                 timeout: float = DEFAULT_TIMEOUT_S, clock: Callable[[], float] = time.monotonic) -> None:
        if not 0 <= unit <= 255:
            raise ValueError(f"Modbus unit id {unit} out of range 0..255")
        if timeout <= 0:
            raise ValueError(f"Modbus timeout must be positive, not {timeout}")
        self.host = host
        self.port = port
        self.unit = unit
        self.timeout = timeout
        self._client = ModbusTcpClient(host, port=port, timeout=timeout, retries=0)
        self._lock = threading.Lock()  # one transaction at a time: threads may share the bus
        self.connects = 0  #: connection attempts made (one per access at most, after a failure)
        self.requests = 0  #: Modbus requests sent
        self.failures = 0  #: accesses failed in a row (no reply, unreachable)
        self._clock = clock
        self._next_connect = 0.0  # clock time before which no new connection is opened
        self._last_reason = ""

    @property
    def gateway(self) -> str:
        return f"{self.host}:{self.port}"

    # -- one Modbus transaction ---------------------------------------------------------
    def _call(self, addr: int, width: int, op: str, request, *args, **kwargs):
        with self._lock:
            return self._transact(addr, width, op, request, *args, **kwargs)

    def _transact(self, addr: int, width: int, op: str, request, *args, **kwargs):
        if not self._client.connected:
            now = self._clock()
            if self.failures >= FREE_RECONNECTS and now < self._next_connect:
                self.failures += 1
                raise BusError(addr, width, op, reason=f"{self._last_reason} ({self.failures} accesses in a row "
                                                       f"failed; reconnecting every "
                                                       f"{RECONNECT_INTERVAL_S * 1e3:g} ms)")
            self._next_connect = now + RECONNECT_INTERVAL_S
            self.connects += 1
            if not self._client.connect():
                self._failed(f"gateway {self.gateway} unreachable")
                raise BusError(addr, width, op, reason=self._last_reason)
        self.requests += 1
        try:
            rr = request(*args, device_id=self.unit, **kwargs)
        except ConnectionException as err:
            self._client.close()
            self._failed(f"gateway {self.gateway} unreachable ({err})")
            raise BusError(addr, width, op, reason=self._last_reason) from err
        except ModbusException as err:  # ModbusIOException: no reply within the timeout
            self._client.close()  # drop the connection so a late reply cannot be mistaken for the next
            self._failed(f"no reply from gateway {self.gateway} within {self.timeout:g} s")
            raise BusError(addr, width, op, reason=self._last_reason) from err
        self.failures = 0  # the gateway answered (an exception response is an answer too)
        if rr.isError():
            code = getattr(rr, "exception_code", None)
            reason = (EXCEPTION_REASONS.get(code, f"gateway exception {code}") if isinstance(code, int)
                      else f"gateway exception {code}")
            raise BusError(addr, width, op, reason=reason) from ModbusException(str(rr))
        return rr

    def _failed(self, reason: str) -> None:
        self.failures += 1
        self._last_reason = reason

    def _read_word(self, addr: int, width: int) -> int:
        rr = self._call(addr, width, "read", self._client.read_holding_registers, (addr & ~1) >> 1)
        return rr.registers[0] & 0xFFFF

    def _write_word(self, addr: int, word: int, width: int) -> None:
        self._call(addr, width, "write", self._client.write_register, addr >> 1, word)

    # -- RegisterBus (read8/read16/write8/write16: drivers.bus.base.WordBus) -------------------
    def read_block16(self, addr: int, n: int) -> list[int]:
        """The ``n`` words from even A16 ``addr`` on: function code 3, one request per
        :data:`MAX_READ_WORDS` words; a failing request's BusError names its first word."""
        check_block(addr, n, "read")
        words: list[int] = []
        read = self._client.read_holding_registers
        for a, k in _chunks(addr, n, MAX_READ_WORDS):
            rr = self._call(a, 16, "read", read, a >> 1, count=k)
            words += [r & 0xFFFF for r in rr.registers[:k]]
        return words

    def write_block16(self, addr: int, words: Sequence[int]) -> None:
        """Write ``words`` (all checked first) from even A16 ``addr`` on: function code 16,
        one request per :data:`MAX_WRITE_WORDS` words."""
        values = check_words(addr, words)
        write = self._client.write_registers
        for i, (a, k) in enumerate(_chunks(addr, len(values), MAX_WRITE_WORDS)):
            chunk = values[i * MAX_WRITE_WORDS:i * MAX_WRITE_WORDS + k]
            self._call(a, 16, "write", write, a >> 1, chunk)

    def read_write_block16(self, read_addr: int, n: int, write_addr: int,
                           words: Sequence[int]) -> list[int]:
        """Write ``words`` at ``write_addr``, then read ``n`` words at ``read_addr``, in ONE
        request (function code 23; at most 121 words written, 125 read; both blocks
        checked before the request). A BusError names the write block's first word
        (the gateway's answer does not say which half failed)."""
        values = check_words(write_addr, words)
        check_block(read_addr, n, "read")
        if n > MAX_READ_WORDS or len(values) > MAX_RW_WRITE_WORDS:
            raise ValueError(f"read_write_block16: {n} words read, {len(values)} written; one "
                             f"function code 23 request reads at most {MAX_READ_WORDS} and writes "
                             f"at most {MAX_RW_WRITE_WORDS}")
        rr = self._call(write_addr, 16, "write", self._client.readwrite_registers,
                        read_address=read_addr >> 1, read_count=n,
                        write_address=write_addr >> 1, values=values)
        return [r & 0xFFFF for r in rr.registers[:n]]

    # -- lifetime ---------------------------------------------------------------------------
    def describe(self) -> str:
        return (f"Modbus TCP gateway {self.gateway} unit {self.unit} (timeout {self.timeout:g} s): "
                f"holding register N = A16 word 2N")

    def close(self) -> None:
        self._client.close()

    def __repr__(self) -> str:
        return f"ModbusTcpBus({self.host!r}, {self.port}, unit={self.unit}, timeout={self.timeout:g})"


def _chunks(addr: int, n: int, size: int) -> list[tuple[int, int]]:
    """(address, words) of each request of a block of ``n`` words split at ``size``."""
    return [(addr + 2 * i, min(size, n - i)) for i in range(0, n, size)]


def open_modbus_bus(url: str, **kwargs) -> ModbusTcpBus:
    """``open_bus("modbus://HOST:PORT[?unit=N&timeout=S]")``.

    :raises ValueError: for a missing host or port, an unknown option or a bad number
    """
    parts = urlsplit(url)
    if parts.scheme != "modbus":
        raise ValueError(f"not a modbus:// bus URL: {url!r}")
    try:
        port = parts.port
    except ValueError:
        raise ValueError(f"bus URL {url!r}: the port is not a number") from None
    if not parts.hostname or port is None:
        raise ValueError(f"bus URL {url!r} needs a host and a port: modbus://HOST:PORT")
    if parts.path not in ("", "/"):
        raise ValueError(f"bus URL {url!r}: unexpected path {parts.path!r}")
    parsers: dict[str, Callable[[str], int | float]] = {"unit": lambda v: int(v, 0), "timeout": float}
    opts: dict = {}
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key not in parsers:
            raise ValueError(f"bus URL {url!r}: unknown option {key!r}; known: timeout, unit")
        try:
            opts[key] = parsers[key](value)
        except ValueError:
            raise ValueError(f"bus URL {url!r}: {key}={value!r} is not a number") from None
    opts.update(kwargs)
    return ModbusTcpBus(parts.hostname, port, **opts)
