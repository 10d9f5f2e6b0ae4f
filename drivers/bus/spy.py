"""A RegisterBus wrapper that records every access (``spy+URL``), like pyserial's ``spy://``.

``open_bus("spy+modbus://10.0.0.5:502")`` wraps the Modbus bus; every access is
appended to :attr:`SpyBus.log` as a :class:`Access` and, when a logger is given (the
URL form uses ``drivers.bus.spy``), logged at DEBUG level. Failed accesses are
recorded with their error and re-raised unchanged. A block transfer is ONE access line
(op ``"read"``/``"write"``, width 16, ``count`` words, ``words`` the values), so
counting the log's entries counts bus transactions.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from drivers.bus.base import BusBase

if TYPE_CHECKING:
    from drivers.bus import RegisterBus

__all__ = ["SpyBus", "Access", "open_spy_bus"]

_log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Access:
    """One bus access as the spy saw it."""

    op: str  #: "read" or "write"
    width: int  #: 8 or 16
    addr: int  #: absolute A16 address
    value: int | None  #: value read or written (None when a read failed; a block's first word)
    error: str | None = None  #: the exception's message, when the access failed
    words: tuple[int, ...] | None = None  #: a block transfer's words (None for a single access)
    count: int = 1  #: words transferred (a block's length)
    block: bool = False  #: True for a block transfer (``read_block16``/``write_block16``)

    def __str__(self) -> str:
        arrow = "->" if self.op == "read" else "<-"
        if self.block:
            shown = ("----" if self.words is None
                     else " ".join(f"0x{w:04X}" for w in self.words))
            text = f"{self.op}B{self.count:<3} 0x{self.addr:04X} {arrow} {shown}"
        else:
            shown = "----" if self.value is None else f"0x{self.value:0{self.width // 4}X}"
            text = f"{self.op}{self.width:<2} 0x{self.addr:04X} {arrow} {shown}"
        return f"{text}  !! {self.error}" if self.error else text


class SpyBus(BusBase):
    """Wrap ``bus`` and record every access.

    :param bus: any RegisterBus
    :param logger: where to log each access at DEBUG level (None: only the list)
    :param keep: keep at most this many accesses in :attr:`log` (None: all)
    """

    def __init__(self, bus: RegisterBus, *, logger: logging.Logger | None = _log,
                 keep: int | None = 100_000) -> None:
        self.bus = bus
        self.logger = logger
        self.keep = keep
        self.log: list[Access] = []

    def _record(self, access: Access) -> None:
        self.log.append(access)
        if self.keep is not None and len(self.log) > self.keep:
            del self.log[: len(self.log) - self.keep]
        if self.logger is not None and self.logger.isEnabledFor(logging.DEBUG):
            self.logger.debug("%s", access)

    def _read(self, fn, addr: int, width: int) -> int:
        try:
            value = fn(addr)
        except Exception as err:
            self._record(Access("read", width, addr, None, str(err)))
            raise
        self._record(Access("read", width, addr, value))
        return value

    def _write(self, fn, addr: int, value: int, width: int) -> None:
        try:
            fn(addr, value)
        except Exception as err:
            self._record(Access("write", width, addr, value, str(err)))
            raise
        self._record(Access("write", width, addr, value))

    def read8(self, addr: int) -> int:
        return self._read(self.bus.read8, addr, 8)

    def read16(self, addr: int) -> int:
        return self._read(self.bus.read16, addr, 16)

    def write8(self, addr: int, value: int) -> None:
        self._write(self.bus.write8, addr, value, 8)

    def write16(self, addr: int, value: int) -> None:
        self._write(self.bus.write16, addr, value, 16)

    def read_block16(self, addr: int, n: int) -> list[int]:
        """One block read, recorded as one access with its words."""
        try:
            words = self.bus.read_block16(addr, n)
        except Exception as err:
            self._record(Access("read", 16, addr, None, str(err), None,
                                n if isinstance(n, int) else 0, True))
            raise
        self._record(Access("read", 16, addr, words[0] if words else None, None, tuple(words), n, True))
        return words

    def write_block16(self, addr: int, words: Sequence[int]) -> None:
        """One block write, recorded as one access with its words."""
        shown = tuple(words)
        try:
            self.bus.write_block16(addr, shown)
        except Exception as err:
            self._record(Access("write", 16, addr, None, str(err), shown, len(shown), True))
            raise
        self._record(Access("write", 16, addr, shown[0] if shown else None, None, shown, len(shown), True))

    def clear(self) -> None:
        self.log.clear()

    def describe(self) -> str:
        inner = self.bus.describe() if hasattr(self.bus, "describe") else repr(self.bus)
        return f"spy on {inner}"

    def close(self) -> None:
        if hasattr(self.bus, "close"):
            self.bus.close()

    def __getattr__(self, name: str):
        # Backend extras (the fake rack's boards and step(), a gateway's port ...) pass through.
        if name == "bus":
            raise AttributeError(name)
        return getattr(self.bus, name)



def open_spy_bus(url: str, **kwargs) -> SpyBus:
    """``open_bus("spy+URL")``: open URL and wrap it in a :class:`SpyBus`."""
    if not url.startswith("spy+") or len(url) <= 4:
        raise ValueError(f"spy bus URL must be spy+URL (e.g. spy+fake), not {url!r}")
    from drivers.bus import open_bus  # late: drivers.bus imports this module by name only

    return SpyBus(open_bus(url[4:], **kwargs))
