"""A process root's logging for as long as it runs (:func:`pfma.log.configure`), undone when
it returns: a verb run in-process (the tests, a verb that starts another) leaves no handler
behind writing to a stream that is gone, and no library's level changed."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

from pfma.log import configure


@contextlib.contextmanager
def process_logging(prog: str, level: str, *, hush: tuple[str, ...] = ()) -> Iterator[logging.Handler]:
    """``PROG: message`` logging at ``level`` while the block runs.

    :param hush: loggers of libraries whose own chatter the process words itself (the Modbus
        client's connection retries: the service names the board that failed): only CRITICAL
        from them, unless ``level`` is debug
    """
    root = logging.getLogger()
    before = root.level
    hushed = {name: logging.getLogger(name).level for name in ("pymodbus", "zenoh", "asyncio", "matplotlib",
                                                                "PIL", *hush)}
    handler = configure(prog, level)
    if level != "debug":
        for name in hush:
            logging.getLogger(name).setLevel(logging.CRITICAL)
    try:
        yield handler
    finally:
        root.removeHandler(handler)
        root.setLevel(before)
        for name, lvl in hushed.items():
            logging.getLogger(name).setLevel(lvl)
