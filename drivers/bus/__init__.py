"""The RegisterBus contract and the registry of bus backends.

A RegisterBus is any object with ``read8/read16/write8/write16`` and the block
transfers ``read_block16/write_block16`` on **absolute A16 short-I/O addresses** as the
IRSS report gives them (0x0100, 0xC000, 0xD000 ...). 16-bit accesses are big-endian;
8-bit chips sit on odd bytes. An access nobody answers raises
:class:`pfma.errors.BusError`. Drivers type against the protocol and never check the
class.

Block transfers (the one way a driver reads or writes consecutive registers in the fewest
transactions a backend allows): ``read_block16(addr, n)`` reads the words at ``addr,
addr+2, ... addr+2(n-1)``, in that order; ``write_block16(addr, words)`` writes them in
that order. Each word is one D16 cycle with exactly the side effects of ``read16`` /
``write16`` at its address (a block is *not* a VME BLT: A16 has no block address
modifier). Checks, all before any access (:func:`check_block`, :func:`check_words`): an
odd ``addr`` is an :class:`pfma.errors.AlignmentError` (a ``BusError`` and a
``ValueError``), ``n < 1``, an empty block or a block running past 0xFFFF a
``ValueError``, a word that does not fit 16 bits a ``ValueError``. A word nobody
answers raises ``BusError`` naming that word's address where the backend can tell (the
fake rack, the device file); a Modbus gateway answers a request as a whole, so there the
error names the first word of the failing request. Words before the failing one have
been transferred (their side effects happened), as on the VME bus.

Backends are opened by URL, as pyserial opens ports:

- ``fake`` or ``fake://``: the register-level fake rack (``fakes.rack``)
- ``modbus://HOST:PORT[?unit=N&timeout=S]``: a Modbus TCP gateway where holding
  register N is the 16-bit word at A16 address 2N (``drivers.bus.modbus``)
- ``file:PATH[?size=N&offset=N&base=N]``: an mmap of a VME A16 window exposed as a device file
  (``drivers.bus.devicefile``)
- ``caen://BOARD/LINK[?node=N&am=0x29]``: a CAEN bridge (V1718 USB, V2718/V3718/V4718 over
  CONET, USB or Ethernet) through CAEN's VMELib binding caen-libs (``drivers.bus.caen``)
- ``vme:/dev/bus/vme/mN[?am=0x29]``: a Linux ``vme_user`` master window, set up for A16
  D16 with the ``VME_SET_MASTER`` ioctl (``drivers.bus.vmeuser``)
- ``spy+URL``: any of the above, logging every access (``drivers.bus.spy``)
"""

from __future__ import annotations

import importlib
import operator
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

from pfma.errors import AlignmentError, BusError, ConfigError

__all__ = ["RegisterBus", "ReadWriteBlockBus", "BusError", "BusUrlError", "open_bus", "BACKENDS",
           "check_addr", "check_value", "check_block", "check_words"]


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


def check_block(addr: int, n: int, op: str) -> None:
    """The checks of a block of ``n`` words at ``addr`` (before any access): ValueError
    unless ``addr`` is an A16 address, ``n`` >= 1 and the block ends inside the A16 space;
    AlignmentError (a BusError and a ValueError) for an odd ``addr``."""
    check_addr(addr)
    if not isinstance(n, int) or isinstance(n, bool) or n < 1:
        raise ValueError(f"{op}_block16 at A16 0x{addr:04X}: {n!r} words; a block has at least one")
    if addr + 2 * n > 0x10000:
        raise ValueError(f"{op}_block16 at A16 0x{addr:04X}: {n} words run past the A16 space "
                         f"(last word 0x{addr + 2 * n - 2:X} > 0xFFFE)")
    if addr % 2:
        raise AlignmentError(addr, 16, op, reason="16-bit block at an odd address")


def check_words(addr: int, words: Sequence[int]) -> list[int]:
    """The words of ``write_block16(addr, words)`` as ints, every one checked before any
    access (:func:`check_block` and :func:`check_value` for each, naming its address)."""
    values = list(words)
    check_block(addr, len(values), "write")
    # the common case in one pass: every word a plain int in 0..0xFFFF (bool, numpy
    # integers and bad words go word by word, for their conversion or their message)
    if all(type(v) is int and 0 <= v <= 0xFFFF for v in values):
        return values
    return [check_value(addr + 2 * i, v, 16) for i, v in enumerate(values)]


@runtime_checkable
class RegisterBus(Protocol):
    def read8(self, addr: int) -> int: ...
    def read16(self, addr: int) -> int: ...
    def write8(self, addr: int, value: int) -> None: ...
    def write16(self, addr: int, value: int) -> None: ...
    def read_block16(self, addr: int, n: int) -> list[int]: ...
    def write_block16(self, addr: int, words: Sequence[int]) -> None: ...


@runtime_checkable
class ReadWriteBlockBus(RegisterBus, Protocol):
    """Optional extension of the contract: a backend that can write one block and read
    another in ONE transaction (Modbus function code 23). ``read_write_block16`` writes
    ``words`` at ``write_addr`` first, then reads ``n`` words at ``read_addr`` (the
    order Modbus defines), with the checks of both blocks made before either starts.
    Only the Modbus bus offers it; no driver needs it (none writes a block and then
    reads one), so it is not part of :class:`RegisterBus`."""

    def read_write_block16(self, read_addr: int, n: int, write_addr: int,
                           words: Sequence[int]) -> list[int]: ...


#: URL scheme -> "module:callable(url) -> bus"
BACKENDS: dict[str, str] = {
    "fake": "fakes.rack:open_fake_bus",
    "modbus": "drivers.bus.modbus:open_modbus_bus",
    "file": "drivers.bus.devicefile:open_devicefile_bus",
    "spy": "drivers.bus.spy:open_spy_bus",
    "caen": "drivers.bus.caen:open_caen_bus",
    "vme": "drivers.bus.vmeuser:open_vme_bus",
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
