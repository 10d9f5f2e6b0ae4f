"""What the bus backends share: the alignment check, block transfers made of single
cycles, ``close`` and the context manager (:class:`BusBase`); byte accesses made of word
accesses, for a backend that can only move words (:class:`WordBus`, the Modbus gateway).

The contract itself (:class:`drivers.bus.RegisterBus`) stays a protocol: drivers never
check a bus's class, and a bus need not derive from these (the fake rack does not).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Self

from drivers.bus import check_addr, check_block, check_value, check_words
from pfma.errors import AlignmentError

__all__ = ["BusBase", "WordBus"]


class BusBase:
    """Base of a bus backend: subclasses give ``read8/read16/write8/write16`` (and
    ``describe``); the block transfers default to one single cycle per word, in address
    order, after the checks of the whole block (a backend with a faster way overrides
    them); ``close`` defaults to nothing; ``with bus:`` closes it."""

    @staticmethod
    def _even(addr: int, op: str) -> None:
        """ValueError unless ``addr`` is an A16 address; AlignmentError (a BusError and a
        ValueError) for an odd one: the check of every 16-bit access."""
        check_addr(addr)
        if addr % 2:
            raise AlignmentError(addr, 16, op, reason="16-bit access at an odd address")

    # -- RegisterBus: the part a subclass gives -------------------------------------------
    def read16(self, addr: int) -> int:
        raise NotImplementedError

    def write16(self, addr: int, value: int) -> None:
        raise NotImplementedError

    # -- block transfers ----------------------------------------------------------------------
    def _read_singly(self, addrs: Sequence[int]) -> list[int]:
        """One ``read16`` per address, in order."""
        return [self.read16(a) for a in addrs]

    def _write_singly(self, addrs: Sequence[int], values: Sequence[int]) -> None:
        """One ``write16`` per (address, value), in order."""
        for a, v in zip(addrs, values):
            self.write16(a, v)

    def read_block16(self, addr: int, n: int) -> list[int]:
        """The ``n`` words from even ``addr`` on, one ``read16`` each (checks first)."""
        check_block(addr, n, "read")
        return self._read_singly([addr + 2 * i for i in range(n)])

    def write_block16(self, addr: int, words: Sequence[int]) -> None:
        """Write ``words`` (all checked first) from even ``addr`` on, one ``write16`` each."""
        values = check_words(addr, words)
        self._write_singly([addr + 2 * i for i in range(len(values))], values)

    # -- lifetime -----------------------------------------------------------------------------
    def close(self) -> None:
        """Release the backend's connection or mapping (nothing by default)."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class WordBus(BusBase):
    """A backend that moves only 16-bit words (the Modbus gateway): subclasses give
    ``_read_word(addr, width)`` (the word at ``addr & ~1``) and ``_write_word(addr, word,
    width)`` (one word at ``addr & ~1``); ``width`` is the width of the access asked for,
    for the error messages.

    - ``read8(addr)`` reads the word at ``addr & ~1`` and returns its high byte for an
      even ``addr``, its low byte for an odd one;
    - ``write8(addr, v)`` at an odd ``addr`` writes the word ``0x00 << 8 | v``, with no
      read first (reading an 8-bit chip register has side effects); at an even ``addr``
      it cannot be expressed (it would also write the odd byte) and is an
      AlignmentError before any access.
    """

    def _read_word(self, addr: int, width: int) -> int:
        raise NotImplementedError

    def _write_word(self, addr: int, word: int, width: int) -> None:
        raise NotImplementedError

    def read16(self, addr: int) -> int:
        """The word at even A16 ``addr``."""
        self._even(addr, "read")
        return self._read_word(addr, 16)

    def read8(self, addr: int) -> int:
        """The byte at ``addr``: the high byte of its word for even, the low byte for odd."""
        check_addr(addr)
        word = self._read_word(addr, 8)
        return word & 0xFF if addr % 2 else word >> 8

    def write16(self, addr: int, value: int) -> None:
        """Write the word at even A16 ``addr``."""
        check_addr(addr)
        value = check_value(addr, value, 16)
        self._even(addr, "write")
        self._write_word(addr, value, 16)

    def write8(self, addr: int, value: int) -> None:
        """Write the byte at odd A16 ``addr`` as the word ``0x00 << 8 | value`` (no read first)."""
        check_addr(addr)
        value = check_value(addr, value, 8)
        if addr % 2 == 0:
            raise AlignmentError(addr, 8, "write", reason="an even-byte write cannot be expressed over "
                                 "Modbus (it would also write the odd byte)")
        self._write_word(addr, value, 8)
