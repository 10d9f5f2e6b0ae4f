"""The address of a remote Bit3 buffer (``zenoh://HOST:PORT/NAME``), parsed without importing
Zenoh: every tool that takes ``--buffer`` asks it (tools/attach.py), the bridge's tools too."""

from __future__ import annotations

from pfma.errors import PfmaError

#: a buffer name read through a bridge: zenoh://HOST:PORT/NAME
REMOTE_PREFIX = "zenoh://"


def remote_target(name: str) -> tuple[str, str] | None:
    """``("tcp/HOST:PORT", NAME)`` for ``zenoh://HOST:PORT/NAME``; None for a shared-memory name.

    :raises PfmaError: a zenoh:// name of another shape
    """
    if not name.startswith(REMOTE_PREFIX):
        return None
    where, _, buffer = name[len(REMOTE_PREFIX):].partition("/")
    host, _, port = where.rpartition(":")
    if not host or not port.isdigit() or not buffer:
        raise PfmaError(f"--buffer {name!r}: a remote buffer is zenoh://HOST:PORT/NAME "
                        f"(e.g. zenoh://127.0.0.1:7447/pfma)")
    return f"tcp/{host}:{port}", buffer
