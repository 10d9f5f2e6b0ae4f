"""Shared-memory files get their pages up front (issue 29 item 8).

A file in ``/dev/shm`` (tmpfs) that is only ``ftruncate``-d has no pages yet: the first
store to a page tmpfs cannot supply kills the process with SIGBUS (exit 135, no message),
possibly long after start-up. :func:`reserve` allocates every page with
``posix_fallocate`` right after the file is created, before it is mapped or written, so a
full ``/dev/shm`` is a one-line :class:`ShmFullError` at start-up, and the caller removes
what it created.
"""

from __future__ import annotations

import errno
import os

from bit3.seqlock import Bit3Error

#: errors that mean "no room" (``posix_fallocate``'s ENOSPC, EFBIG beyond a size limit)
_NO_ROOM = (errno.ENOSPC, errno.EFBIG, errno.EDQUOT)


class ShmFullError(Bit3Error):
    """The shared-memory file system has no room for a segment."""


def _size(n: int) -> str:
    for unit, scale in (("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}".replace(".0 ", " ")
    return f"{n} bytes"


def free_bytes(path: str) -> int | None:
    """Bytes this user may still allocate on the file system holding ``path`` (None: unknown)."""
    try:
        st = os.statvfs(os.path.dirname(path) or ".")
    except OSError:
        return None
    return st.f_bavail * st.f_frsize


def reserve(fd: int, size: int, path: str, what: str) -> None:
    """Allocate ``size`` bytes of ``fd`` (the file ``path``, described as ``what``) now.

    A file system without ``posix_fallocate`` (EOPNOTSUPP, EINVAL) gets its pages written
    with zeros instead (the equivalent: tmpfs allocates a page on its first write).

    :raises ShmFullError: no room; one line naming the size needed and what is free
    """
    try:
        try:
            os.posix_fallocate(fd, 0, size)
        except OSError as err:
            if err.errno not in (errno.EOPNOTSUPP, errno.EINVAL):
                raise
            zeros = bytes(min(size, 1 << 16))
            for off in range(0, size, len(zeros)):
                os.pwrite(fd, zeros[:size - off], off)
    except OSError as err:
        if err.errno not in _NO_ROOM:
            raise
        free = free_bytes(path)
        has = f"has {_size(free)} free" if free is not None else "is full"
        where = os.path.dirname(path) or "."
        raise ShmFullError(f"no room for {what} ({path}): it needs {_size(size)}, {where} {has} "
                           f"({err.strerror}); free space there or make it larger") from None
