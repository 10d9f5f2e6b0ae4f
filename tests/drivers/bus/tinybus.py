"""A tiny in-test RegisterBus: 64 KiB of words with a dead and a broken region.

Used where a test needs to see exactly which accesses a backend made (the Modbus
gateway's one-read-per-requested-register rule, write8 without read-modify-write).
"""

from __future__ import annotations

import logging
import socket
from contextlib import contextmanager

from pfma.errors import BusError

DEAD = range(0x8000, 0x9000)  #: nobody answers here (BusError)
BROKEN = range(0x9000, 0x9100)  #: the bus itself fails here (not a BusError)


class TinyBus:
    def __init__(self) -> None:
        self.words: dict[int, int] = {}
        self.log: list[tuple[str, int, int]] = []  # (op, addr, value)

    def read16(self, addr: int) -> int:
        if addr in DEAD:
            raise BusError(addr, 16, "read", reason="nobody home")
        if addr in BROKEN:
            raise RuntimeError("tiny bus broke")
        value = self.words.get(addr, 0)
        self.log.append(("r", addr, value))
        return value

    def write16(self, addr: int, value: int) -> None:
        if addr in DEAD:
            raise BusError(addr, 16, "write", reason="nobody home")
        if addr in BROKEN:
            raise RuntimeError("tiny bus broke")
        self.log.append(("w", addr, value))
        self.words[addr] = value

    def read_block16(self, addr: int, n: int) -> list[int]:
        return [self.read16(addr + 2 * i) for i in range(n)]

    def write_block16(self, addr: int, words) -> None:
        for i, w in enumerate(words):
            self.write16(addr + 2 * i, w)

    def read8(self, addr: int) -> int:
        word = self.read16(addr & ~1)
        return word & 0xFF if addr & 1 else word >> 8

    def write8(self, addr: int, value: int) -> None:
        raise BusError(addr, 8, "write", reason="tiny bus has no byte lanes")


@contextmanager
def quiet_pymodbus():
    """pymodbus logs refused connections and exception replies at error level."""
    logger = logging.getLogger("pymodbus")
    old = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(old)


def free_port() -> int:
    """A loopback port nobody listens on (bound then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
