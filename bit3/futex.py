"""Wake the buffer's readers when the service publishes a frame: a Linux futex on the header.

The Bit3 dual-port RAM had no way to tell the computational chassis that the I/O chassis had
written a frame: its readers polled. Here the service, after each publish
(``Bit3Buffer.set_frame``), wakes every process waiting on the low 32-bit word of the
header's frame counter (a shared, not private, futex: the buffer is a file mapping, so
waiters in any process, through any mapping of it, are found by the kernel). A reader that
wants the next frame (the live controller's pacer) reads that word, checks that the frame
it has is still the newest, and waits for the word to change: one wake-up per frame at the
moment of the publish, instead of polling every 50 us through the end of the service's frame
work (~7 sleeps and wake-ups a frame, each ~25-40 us of CPU on the 2-core dev VM).

The futex system call is reached through ctypes (the standard library has no binding). Its
number differs per architecture: the table below names the ones this project runs on; on
any other machine (or a non-Linux system) :data:`AVAILABLE` is False and readers poll as
before. A wait is always bounded by its time-out, so a service that stops (no more wakes)
costs a reader its time-out, never a hang; a futex on a mapping that is gone returns EFAULT,
not a crash.
"""

from __future__ import annotations

import ctypes
import errno
import platform
import sys

#: futex(2) system call numbers (Linux ``asm/unistd.h`` of each architecture)
_SYS_FUTEX = {"x86_64": 202, "aarch64": 98, "riscv64": 98, "ppc64le": 221, "armv7l": 240, "i686": 240}
_FUTEX_WAIT, _FUTEX_WAKE = 0, 1  # shared (no FUTEX_PRIVATE_FLAG): waiters in other processes
_INT_MAX = 0x7FFFFFFF

WOKEN, CHANGED, TIMED_OUT = "woken", "changed", "timed out"


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


def _load():
    nr = _SYS_FUTEX.get(platform.machine())
    if nr is None or not sys.platform.startswith("linux"):
        return None, None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        call = libc.syscall
    except (OSError, AttributeError):
        return None, None
    call.restype = ctypes.c_long
    call.argtypes = [ctypes.c_long, ctypes.c_void_p, ctypes.c_int, ctypes.c_int, ctypes.c_void_p,
                     ctypes.c_void_p, ctypes.c_int]
    return nr, call


_NR, _syscall = _load()
#: whether futex waits and wakes work on this machine (else readers poll)
AVAILABLE = _syscall is not None


def wake(addr: int) -> int:
    """Wake every waiter on the 32-bit word at ``addr``; returns how many were waiting
    (-1 where futexes are not available or the call failed)."""
    if _syscall is None:
        return -1
    return int(_syscall(_NR, addr, _FUTEX_WAKE, _INT_MAX, None, None, 0))


def wait(addr: int, expected: int, timeout_s: float) -> str:
    """Sleep while the 32-bit word at ``addr`` still holds ``expected`` (its low 32 bits),
    at most ``timeout_s``. Returns :data:`WOKEN` (a wake came), :data:`CHANGED` (the word
    already differed: nothing to wait for) or :data:`TIMED_OUT` (also for a signal's
    interruption, which the caller's loop treats like a time-out: it looks again)."""
    if _syscall is None:
        raise OSError(errno.ENOSYS, "futex is not available on this machine")
    if timeout_s <= 0:
        return TIMED_OUT
    sec = int(timeout_s)
    ts = _Timespec(sec, int((timeout_s - sec) * 1e9))
    r = _syscall(_NR, addr, _FUTEX_WAIT, ctypes.c_int32(expected & 0xFFFFFFFF).value, ctypes.byref(ts), None, 0)
    if r == 0:
        return WOKEN
    err = ctypes.get_errno()
    if err == errno.EAGAIN:
        return CHANGED
    if err in (errno.ETIMEDOUT, errno.EINTR):
        return TIMED_OUT
    raise OSError(err, f"futex wait: {errno.errorcode.get(err, err)}")
