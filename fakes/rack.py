"""The fake rack: every fake board mapped at its address, behind the RegisterBus contract.

``FakeRack`` is a RegisterBus (absolute A16 addresses). It dispatches each access to
the board whose window holds the address, turns a board's ``NoAnswer`` into a
``BusError`` naming board, register and address, and charges each access
``access_time_s`` of simulated time (a VME short-I/O cycle is about a microsecond),
so a driver polling a busy bit sees simulated time pass.

A block transfer (``read_block16``/``write_block16``) is ONE call into each board it
covers (``FakeBoard.read_block16``): every word keeps its register's side effects and
is charged ``access_time_s`` just before it is accessed, exactly as the same words read
one by one; only the Python cost is one call per board instead of one per word.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import partial

from drivers.bus import check_block, check_value, check_words
from drivers.catalog import board_kind, resolve
from drivers.registers import register_name
from fakes.board import FakeBoard, NoAnswer
from pfma.clock import Clock, SimClock
from pfma.errors import BusError
from pfma.rack import RackConfig, load_rack

def fake_class(kind: str) -> type[FakeBoard]:
    """The register-level fake of a board kind (the catalogue's ``fake`` column)."""
    return resolve(board_kind(kind).fake)


class FakeRack:
    """A register-level rack of fake boards.

    :param clock: simulated (default) or monotonic clock shared by every board
    :param access_time_s: simulated time charged per bus access
    """

    def __init__(self, clock: Clock | None = None, access_time_s: float = 1e-6) -> None:
        self.clock = clock if clock is not None else SimClock()
        self.access_time_s = access_time_s
        # real time passes by itself: only a simulated clock is charged per access
        self._charge = bool(access_time_s) and getattr(self.clock, "simulated", True)
        self._map: list[tuple[int, int, FakeBoard]] = []  # (base, end, board)
        self._pages: dict[int, tuple[FakeBoard, int]] = {}  # addr >> 4 -> (board, base)
        self.boards: dict[str, FakeBoard] = {}
        self.bases: dict[str, int] = {}

    # -- building ---------------------------------------------------------------
    def add(self, base: int, board: FakeBoard) -> FakeBoard:
        end = base + board.description.window
        for b0, b1, other in self._map:
            if base < b1 and b0 < end:
                raise ValueError(f"{board.name} at 0x{base:04X} overlaps {other.name} at 0x{b0:04X}")
        self._map.append((base, end, board))
        self._map.sort(key=lambda e: e[0])
        if base % 16 == 0 and end % 16 == 0:  # every board here; others use the linear search
            for page in range(base >> 4, end >> 4):
                self._pages[page] = (board, base)
        self.boards[board.name] = board
        self.bases[board.name] = base
        return board

    @classmethod
    def from_config(cls, rack: RackConfig | None = None, clock: Clock | None = None,
                    **kwargs) -> "FakeRack":
        rack = rack if rack is not None else load_rack()
        self = cls(clock=clock, **kwargs)
        for b in rack.boards:
            self.add(b.base, fake_class(b.kind)(name=b.name, clock=self.clock))
        return self

    def __getitem__(self, name: str) -> FakeBoard:
        return self.boards[name]

    def describe(self) -> str:
        return "fake a16 rack: " + ", ".join(f"{b.name}@0x{b0:04X}" for b0, _, b in self._map)

    def step(self, dt_s: float) -> None:
        """Advance every board's physical side by ``dt_s`` (does not move the clock)."""
        for _, _, b in self._map:
            b.step(dt_s)

    # -- RegisterBus ------------------------------------------------------------
    def _find(self, addr: int, width: int, op: str) -> tuple[FakeBoard, int]:
        hit = self._pages.get(addr >> 4)
        if hit is not None and addr >= 0:
            if self._charge:
                self.clock.advance(self.access_time_s)
            return hit[0], addr - hit[1]
        if not 0 <= addr <= 0xFFFF:
            raise ValueError(f"A16 address 0x{addr:X} out of range")
        if self._charge:
            self.clock.advance(self.access_time_s)
        for b0, b1, board in self._map:
            if b0 <= addr < b1:
                return board, addr - b0
        raise BusError(addr, width, op, reason="no board decodes this address")

    def _fail(self, err: NoAnswer, board: FakeBoard, off: int, addr: int, width: int, op: str):
        raise BusError(addr, width, op, board.name, register_name(board.description, off),
                       err.reason) from None

    def _span(self, addr: int, op: str) -> tuple[FakeBoard, int, int]:
        """The board decoding ``addr`` (no charge), its base and its window's end; a BusError
        (after charging the one access nobody answers) when no board decodes it."""
        hit = self._pages.get(addr >> 4)
        if hit is not None:
            board, base = hit
            return board, base, base + board.description.window
        for b0, b1, board in self._map:
            if b0 <= addr < b1:
                return board, b0, b1
        if self._charge:
            self.clock.advance(self.access_time_s)
        raise BusError(addr, 16, op, reason="no board decodes this address")

    def _tick(self):
        return partial(self.clock.advance, self.access_time_s) if self._charge else None

    def read_block16(self, addr: int, n: int) -> list[int]:
        """``n`` words from ``addr`` on: one call per board covered, each word charged and
        with its side effects as a single read; BusError names the first word nobody answered."""
        check_block(addr, n, "read")
        tick, out, a, end = self._tick(), [], addr, addr + 2 * n
        while a < end:
            board, base, b_end = self._span(a, "read")
            k = (min(end, b_end) - a) >> 1
            try:
                out += board.read_block16(a - base, k, tick)
            except NoAnswer as err:
                off = err.offset if err.offset is not None else a - base
                self._fail(err, board, off, base + off, 16, "read")
            a += 2 * k
        return out

    def write_block16(self, addr: int, words: Sequence[int]) -> None:
        """Write ``words`` from ``addr`` on (all checked first): one call per board covered."""
        values = check_words(addr, words)
        tick, a, i = self._tick(), addr, 0
        while i < len(values):
            board, base, b_end = self._span(a, "write")
            k = min(len(values) - i, (b_end - a) >> 1)
            try:
                board.write_block16(a - base, values[i:i + k], tick)
            except NoAnswer as err:
                off = err.offset if err.offset is not None else a - base
                self._fail(err, board, off, base + off, 16, "write")
            a += 2 * k
            i += k

    def read8(self, addr: int) -> int:
        board, off = self._find(addr, 8, "read")
        try:
            return board.read8(off)
        except NoAnswer as err:
            self._fail(err, board, off, addr, 8, "read")

    def read16(self, addr: int) -> int:
        board, off = self._find(addr, 16, "read")
        try:
            return board.read16(off)
        except NoAnswer as err:
            self._fail(err, board, off, addr, 16, "read")

    def write8(self, addr: int, value: int) -> None:
        value = check_value(addr, value, 8)
        board, off = self._find(addr, 8, "write")
        try:
            board.write8(off, value)
        except NoAnswer as err:
            self._fail(err, board, off, addr, 8, "write")

    def write16(self, addr: int, value: int) -> None:
        value = check_value(addr, value, 16)
        board, off = self._find(addr, 16, "write")
        try:
            board.write16(off, value)
        except NoAnswer as err:
            self._fail(err, board, off, addr, 16, "write")


def open_fake_bus(url: str = "fake", rack: RackConfig | None = None, clock: Clock | None = None,
                  **kwargs) -> FakeRack:
    """``open_bus("fake")``: the fake rack built from the rack configuration."""
    return FakeRack.from_config(rack, clock=clock, **kwargs)
