"""One logging configuration for every pfma process (issue 31 item 5).

Libraries log through ``logging.getLogger(__name__)`` (or a named logger) and never print
to stderr; the process's composition root calls :func:`configure` once, from ``--log-level``.

Formats, chosen from where stderr goes:

- a terminal or a pipe: ``PROG: message`` -- the same terse line the tools printed before
  logging came in, so operators (and tests that read stderr) see what they always saw;
- systemd's journal (``JOURNAL_STREAM`` names stderr's device and inode, as systemd sets it
  for a unit whose StandardError is the journal): ``<N>PROG: message``, the sd-daemon(3)
  priority prefix that journald reads as the line's priority (3 error, 4 warning, 6 info,
  7 debug), so ``journalctl -p warning -u pfma-serve`` finds the trips.

``PROG`` is the process's name (``pfma serve``), given once to :func:`configure`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from collections.abc import Iterator
from typing import TextIO

LEVELS = ("debug", "info", "warning", "error")
DEFAULT_LEVEL = "info"

# sd-daemon(3) priorities: the journal reads "<N>" at the start of a line as its priority
_SD_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3,
                logging.CRITICAL: 2}

_HANDLER_NAME = "pfma"
#: libraries whose chatter stays out of the operator's stream (WARNING and up only)
_NOISY = ("pymodbus", "zenoh", "asyncio", "matplotlib", "PIL")


def to_journal(stream: TextIO) -> bool:
    """True when ``stream`` is the journal's stream socket (systemd sets ``JOURNAL_STREAM``
    to ``DEVICE:INODE`` of the stderr it connected)."""
    want = os.environ.get("JOURNAL_STREAM", "")
    if not want:
        return False
    try:
        st = os.fstat(stream.fileno())
    except (OSError, ValueError, AttributeError):
        return False
    return want == f"{st.st_dev}:{st.st_ino}"


class TerseFormatter(logging.Formatter):
    """``PROG: message``, with the journal's ``<N>`` priority prefix when ``journal``."""

    def __init__(self, prog: str, journal: bool = False) -> None:
        super().__init__()
        self.prog = prog
        self.journal = journal

    def format(self, record: logging.LogRecord) -> str:
        text = record.getMessage()
        if record.exc_info and record.levelno >= logging.ERROR:
            text = f"{text}\n{self.formatException(record.exc_info)}"
        prefix = getattr(record, "prog", None) or self.prog
        line = f"{prefix}: {text}" if prefix else text
        if self.journal:
            pri = _SD_PRIORITY.get(record.levelno, 6)
            line = "\n".join(f"<{pri}>{part}" for part in line.split("\n"))
        return line


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time of each record (a test's capture, a
    redirected stream), never to a stream that was closed after :func:`configure`."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:  # StreamHandler's own assignments: stderr is looked up instead
        pass


def level_number(name: str) -> int:
    """The logging level for ``--log-level NAME`` (one of :data:`LEVELS`)."""
    if name.lower() not in LEVELS:
        raise ValueError(f"--log-level {name!r}: one of {', '.join(LEVELS)}")
    return int(getattr(logging, name.upper()))


def configure(prog: str, level: str = DEFAULT_LEVEL, stream: TextIO | None = None) -> logging.Handler:
    """Send every pfma logger's records at ``level`` and above to ``stream`` (stderr) in the
    terse format (``stream`` None: ``sys.stderr`` as it is at each record). Called once per
    process by its composition root; calling it again replaces the handler (tests, and a verb
    that starts another)."""
    out = stream if stream is not None else sys.stderr
    handler: logging.StreamHandler = logging.StreamHandler(out) if stream is not None else _StderrHandler()
    handler.set_name(_HANDLER_NAME)
    handler.setFormatter(TerseFormatter(prog, journal=to_journal(out)))
    root = logging.getLogger()
    for old in [h for h in root.handlers if h.get_name() == _HANDLER_NAME]:
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level_number(level))
    # third-party chatter stays out of the operator's stream unless asked for
    for noisy in _NOISY:
        logging.getLogger(noisy).setLevel(max(logging.WARNING, root.level))
    return handler


@contextlib.contextmanager
def for_process(prog: str, level: str, *, hush: tuple[str, ...] = ()) -> Iterator[logging.Handler]:
    """A process root's logging (:func:`configure`) while the block runs, undone when it
    ends: a verb run in-process (the tests, a verb that starts another) leaves no handler
    and no library's level changed behind it.

    :param hush: loggers of libraries whose own chatter the process words itself (the Modbus
        client's connection retries: the service names the board that failed): only CRITICAL
        from them, unless ``level`` is debug
    """
    root = logging.getLogger()
    before = root.level
    levels = {name: logging.getLogger(name).level for name in (*_NOISY, *hush)}
    handler = configure(prog, level)
    if level != "debug":
        for name in hush:
            logging.getLogger(name).setLevel(logging.CRITICAL)
    try:
        yield handler
    finally:
        root.removeHandler(handler)
        root.setLevel(before)
        for name, lvl in levels.items():
            logging.getLogger(name).setLevel(lvl)


def add_argument(parser) -> None:
    """``--log-level`` on a verb's parser (argparse)."""
    parser.add_argument("--log-level", default=DEFAULT_LEVEL, choices=LEVELS, metavar="LEVEL",
                        help=f"what the process says on stderr: {', '.join(LEVELS)} (default {DEFAULT_LEVEL})")
