"""Board descriptions as data: one table per board, read by its driver, its fake and the docs.

Every entry carries its provenance (``source``): ``"sourced: ..."``, ``"inferred: ..."``
or ``"assumed: ..."``. ``pfma regs`` lists them, so every assumption about a board
is visible in one place and can be corrected in one edit.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass, field
from functools import cached_property


@dataclass(frozen=True)
class Field:
    """A bit field inside a register."""

    name: str  #: snake_case field name
    lsb: int  #: lowest bit
    bits: int = 1  #: width in bits
    doc: str = ""

    @cached_property
    def mask(self) -> int:
        """The field's bits in place (computed once: drivers and fakes test it per access)."""
        return ((1 << self.bits) - 1) << self.lsb

    def get(self, word: int) -> int:
        return (word >> self.lsb) & ((1 << self.bits) - 1)

    def put(self, word: int, value: int) -> int:
        if not 0 <= value < (1 << self.bits):
            raise ValueError(f"field {self.name}: value {value} does not fit {self.bits} bits")
        return (word & ~self.mask) | (value << self.lsb)


@dataclass(frozen=True)
class Register:
    """One register at a byte offset from the board base."""

    name: str
    offset: int  #: byte offset from the board base
    width: int  #: 8 or 16 bits
    access: str  #: "r", "w" or "rw"
    reset: int = 0  #: value after reset
    fields: tuple[Field, ...] = ()
    doc: str = ""
    source: str = "sourced"  #: provenance: sourced / inferred / assumed, with a reference
    count: int = 1  #: >1 for an array of registers at offset + i*width/8

    def field(self, name: str) -> Field:
        for f in self.fields:
            if f.name == name:
                return f
        raise KeyError(f"register {self.name} has no field {name!r}")

    def addr(self, index: int = 0) -> int:
        """Byte offset of element ``index`` (for register arrays)."""
        if not 0 <= index < self.count:
            raise IndexError(f"{self.name}[{index}] out of range 0..{self.count - 1}")
        return self.offset + index * (self.width // 8)


@dataclass(frozen=True)
class BoardDescription:
    """Everything software needs to know about one kind of board."""

    kind: str  #: short key used in the rack TOML, e.g. "vmivme4100"
    title: str  #: human name, e.g. "VMIC VMIVME-4100 16-channel 12-bit DAC"
    window: int  #: bytes decoded from the base address
    registers: tuple[Register, ...]
    byte_lanes: str = "word"  #: "word" (D16 board) or "odd" (8-bit chip on odd bytes)
    constants: dict = field(default_factory=dict)  #: scaling and timing constants
    assumptions: tuple[str, ...] = ()  #: every modelling choice not backed by a source

    def reg(self, name: str) -> Register:
        for r in self.registers:
            if r.name == name:
                return r
        raise KeyError(f"{self.kind} has no register {name!r}")

    def register_at(self, offset: int) -> Register | None:
        for r in self.registers:
            span = r.count * (r.width // 8)
            if r.offset <= offset < r.offset + span:
                return r
        return None


def register_name(desc: BoardDescription, offset: int) -> str:
    """Name of the register at ``offset`` (with array index), for error messages."""
    r = desc.register_at(offset)
    if r is None:
        return f"+0x{offset:02X}"
    if r.count > 1:
        return f"{r.name}[{(offset - r.offset) // (r.width // 8)}]"
    return r.name


def check_channel(board: str, base: int, channel: int, n_channels: int) -> int:
    """``channel`` as an int in 0..n_channels-1, or ValueError naming board and address."""
    try:
        ch = operator.index(channel)
    except TypeError:
        ch = -1
    if not 0 <= ch < n_channels:
        raise ValueError(f"{board} (A16 0x{base:04X}): channel {channel!r} "
                         f"out of range 0..{n_channels - 1}")
    return ch
