"""A RegisterBus on a Linux ``vme_user`` master window (an SBC in the crate, or a
PCI-VME bridge with a Tsi148 or Universe II and Linux's VME drivers).

URL::

    vme:/dev/bus/vme/m0[?am=0x29]

``vme_user`` (drivers/staging/vme_user in the kernel; modules ``vme_tsi148`` or
``vme_ca91cx42``, then ``vme_user``) gives four master windows, ``/dev/bus/vme/m0`` ..
``m3``. Opening the bus:

1. configures the window with the ``VME_SET_MASTER`` ioctl, through
   :func:`drivers.bus.devicefile.vme_user_set_master`: ``enable=1``, ``vme_addr=0``,
   ``size=0x10000`` (the whole A16 space, so bus address = file offset), address
   space ``VME_A16``, cycle ``VME_SCT | VME_USER | VME_DATA`` (AM 0x29) or
   ``VME_SCT | VME_SUPER | VME_DATA`` (AM 0x2D, ``?am=0x2D``), data width ``VME_D16``.
   The window keeps this set-up until the next ``VME_SET_MASTER``. Needs write access
   to the device file (root, or a udev rule for the service user);
2. opens the file and does every access with ``pread``/``pwrite`` at file offset =
   A16 address.

**Assumption (address modifier):** AM 0x29, A16 non-privileged data, as on the caen bus
(:mod:`drivers.bus.caen` names why; ``?am=0x2D`` for boards strapped supervisory only).

Why ``pread``/``pwrite`` and not ``mmap`` (``file:/dev/bus/vme/m0`` maps it, see
:mod:`drivers.bus.devicefile`): the driver copies through its own buffer with the
bridge's 8/16-bit I/O accessors (``vme_master_read``), so a 2-byte ``pread`` at an even
offset is one D16 cycle and a 1-byte one a D08(O)/D08(EO) cycle; and a VME bus error
reaches us as a short count or ``EIO`` (with the Tsi148 driver's ``err_chk=1``)
instead of a ``SIGBUS`` that kills the process. Without ``err_chk`` the driver does
not look for bus errors and an empty address reads as whatever the bridge returns
(typically all ones): load ``modprobe vme_tsi148 err_chk=1``.

Byte order: the window is *address invariant* (the bridge's default; the byte at VME
address A is file byte A), so a word is assembled big-endian from its two bytes, as
in :mod:`drivers.bus.devicefile`.

Blocks: ``read_block16(addr, n)`` is one ``pread`` of ``2n`` bytes and
``write_block16`` one ``pwrite``: one system call; the driver runs D16 cycles (or D32
cycles split into two D16 by the bridge, whose window width is D16) in address order.
A bus error part-way through names the first word not transferred.
"""

from __future__ import annotations

import errno
import os
import struct
import threading
from collections.abc import Callable, Sequence
from typing import Any
from urllib.parse import parse_qsl, urlsplit

from drivers.bus import check_addr, check_block, check_value, check_words
from drivers.bus.base import BusBase
from drivers.bus.devicefile import VME_DATA, VME_SCT, VME_SUPER, VME_USER, vme_user_set_master
from pfma.errors import BusError, LinkError

__all__ = ["VmeUserBus", "open_vme_bus", "AM_CYCLES"]

#: A16 address modifier -> the ``cycle`` bits of ``struct vme_master``
AM_CYCLES: dict[int, int] = {
    0x29: VME_SCT | VME_USER | VME_DATA,  # A16 non-privileged data (the default)
    0x2D: VME_SCT | VME_SUPER | VME_DATA,  # A16 supervisory data
}
A16_SIZE = 0x10000


class VmeUserBus(BusBase):
    """RegisterBus on a ``vme_user`` master window set up for the whole A16 space.

    :param path: the master window (``/dev/bus/vme/m0`` .. ``m3``)
    :param am: 0x29 (default) or 0x2D
    :param set_master: configures the window (default :func:`vme_user_set_master`;
        tests pass a recorder)
    :param pread: ``os.pread`` (tests pass a recorder)
    :param pwrite: ``os.pwrite`` (tests pass a recorder)
    :raises LinkError: when the window cannot be configured or opened
    """

    def __init__(self, path: str, *, am: int = 0x29,
                 set_master: Callable[..., None] = vme_user_set_master,
                 pread: Callable[[int, int, int], bytes] = os.pread,
                 pwrite: Callable[[int, bytes, int], int] = os.pwrite) -> None:
        if am not in AM_CYCLES:
            raise ValueError(f"A16 address modifier must be 0x29 (non-privileged data) or 0x2D "
                             f"(supervisory data), not 0x{am:02X}")
        self.path = path
        self.am = am
        self._pread = pread
        self._pwrite = pwrite
        self._lock = threading.Lock()
        try:
            set_master(path, vme_addr=0, size=A16_SIZE, cycle=AM_CYCLES[am])
        except OSError as err:
            raise LinkError(self._setup_hint(err, "configure (VME_SET_MASTER)")) from err
        try:
            self._fd: int | None = os.open(path, os.O_RDWR | getattr(os, "O_CLOEXEC", 0))
        except OSError as err:
            raise LinkError(self._setup_hint(err, "open")) from err

    def _setup_hint(self, err: OSError, what: str) -> str:
        text = f"cannot {what} the VME master window {self.path}: {err.strerror or err}"
        if err.errno == errno.ENOENT:
            return text + "; load the bridge and vme_user modules (modprobe vme_tsi148 err_chk=1 vme_user)"
        if err.errno in (errno.EACCES, errno.EPERM):
            return text + "; give the service user read/write access to it (a udev rule) or run as root"
        if err.errno in (errno.EINVAL, errno.ENOTTY):
            return text + "; the bridge refused an A16 D16 window of 64 KiB at 0 (is this a vme_user master window?)"
        return text

    # -- helpers ------------------------------------------------------------------
    def _fd_or_fail(self, addr: int, width: int, op: str) -> int:
        if self._fd is None:
            raise BusError(addr, width, op, reason=f"{self.path} is closed")
        return self._fd

    def _io_error(self, addr: int, width: int, op: str, err: OSError) -> BusError:
        if err.errno == errno.EIO:
            return BusError(addr, width, op, reason=f"VME bus error (EIO from {self.path}: no board "
                            f"answered AM 0x{self.am:02X})")
        return BusError(addr, width, op, reason=f"{self.path}: {err.strerror or err}")

    def _read(self, addr: int, nbytes: int, width: int) -> bytes:
        with self._lock:
            fd = self._fd_or_fail(addr, width, "read")
            try:
                data = self._pread(fd, nbytes, addr)
            except OSError as err:
                raise self._io_error(addr, width, "read", err) from err
        if len(data) != nbytes:  # the driver stops at the first bus error (err_chk=1)
            first = addr + (len(data) & ~1 if width == 16 else len(data))
            raise BusError(first, width, "read", reason=f"VME bus error (short read from {self.path}: "
                           f"no board answered AM 0x{self.am:02X})")
        return data

    def _write(self, addr: int, data: bytes, width: int) -> None:
        with self._lock:
            fd = self._fd_or_fail(addr, width, "write")
            try:
                done = self._pwrite(fd, data, addr)
            except OSError as err:
                raise self._io_error(addr, width, "write", err) from err
        if done != len(data):
            first = addr + (done & ~1 if width == 16 else done)
            raise BusError(first, width, "write", reason=f"VME bus error (short write to {self.path}: "
                           f"no board answered AM 0x{self.am:02X})")

    # -- RegisterBus ----------------------------------------------------------------
    def read8(self, addr: int) -> int:
        """One 1-byte ``pread`` at A16 ``addr`` (a D08(O) cycle at an odd address)."""
        check_addr(addr)
        return self._read(addr, 1, 8)[0]

    def read16(self, addr: int) -> int:
        """One 2-byte ``pread`` at even A16 ``addr`` (one D16 cycle), big-endian."""
        self._even(addr, "read")
        return int.from_bytes(self._read(addr, 2, 16), "big")

    def write8(self, addr: int, value: int) -> None:
        """One 1-byte ``pwrite`` at A16 ``addr``."""
        check_addr(addr)
        value = check_value(addr, value, 8)
        self._write(addr, bytes((value,)), 8)

    def write16(self, addr: int, value: int) -> None:
        """One 2-byte big-endian ``pwrite`` at even A16 ``addr`` (one D16 cycle)."""
        self._even(addr, "write")
        value = check_value(addr, value, 16)
        self._write(addr, value.to_bytes(2, "big"), 16)

    def read_block16(self, addr: int, n: int) -> list[int]:
        """``n`` big-endian words from even ``addr`` upward: one ``pread`` of ``2n`` bytes."""
        check_block(addr, n, "read")
        return list(struct.unpack(f">{n}H", self._read(addr, 2 * n, 16)))

    def write_block16(self, addr: int, words: Sequence[int]) -> None:
        """``words`` (all checked first) from even ``addr`` upward: one ``pwrite``."""
        values = check_words(addr, words)
        self._write(addr, struct.pack(f">{len(values)}H", *values), 16)

    # -- lifetime ---------------------------------------------------------------------
    def describe(self) -> str:
        kind = "non-privileged" if self.am == 0x29 else "supervisory"
        return (f"vme_user master window {self.path}: A16 0x0000-0xFFFF, {kind} data "
                f"(AM 0x{self.am:02X}), D16")

    def close(self) -> None:
        with self._lock:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None

    def __repr__(self) -> str:
        return f"VmeUserBus({self.path!r}, am=0x{self.am:02X})"


def open_vme_bus(url: str, **kwargs) -> VmeUserBus:
    """``open_bus("vme:/dev/bus/vme/m0[?am=0x29]")``; ``kwargs`` go to :class:`VmeUserBus`.

    :raises ValueError: a URL without a path, an unknown option or a bad number
    :raises LinkError: when the window cannot be configured or opened
    """
    if not url.startswith("vme:"):
        raise ValueError(f"not a vme: bus URL: {url!r}")
    parts = urlsplit(url)
    path = parts.path if not parts.netloc else f"//{parts.netloc}{parts.path}"
    if not path:
        raise ValueError(f"bus URL {url!r} names no master window; use vme:/dev/bus/vme/m0")
    opts: dict[str, Any] = {}
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key != "am":
            raise ValueError(f"bus URL {url!r}: unknown option {key!r}; known: am")
        try:
            opts["am"] = int(value, 0)
        except ValueError:
            raise ValueError(f"bus URL {url!r}: am={value!r} is not a number") from None
        if opts["am"] not in AM_CYCLES:
            raise ValueError(f"bus URL {url!r}: am must be 0x29 (A16 non-privileged data) or "
                             f"0x2D (A16 supervisory data)")
    opts.update(kwargs)
    return VmeUserBus(path, **opts)
