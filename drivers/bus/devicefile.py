"""A RegisterBus on a memory-mapped VME A16 window exposed as a device file.

PCI-to-VME bridges (Tundra Universe II, Tundra/IDT Tsi148) make a VME address
window appear as a file. With Linux's ``vme_user`` driver (drivers/staging/vme_user,
modules ``vme_tsi148`` or ``vme_ca91cx42`` plus ``vme_user``) the master windows are
``/dev/bus/vme/m0`` .. ``m3``; ``mmap`` of such a file gives the VME window as memory
(``vme_user_master_mmap`` in vme_user.c). What to configure, once per boot:

1. load the bridge module and ``vme_user`` (``modprobe vme_tsi148 vme_user``;
   on older kernels ``vme_user bus=0``);
2. set the master window with the ``VME_SET_MASTER`` ioctl (:func:`vme_user_set_master`
   does it): ``vme_addr=0``, ``size=0x10000``, address space A16, cycle
   ``SCT | SUPER | DATA`` (address modifier 0x2D, supervisory short I/O as the PFMA
   I/O processor used), data width D16;
3. give the service user read/write access to the device file (a udev rule).

Then ``open_bus("file:/dev/bus/vme/m0")`` maps the whole A16 space. Any other file
that holds the A16 space (a ``/dev/mem`` window at the bridge's PCI address, a
Universe ``/dev/vme_m0`` from the older out-of-tree driver, or an ordinary file in
tests) works the same way with ``offset`` (file offset of the window's first byte)
and ``base`` (A16 address of that byte).

Byte order: the file is assumed *address invariant* (the bridge's default; byte at
VME address A is at file offset A), so a 16-bit word is assembled big-endian from
its two bytes. Each 16-bit access is one native 16-bit load or store (via a
``memoryview`` cast), so the bridge issues one D16 cycle, never two D8 cycles:
that matters for registers whose reads have side effects. A block transfer
(``read_block16``/``write_block16``) is one slice of the same word view: one native
16-bit load or store per word, in address order, in one Python call.

**What this backend cannot do:** an access to an address *inside* the window that
no board answers ends, on a real bridge, either in all-ones data (a PCI master
abort) or in a ``SIGBUS`` that kills the process; Python cannot catch ``SIGBUS``
(``faulthandler`` can at least print where it happened). Only addresses *outside*
the mapped window raise :class:`BusError` here. Probe new boards with
``pfma reg read`` in a throwaway process, never from the service.
"""

from __future__ import annotations

import fcntl
from array import array
import mmap
import os
import struct
import sys
from urllib.parse import parse_qsl, urlsplit

from collections.abc import Sequence

from drivers.bus import check_addr, check_block, check_value, check_words
from drivers.bus.base import BusBase
from pfma.errors import BusError, LinkError

__all__ = ["DeviceFileBus", "open_devicefile_bus", "vme_user_set_master"]

_SWAP = sys.byteorder == "little"


class DeviceFileBus(BusBase):
    """RegisterBus on an mmap of a file holding (part of) the A16 space.

    :param path: the device file (``/dev/bus/vme/m0``) or any regular file
    :param size: bytes of A16 space mapped (even, default the whole 64 KiB)
    :param offset: file offset of the window's first byte
    :param base: A16 address of the window's first byte (even)
    :raises LinkError: when the file cannot be opened or mapped
    """

    def __init__(self, path: str | os.PathLike, *, size: int = 0x10000, offset: int = 0,
                 base: int = 0) -> None:
        if size <= 0 or size % 2 or base % 2 or offset % 2:
            raise ValueError(f"{path}: size, offset and base must be even and size > 0 "
                             f"(got size=0x{size:X}, offset=0x{offset:X}, base=0x{base:X})")
        if not 0 <= base or base + size > 0x10000:
            raise ValueError(f"{path}: window 0x{base:04X}+0x{size:X} runs past the A16 space")
        self.path = os.fspath(path)
        self.size = size
        self.offset = offset
        self.base = base
        flags = os.O_RDWR | getattr(os, "O_SYNC", 0) | getattr(os, "O_CLOEXEC", 0)
        try:
            self._fd = os.open(self.path, flags)
        except OSError as err:
            raise LinkError(f"cannot open VME window file {self.path}: {err.strerror}") from err
        granule = mmap.ALLOCATIONGRANULARITY
        start = offset - offset % granule  # mmap offsets must be page aligned
        self._delta = offset - start
        try:
            self._mm = mmap.mmap(self._fd, self._delta + size, mmap.MAP_SHARED,
                                 mmap.PROT_READ | mmap.PROT_WRITE, offset=start)
        except (OSError, ValueError) as err:
            os.close(self._fd)
            raise LinkError(f"cannot map 0x{size:X} bytes at offset 0x{offset:X} of "
                            f"{self.path}: {err}") from err
        window = memoryview(self._mm)[self._delta:self._delta + size]
        self._bytes = window
        self._words = window.cast("H")  # native 16-bit loads/stores: one D16 cycle each

    # -- helpers ------------------------------------------------------------------
    def _index(self, addr: int, width: int, op: str) -> int:
        if width == 16:
            self._even(addr, op)
        else:
            check_addr(addr)
        i = addr - self.base
        if not 0 <= i <= self.size - width // 8:
            raise BusError(addr, width, op, reason=f"outside the mapped window 0x{self.base:04X}-"
                           f"0x{self.base + self.size - 1:04X} of {self.path}")
        return i

    def _live(self, addr: int, width: int, op: str) -> None:
        if self._mm.closed:
            raise BusError(addr, width, op, reason=f"{self.path} is closed")

    # -- RegisterBus ----------------------------------------------------------------
    def read8(self, addr: int) -> int:
        """Read the byte at A16 ``addr``."""
        i = self._index(addr, 8, "read")
        self._live(addr, 8, "read")
        return self._bytes[i]

    def read16(self, addr: int) -> int:
        """Read the big-endian word at even A16 ``addr`` (one D16 cycle)."""
        i = self._index(addr, 16, "read")
        self._live(addr, 16, "read")
        v = self._words[i >> 1]
        return ((v & 0xFF) << 8) | (v >> 8) if _SWAP else v

    def write8(self, addr: int, value: int) -> None:
        """Write one byte at A16 ``addr``."""
        value = check_value(addr, value, 8)
        i = self._index(addr, 8, "write")
        self._live(addr, 8, "write")
        self._bytes[i] = value

    def write16(self, addr: int, value: int) -> None:
        """Write the big-endian word ``value`` at even A16 ``addr`` (one D16 cycle)."""
        value = check_value(addr, value, 16)
        i = self._index(addr, 16, "write")
        self._live(addr, 16, "write")
        self._words[i >> 1] = ((value & 0xFF) << 8) | (value >> 8) if _SWAP else value

    def _block(self, addr: int, n: int, op: str) -> int:
        """Word index of a checked block inside the window; BusError naming the first word
        outside it (before any access)."""
        i = addr - self.base
        end = self.base + self.size
        if not 0 <= i < self.size:
            raise BusError(addr, 16, op, reason=f"outside the mapped window 0x{self.base:04X}-"
                           f"0x{end - 1:04X} of {self.path}")
        if addr + 2 * n > end:
            raise BusError(end, 16, op, reason=f"block from 0x{addr:04X} ({n} words) leaves the "
                           f"mapped window 0x{self.base:04X}-0x{end - 1:04X} of {self.path}")
        self._live(addr, 16, op)
        return i >> 1

    def read_block16(self, addr: int, n: int) -> list[int]:
        """The ``n`` big-endian words from even A16 ``addr`` on: one slice of the window."""
        check_block(addr, n, "read")
        j = self._block(addr, n, "read")
        words = self._words[j:j + n].tolist()
        if _SWAP:
            return [((v & 0xFF) << 8) | (v >> 8) for v in words]
        return words

    def write_block16(self, addr: int, words: Sequence[int]) -> None:
        """Write ``words`` (all checked first) from even A16 ``addr`` on: one slice store."""
        values = check_words(addr, words)
        j = self._block(addr, len(values), "write")
        if _SWAP:
            values = [((v & 0xFF) << 8) | (v >> 8) for v in values]
        self._words[j:j + len(values)] = memoryview(array("H", values))

    # -- lifetime ---------------------------------------------------------------------
    def describe(self) -> str:
        return (f"device file {self.path}: A16 0x{self.base:04X}-0x{self.base + self.size - 1:04X} "
                f"at file offset 0x{self.offset:X}")

    def close(self) -> None:
        if self._mm.closed:
            return
        self._words.release()
        self._bytes.release()
        self._mm.close()
        os.close(self._fd)

    def __repr__(self) -> str:
        return f"DeviceFileBus({self.path!r}, size=0x{self.size:X}, offset=0x{self.offset:X}, base=0x{self.base:04X})"


def _int(text: str, name: str, url: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise ValueError(f"bus URL {url!r}: {name}={text!r} is not an integer") from None


def open_devicefile_bus(url: str, **kwargs) -> DeviceFileBus:
    """``open_bus("file:PATH[?size=N&offset=N&base=N]")`` (numbers decimal or 0x hex).

    :raises ValueError: for an unknown query option or a malformed number
    """
    if not url.startswith("file:"):
        raise ValueError(f"not a file: bus URL: {url!r}")
    parts = urlsplit(url)
    path = parts.path if not parts.netloc else f"//{parts.netloc}{parts.path}"
    if not path:
        raise ValueError(f"bus URL {url!r} names no file; use file:/dev/bus/vme/m0")
    opts: dict[str, int] = {}
    for key, value in parse_qsl(parts.query, keep_blank_values=True):
        if key not in ("size", "offset", "base"):
            raise ValueError(f"bus URL {url!r}: unknown option {key!r}; known: base, offset, size")
        opts[key] = _int(value, key, url)
    opts.update(kwargs)
    return DeviceFileBus(path, **opts)


# -- vme_user window set-up (Linux drivers/staging/vme_user/vme_user.h, include/linux/vme.h) --
VME_A16 = 0x1
VME_SCT = 0x1
VME_SUPER = 0x1000
VME_USER = 0x2000
VME_DATA = 0x8000
VME_D16 = 0x2
_VME_MASTER = struct.Struct("=IQQIII")  # struct vme_master, __packed: enable, vme_addr, size, aspace, cycle, dwidth


def _iow(type_: int, nr: int, size: int, machine: str | None = None) -> int:
    """Linux's ``_IOW(type, nr, size)``: the "write" direction is 1 << 30 on most
    architectures, 4 << 29 on PowerPC, MIPS, SPARC and Alpha (most VME SBCs with a Tsi148
    or Universe II are PowerPC)."""
    m = os.uname().machine if machine is None else machine
    write = 4 << 29 if m.startswith(("ppc", "powerpc", "mips", "sparc", "alpha")) else 1 << 30
    return write | (size << 16) | (type_ << 8) | nr


_VME_SET_MASTER = _iow(0xAE, 4, _VME_MASTER.size)  # _IOW(VME_IOC_MAGIC, 4, struct vme_master)


def vme_user_set_master(path: str, *, vme_addr: int = 0, size: int = 0x10000,
                        cycle: int = VME_SCT | VME_SUPER | VME_DATA) -> None:
    """Configure a ``vme_user`` master window for A16 D16 access (needs root).

    Untested here (no bridge on the development machine); the layout follows
    ``struct vme_master`` in Linux's vme_user.h.
    """
    arg = _VME_MASTER.pack(1, vme_addr, size, VME_A16, cycle, VME_D16)
    fd = os.open(path, os.O_RDWR)
    try:
        fcntl.ioctl(fd, _VME_SET_MASTER, arg)
    finally:
        os.close(fd)
