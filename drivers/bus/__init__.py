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
from typing import Protocol, runtime_checkable

from pfma.errors import BusError

__all__ = ["RegisterBus", "BusError", "open_bus", "BACKENDS"]


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
        raise ValueError(f"bus URL {url!r} has no scheme; use fake, modbus://HOST:PORT or file:PATH")
    return scheme


def open_bus(url: str = "fake", **kwargs):
    """Open a RegisterBus by URL.

    :raises ValueError: for an unknown scheme or malformed URL
    """
    scheme = _scheme(url)
    try:
        target = BACKENDS[scheme]
    except KeyError:
        raise ValueError(f"unknown bus scheme {scheme!r} in {url!r}; known: {', '.join(sorted(BACKENDS))}") from None
    module_name, _, func_name = target.partition(":")
    factory = getattr(importlib.import_module(module_name), func_name)
    return factory(url, **kwargs)
