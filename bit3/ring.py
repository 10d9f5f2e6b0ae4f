"""Frame history ring: every published inputs body, kept for readers that may stall.

The Bit3 buffer holds one inputs frame: a reader that is not scheduled for more than a
frame period (3.125 ms) misses a frame, and on a shared VM a process is sometimes not
scheduled for 3-4 ms (measured: a reader doing nothing but copying missed 5 publishes
in 4,800). A recorder must not. So ``pfma serve`` also copies each inputs body it
publishes into this ring, a separate shared-memory file ``/dev/shm/<buffer>.ring``, and
the recorder reads the ring: it may fall up to ``n_slots - 1`` frames behind (0.8 s at
320 Hz with 256 slots) without losing one. The ring is not part of the Bit3 layout (the
IRSS dual-port RAM had no such thing); it is an addition of this project.

Format (little-endian; all offsets from the start of the file)::

    0   8s  magic b"PFMARING"
    8   u4  version (1)
    12  u4  n_slots
    16  u4  slot_size (bytes, a multiple of 64)
    20  u4  body_size (bytes of the inputs body stored per slot)
    24  8s  layout hash (the Bit3 buffer's)
    32  u8  count: frames written so far (the next frame number k goes to slot k % n_slots)
    64  slots; each: u8 stamp (2k+1 while frame k is written, 2k+2 when whole), body

A reader of frame k checks the stamp is 2k+2 before and after copying the body (like the
buffer's sequence lock); any other value means the slot was overwritten (the reader
fell more than ``n_slots - 1`` behind) or is being written.

**Replacement, never truncation.** A restarted service makes a new ring file (under a
temporary name in the same directory, then ``os.rename`` over the path); it never
truncates the old one, whose pages a reader may still have mapped (a mapped page beyond
the end of a truncated file kills the reader with SIGBUS). The reader keeps reading its
old ring -- which simply stops growing -- and sees the replacement with
:meth:`FrameRing.replaced` (the path now names another file, or none), then attaches the
new ring.

**Mode.** The ring carries its buffer's mode and group (bit3/access.py): private 0600 by
default, 0640 and the buffer's group in the lab PC's group model. :meth:`FrameRing.create`
reads them from the buffer's shared-memory file, so a ring never lets in a reader the
buffer keeps out (or keeps out a reader of the buffer).
"""

from __future__ import annotations

import mmap
import os
import struct
import uuid

from bit3 import space
from bit3.access import PRIVATE_MODE, access_error, segment_access

MAGIC = b"PFMARING"
VERSION = 1
HEADER = 64
DEFAULT_SLOTS = 256
#: the ring file's mode when its buffer does not exist (a ring alone, in tests): private
MODE = PRIVATE_MODE
_HDR = struct.Struct("<8sIIII8s")
_U64 = struct.Struct("<Q")


def ring_path(buffer_name: str) -> str:
    return f"/dev/shm/{buffer_name}.ring"


class RingError(Exception):
    """No ring, or a ring of another layout."""


class FrameRing:
    """One writer (the service), any number of readers.

    Create with :meth:`create` (writer) or :meth:`attach` (reader).
    """

    def __init__(self, mm: mmap.mmap, path: str, n_slots: int, slot_size: int, body_size: int,
                 layout_hash: bytes, file_id: tuple[int, int] = (0, 0), buffer_name: str = "") -> None:
        self._mm = mm
        self.path = path
        self.buffer_name = buffer_name
        self.file_id = file_id  #: (st_dev, st_ino) of the mapped file
        self.n_slots = n_slots
        self.slot_size = slot_size
        self.body_size = body_size
        self.layout_hash = layout_hash
        self._count = self.count()

    @classmethod
    def create(cls, buffer_name: str, body_size: int, layout_hash: bytes,
               n_slots: int = DEFAULT_SLOTS) -> "FrameRing":
        """Create (or replace) the ring of ``buffer_name``: a new file, complete with its
        header, renamed over the path; an old ring file is never truncated (see the module
        docstring), readers that map it keep valid memory. Its mode and group are the
        buffer's (private 0600 when there is no buffer)."""
        if n_slots < 2 or body_size <= 0:
            raise ValueError(f"ring needs >= 2 slots and a body (got {n_slots}, {body_size})")
        slot = -(-(8 + body_size) // 64) * 64
        path = ring_path(buffer_name)
        size = HEADER + n_slots * slot
        mode, gid = segment_access(buffer_name) or (MODE, -1)
        tmp = f"{path}.{os.getpid()}-{uuid.uuid4().hex[:8]}.new"
        fd = os.open(tmp, os.O_RDWR | os.O_CREAT | os.O_EXCL, PRIVATE_MODE)
        try:
            if gid != -1 and gid != os.fstat(fd).st_gid:
                os.fchown(fd, -1, gid)  # before the mode: never readable by the wrong group
            os.fchmod(fd, mode)  # whatever the umask
            os.ftruncate(fd, size)
            # every page before the mapping (bit3/space.py): a full /dev/shm is a ShmFullError
            # here, the temporary file removed below, not a SIGBUS in a frame
            space.reserve(fd, size, path, f"the frame ring of {buffer_name!r}")
            mm = mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ | mmap.PROT_WRITE)
            st = os.fstat(fd)
            _HDR.pack_into(mm, 0, MAGIC, VERSION, n_slots, slot, body_size,
                           bytes(layout_hash)[:8].ljust(8, b"\0"))
            _U64.pack_into(mm, 32, 0)
            os.rename(tmp, path)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise
        finally:
            os.close(fd)
        return cls(mm, path, n_slots, slot, body_size, bytes(layout_hash)[:8], (st.st_dev, st.st_ino),
                   buffer_name)

    @classmethod
    def attach(cls, buffer_name: str, layout_hash: bytes | None = None) -> "FrameRing":
        """Map the ring of ``buffer_name`` read-only.

        :raises RingError: no ring, not a ring, or (``layout_hash`` given) another layout
        """
        path = ring_path(buffer_name)
        try:
            fd = os.open(path, os.O_RDONLY)
        except PermissionError:
            raise RingError(str(access_error(path, writing=False))) from None
        except OSError as err:
            raise RingError(f"no frame ring {path}: {err.strerror}") from None
        try:
            st = os.fstat(fd)
            size = st.st_size
            if size < HEADER:
                raise RingError(f"{path}: {size} bytes, not a frame ring")
            mm = mmap.mmap(fd, size, mmap.MAP_SHARED, mmap.PROT_READ)
        finally:
            os.close(fd)
        magic, version, n, slot, body, h = _HDR.unpack_from(mm, 0)
        if magic != MAGIC or version != VERSION or size < HEADER + n * slot:
            mm.close()
            raise RingError(f"{path}: not a version-{VERSION} frame ring")
        if layout_hash is not None and h != bytes(layout_hash)[:8]:
            mm.close()
            raise RingError(f"{path}: layout {h.hex()}, expected {bytes(layout_hash)[:8].hex()}")
        return cls(mm, path, n, slot, body, h, (st.st_dev, st.st_ino), buffer_name)

    def replaced(self) -> bool:
        """The path no longer names the file this ring maps (a restarted service made a new
        ring, or the ring was removed). One ``stat``; this ring's memory stays readable."""
        try:
            st = os.stat(self.path)
        except FileNotFoundError:
            return True
        return (st.st_dev, st.st_ino) != self.file_id

    # -- writer -------------------------------------------------------------------------
    def write(self, body) -> None:
        """Append one inputs body (bytes-like of ``body_size`` bytes) as the next frame."""
        k = self._count
        off = HEADER + (k % self.n_slots) * self.slot_size
        mm = self._mm
        _U64.pack_into(mm, off, 2 * k + 1)
        mm[off + 8: off + 8 + self.body_size] = body
        _U64.pack_into(mm, off, 2 * k + 2)
        self._count = k + 1
        _U64.pack_into(mm, 32, k + 1)

    # -- reader -------------------------------------------------------------------------
    def count(self) -> int:
        """Frames written so far."""
        return _U64.unpack_from(self._mm, 32)[0]

    def read(self, k: int) -> bytearray | None:
        """Frame ``k``'s body, or None when it is no longer (or not yet) whole in the ring."""
        off = HEADER + (k % self.n_slots) * self.slot_size
        mm = self._mm
        want = 2 * k + 2
        if _U64.unpack_from(mm, off)[0] != want:
            return None
        data = bytearray(mm[off + 8: off + 8 + self.body_size])
        if _U64.unpack_from(mm, off)[0] != want:
            return None
        return data

    def close(self) -> None:
        try:
            self._mm.close()
        except BufferError:  # a view is still alive; the mapping goes with the process
            pass

    @staticmethod
    def unlink(buffer_name: str) -> None:
        try:
            os.unlink(ring_path(buffer_name))
        except FileNotFoundError:
            pass
