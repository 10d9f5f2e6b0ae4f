"""The RegisterBus contract and the registry of bus backends.

A RegisterBus is any object with ``read8/read16/write8/write16`` on **absolute A16
short-I/O addresses** as the IRSS report gives them (0x0100, 0xC000, 0xD000 ...).
16-bit accesses are big-endian; 8-bit chips sit on odd bytes. An access nobody
answers raises :class:`pfma.errors.BusError`. Drivers type against the protocol
and never check the class.

Backends are opened by URL, as pyserial opens ports:

- ``fake`` or ``fake://``: the register-level fake rack (``fakes.rack``)
- ``modbus://HOST:PORT[?unit=N&timeout=S]``: a Modbus TCP gateway where holding
  register N is the 16-bit word at A16 address 2N (``drivers.bus.modbus``)
- ``file:PATH[?size=N&offset=N&base=N]``: an mmap of a VME A16 window exposed as a device file
  (``drivers.bus.devicefile``)
- ``spy+URL``: any of the above, logging every access (``drivers.bus.spy``)
"""

from __future__ import annotations

import importlib
import operator
from typing import Protocol, runtime_checkable

from pfma.errors import BusError, ConfigError

__all__ = ["RegisterBus", "BusError", "BusUrlError", "open_bus", "BACKENDS", "check_addr", "check_value"]


class BusUrlError(ConfigError):
    """A bus URL :func:`open_bus` cannot open: unknown scheme or malformed (a ``ValueError``
    too, as before)."""


def check_addr(addr: int) -> None:
    """ValueError unless ``addr`` is an A16 address (0..0xFFFF)."""
    if not isinstance(addr, int) or not 0 <= addr <= 0xFFFF:
        raise ValueError(f"A16 address {addr!r} out of range 0..0xFFFF")


def check_value(addr: int, value: int, width: int) -> int:
    """The value as an int, or ValueError: every backend refuses, never masks (contract:
    masking -1 to 0xFFFF would hit the DAC control register)."""
    try:
        v = operator.index(value)  # ints and numpy integers, not floats
    except TypeError:
        v = -1
    if not 0 <= v < (1 << width):
        raise ValueError(f"write{width} to A16 0x{addr:04X}: value {value!r} does not fit "
                         f"{width} bits (0..0x{(1 << width) - 1:X})")
    return v


@runtime_checkable
class RegisterBus(Protocol):
    def read8(self, addr: int) -> int: ...
    def read16(self, addr: int) -> int: ...
    def write8(self, addr: int, value: int) -> None: ...
    def write16(self, addr: int, value: int) -> None: ...


#: URL scheme -> "module:callable(url) -> bus"
BACKENDS: dict[str, str] = {
    "fake": "fakes.rack:open_fake_bus",
    "modbus": "drivers.bus.modbus:open_modbus_bus",
    "file": "drivers.bus.devicefile:open_devicefile_bus",
    "spy": "drivers.bus.spy:open_spy_bus",
}


def _scheme(url: str) -> str:
    if url in ("fake", ""):
        return "fake"
    if url.startswith("spy+"):
        return "spy"
    scheme, sep, _ = url.partition(":")
    if not sep:
        raise BusUrlError(f"bus URL {url!r} has no scheme; use fake, modbus://HOST:PORT or file:PATH")
    return scheme


def open_bus(url: str = "fake", **kwargs):
    """Open a RegisterBus by URL.

    :raises BusUrlError: (a ``PfmaError`` and a ``ValueError``) for an unknown scheme or a
        malformed URL (``modbus://HOST`` without a port, an unknown option ...)
    """
    scheme = _scheme(url)
    try:
        target = BACKENDS[scheme]
    except KeyError:
        raise BusUrlError(f"unknown bus scheme {scheme!r} in {url!r}; known: "
                          f"{', '.join(sorted(BACKENDS))}") from None
    module_name, _, func_name = target.partition(":")
    factory = getattr(importlib.import_module(module_name), func_name)
    try:
        return factory(url, **kwargs)
    except ValueError as err:
        if isinstance(err, BusUrlError):
            raise
        raise BusUrlError(str(err)) from err
