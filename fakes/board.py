"""Base class of every register-level fake board.

A fake is addressed by **byte offset from its base**. It knows one board's
registers (from the board description the driver also uses) and the physics
behind them, never a driver. Bus-side methods raise :class:`NoAnswer` for an
access the board does not decode; the rack turns that into a ``BusError`` that
names the board, register and absolute address.

Every fake offers:

- physical-side hooks (per board: set a resolver angle, an ADC input voltage ...);
- ``inject(fault, **kw)`` / ``clear(fault)`` for named faults; ``"no_answer"`` is
  common to all boards and makes every access a bus error (``no_answer`` with
  ``offset=N``: only accesses to the 16-bit word holding byte offset N go unanswered, as
  a register whose decode or data path has failed; repeat for more registers);
- ``traffic``: a log of ``(op, width, offset, value)`` tuples that tests compare
  with init sequences (``fakes.testing``);
- ``read_block16/write_block16``: consecutive words in ONE call (the rack routes a bus
  block transfer here). The default loops over :meth:`read16`/:meth:`write16`, so every
  word has its register's side effects and its traffic entry; a board may override
  them with a cheaper slice where its model allows (same result word for word).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from drivers.registers import BoardDescription
from pfma.clock import Clock, SimClock


class NoAnswer(Exception):
    """Raised by a fake board for an access it does not decode (becomes BusError)."""

    def __init__(self, reason: str = "no answer") -> None:
        super().__init__(reason)
        self.reason = reason
        self.offset: int | None = None  #: the failing word's offset, set by the block transfers


class FakeBoard:
    """Register-level fake of one board. Subclasses set ``description`` and
    implement ``_read8/_read16/_write8/_write16`` (offsets relative to the base).
    """

    description: BoardDescription

    def __init__(self, name: str | None = None, clock: Clock | None = None) -> None:
        self.name = name or self.description.kind
        self.clock = clock if clock is not None else SimClock()
        self.faults: dict[str, dict] = {}
        self.traffic: list[tuple[str, int, int, int]] = []
        self.log_traffic = True

    # -- faults ---------------------------------------------------------------
    @property
    def stuck_bits_altered(self) -> int | None:
        """Words this board's stuck bits changed so far (None: the board has none; 0: they
        never took a value other than the true one, so nothing could tell them)."""
        stuck = getattr(self, "_stuck", None)
        return stuck.altered if stuck else None

    def inject(self, fault: str, **params) -> None:
        """Switch on a named fault (board-specific names, plus ``no_answer``)."""
        known = ("no_answer",) + tuple(getattr(self, "FAULTS", ()))
        if fault not in known:
            raise ValueError(f"{self.name}: unknown fault {fault!r}; known: {', '.join(known)}")
        if fault == "no_answer":
            params = self._no_answer_params(params)
        self.faults[fault] = params

    def _no_answer_params(self, params: dict) -> dict:
        """``no_answer`` alone: the whole board (``{}``); with ``offset=N``: the word holding
        byte N joins the unanswered words (``{"words": frozenset}``); whole-board wins."""
        if "offset" not in params:
            return {}
        off = int(params["offset"])
        if not 0 <= off < self.description.window:
            raise ValueError(f"{self.name}: offset 0x{off:X} outside the board's "
                             f"0x{self.description.window:X}-byte window")
        prev = self.faults.get("no_answer")
        if prev is not None and "words" not in prev:
            return prev  # the whole board is silent already
        words = prev["words"] if prev is not None else frozenset()
        return {"words": words | {off & ~1}}

    def clear(self, fault: str | None = None) -> None:
        """Clear one fault, or all of them."""
        if fault is None:
            self.faults.clear()
        else:
            self.faults.pop(fault, None)

    # -- bus side -----------------------------------------------------------
    def _check(self, offset: int, width: int) -> None:
        if self.faults and "no_answer" in self.faults:
            words = self.faults["no_answer"].get("words")
            if words is None:
                raise NoAnswer("board does not answer (injected fault)")
            if offset & ~1 in words:
                raise NoAnswer("register does not answer (injected fault)")
        if not 0 <= offset < self.description.window:
            raise NoAnswer("outside the board's decoded window")
        if self.description.byte_lanes == "odd" and width == 8 and offset % 2 == 0:
            raise NoAnswer("even byte of an odd-byte board is not decoded")
        if width == 16 and offset % 2:
            raise NoAnswer("16-bit access at an odd address")

    def read8(self, offset: int) -> int:
        self._check(offset, 8)
        v = self._read8(offset) & 0xFF
        if self.log_traffic:
            self.traffic.append(("r", 8, offset, v))
        return v

    def read16(self, offset: int) -> int:
        self._check(offset, 16)
        if self.description.byte_lanes == "odd":
            # Assumed: a D16 cycle to an odd-byte board reaches the chip on D7..D0;
            # the undriven upper lane reads 0xFF. This is what a word-only gateway sees.
            v = 0xFF00 | (self._read8(offset + 1) & 0xFF)
        else:
            v = self._read16(offset) & 0xFFFF
        if self.log_traffic:
            self.traffic.append(("r", 16, offset, v))
        return v

    def write8(self, offset: int, value: int) -> None:
        self._check(offset, 8)
        if self.log_traffic:
            self.traffic.append(("w", 8, offset, value & 0xFF))
        self._write8(offset, value & 0xFF)

    def write16(self, offset: int, value: int) -> None:
        self._check(offset, 16)
        if self.log_traffic:
            self.traffic.append(("w", 16, offset, value & 0xFFFF))
        if self.description.byte_lanes == "odd":
            self._write8(offset + 1, value & 0xFF)
        else:
            self._write16(offset, value & 0xFFFF)

    def read_block16(self, offset: int, n: int, tick: Callable[[], None] | None = None) -> list[int]:
        """``n`` words from ``offset`` on, each exactly as :meth:`read16` (its side effects,
        its traffic entry). ``tick`` (the rack's per-access charge of simulated time) is
        called before each word, as before each single access. A word the board does not
        decode raises :class:`NoAnswer` with ``offset`` set to that word's offset; the
        words before it were read."""
        r16, words = self.read16, []
        off = offset
        try:
            for off in range(offset, offset + 2 * n, 2):
                if tick is not None:
                    tick()
                words.append(r16(off))
        except NoAnswer as err:
            err.offset = off
            raise
        return words

    def write_block16(self, offset: int, words: Sequence[int],
                      tick: Callable[[], None] | None = None) -> None:
        """Write ``words`` from ``offset`` on, each exactly as :meth:`write16` (``tick``
        before each); a word the board does not decode raises :class:`NoAnswer` with its
        ``offset``."""
        w16 = self.write16
        off = offset
        try:
            for i, value in enumerate(words):
                off = offset + 2 * i
                if tick is not None:
                    tick()
                w16(off, value)
        except NoAnswer as err:
            err.offset = off
            raise

    # -- to be implemented by boards -------------------------------------------
    def _read8(self, offset: int) -> int:
        raise NoAnswer("8-bit access not decoded by this board")

    def _write8(self, offset: int, value: int) -> None:
        raise NoAnswer("8-bit access not decoded by this board")

    def _read16(self, offset: int) -> int:
        raise NoAnswer("16-bit access not decoded by this board")

    def _write16(self, offset: int, value: int) -> None:
        raise NoAnswer("16-bit access not decoded by this board")

    # -- simulated time -----------------------------------------------------------
    def step(self, dt_s: float) -> None:
        """Advance the board's physical side by ``dt_s`` (boards with dynamics override)."""
