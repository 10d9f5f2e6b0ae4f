"""Helpers shared by the fakes and their tests: traffic checks and the stuck-bit fault.

``assert_register_writes(fake, expected)`` compares the writes in a fake's traffic log
with an expected sequence and, on a mismatch, prints both with register names, so an
init-sequence test failure reads like a bus analyser trace.
"""

from __future__ import annotations

import operator
from collections.abc import Iterable, Sequence

from drivers.registers import BoardDescription, register_name


def register_writes(fake, width: int | None = 16, since: int = 0) -> list[tuple[int, int]]:
    """``(offset, value)`` of every write in ``fake.traffic[since:]`` (of one width, or all)."""
    return [(off, val) for op, w, off, val in fake.traffic[since:]
            if op == "w" and (width is None or w == width)]


def format_traffic(fake, entries: Iterable[tuple] | None = None) -> str:
    """One line per access: ``w16 +0x00 DAC[0] = 0x0800``."""
    desc = fake.description
    name_of = getattr(fake, "access_name", None)  # boards whose registers overlay (VMIVME-4100)
    rows = fake.traffic if entries is None else entries
    lines = []
    for op, width, off, val in rows:
        reg = name_of(op, off, val) if name_of else register_name(desc, off)
        lines.append(f"{op}{width} +0x{off:02X} {reg:<10} = 0x{val:04X}")
    return "\n".join(lines)


def assert_register_writes(fake, expected: Sequence[tuple[int | str, int]], *,
                           width: int | None = 16, since: int = 0) -> None:
    """Assert that the fake saw exactly these writes, in order.

    :param expected: ``(offset or register name, value)`` pairs; a name such as ``"CTRL"``
        or ``"DAC[3]"`` is looked up in the fake's description
    :param since: index in ``fake.traffic`` to start from (``len(fake.traffic)`` taken earlier)
    :raises AssertionError: listing expected and actual writes with register names
    """
    desc = fake.description
    want = [(register_offset(desc, reg), value) for reg, value in expected]
    got = register_writes(fake, width, since)
    if got != want:
        w = width or 16
        raise AssertionError(
            f"{fake.name}: register writes differ\nexpected:\n"
            + format_traffic(fake, [("w", w, o, v) for o, v in want])
            + "\nactual:\n" + format_traffic(fake, [("w", w, o, v) for o, v in got]))


def register_offset(desc: BoardDescription, register: int | str) -> int:
    """Byte offset of ``register``: an int offset, a name (``"CH0"``, ``"STATUS"``) or an
    indexed name of a register array (``"DAC[3]"``, ``"SCAN[31]"``).

    :raises KeyError: unknown name; ValueError: offset outside the window
    """
    if isinstance(register, str):
        name, _, index = register.partition("[")
        reg = desc.reg(name)
        return reg.addr(int(index.rstrip("]")) if index else 0)
    off = operator.index(register)
    if not 0 <= off < desc.window:
        raise ValueError(f"{desc.kind}: offset 0x{off:X} outside the 0x{desc.window:X}-byte window")
    return off


class StuckBits:
    """The ``stuck_bit`` fault: data bits of given registers forced to 0 or 1.

    A fake calls :meth:`add` from ``inject("stuck_bit", register=..., bit=..., value=...)``
    and :meth:`apply` on the word of the affected register (on read, or on the latch
    it feeds). Several stuck bits may be active at once.
    """

    def __init__(self, desc: BoardDescription) -> None:
        self.desc = desc
        self._by_offset: dict[int, tuple[int, int]] = {}  # offset -> (mask, forced bits)
        #: words the stuck bits changed (read, or latched): 0 means a run with them looked
        #: bit for bit like a healthy one (each stuck bit only ever held its true value)
        self.altered = 0

    def add(self, register: int | str = 0, bit: int = 0, value: int = 1) -> None:
        off = register_offset(self.desc, register)
        if not 0 <= bit < 16:
            raise ValueError(f"stuck_bit: bit {bit} outside 0..15")
        if value not in (0, 1):
            raise ValueError(f"stuck_bit: value must be 0 or 1, not {value!r}")
        mask, forced = self._by_offset.get(off, (0, 0))
        m = 1 << bit
        self._by_offset[off] = (mask | m, (forced & ~m) | (m if value else 0))

    def clear(self) -> None:
        self._by_offset.clear()
        self.altered = 0

    def __bool__(self) -> bool:
        return bool(self._by_offset)

    def apply(self, offset: int, word: int) -> int:
        """``word`` with the bits stuck at ``offset`` forced."""
        entry = self._by_offset.get(offset)
        if entry is None:
            return word
        mask, forced = entry
        out = (word & ~mask) | forced
        if out != word:
            self.altered += 1
        return out


def fake_rack_of_kinds(kinds: Iterable[str], clock=None, rack=None):
    """``FakeRack.from_config`` restricted to boards of the given kinds (default rack file),
    for tests of some boards that must not depend on every other board's fake."""
    import dataclasses

    from fakes.rack import FakeRack
    from pfma.rack import load_rack

    cfg = rack if rack is not None else load_rack()
    wanted = set(kinds)
    sub = dataclasses.replace(cfg, boards=tuple(b for b in cfg.boards if b.kind in wanted))
    return FakeRack.from_config(sub, clock=clock)
