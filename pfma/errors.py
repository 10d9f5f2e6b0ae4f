"""The project's exception tree. Messages name the channel, board and address."""

from __future__ import annotations

import difflib
from collections.abc import Iterable


def did_you_mean(name: str, known: Iterable[str], n: int = 3, cutoff: float = 0.6) -> str:
    """``"; did you mean a, b?"`` for the known names closest to a mistyped ``name``, or ""
    (every tool's message for an unknown signal, board, field or variable ends with it)."""
    close = difflib.get_close_matches(name, list(known), n=n, cutoff=cutoff)
    return f"; did you mean {', '.join(close)}?" if close else ""


class PfmaError(Exception):
    """Base of every error this project raises on purpose."""


class BusError(PfmaError, OSError):
    """A bus access nobody answered (the I/O processor's 115 us VME bus time-out).

    :param addr: absolute A16 address of the access
    :param width: 8 or 16 (bits)
    :param op: ``"read"`` or ``"write"``
    :param board: name of the board expected there, if known
    :param register: register name, if known
    """

    def __init__(self, addr: int, width: int, op: str, board: str | None = None,
                 register: str | None = None, reason: str = "no answer") -> None:
        self.addr = addr
        self.width = width
        self.op = op
        self.board = board
        self.register = register
        self.reason = reason
        where = f"A16 0x{addr:04X}"
        if board:
            where = f"{board} {register or 'register'} at {where}" if register else f"{board} at {where}"
        super().__init__(f"bus error: {op}{width} {where}: {reason}")

    def with_context(self, board: str, register: str | None) -> "BusError":
        """Return a copy that names the board and register (drivers add what they know)."""
        return BusError(self.addr, self.width, self.op, board, register, self.reason)


class AlignmentError(BusError, ValueError):
    """A 16-bit access at an odd address, or an 8-bit access a backend cannot express.

    Both a :class:`BusError` (the access did not happen; same ``addr/width/op``) and a
    ``ValueError`` (it is the caller's bug: a 68000 raises an address error before
    any bus cycle starts). Raised by the Modbus and device-file buses; the fake rack
    raises a plain ``BusError`` for the same access.
    """

    def with_context(self, board: str, register: str | None) -> "AlignmentError":
        return AlignmentError(self.addr, self.width, self.op, board, register, self.reason)


class BoardError(PfmaError):
    """A board answered but is not doing what it must (stuck busy bit, bad status)."""


class BoardInitError(BoardError):
    """A board failed its initialisation sequence."""


class ConfigError(PfmaError, ValueError):
    """Invalid configuration; the message names the file and line where it can."""


class CalibrationError(PfmaError, ValueError):
    """Invalid or unusable calibration data."""


class LinkError(PfmaError, IOError):
    """A serial/CAN/HID link failed (disconnect, repeated framing errors)."""


class PfmaTimeoutError(PfmaError, TimeoutError):
    """A bounded wait ran out."""


def os_error_text(err: OSError) -> str:
    """``strerror: filename`` of an OSError (``str(err)`` when it has neither), as ``pfma``
    names a file it could not read or write."""
    text = err.strerror or str(err) or type(err).__name__
    names = [n for n in (err.filename, err.filename2) if n is not None]
    return ": ".join([text, *map(str, names)])
