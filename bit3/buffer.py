"""The Bit3 buffer: 32 KB of shared memory with sequence-locked areas and one writer each.

Backings (one class, :class:`Bit3Buffer`):

- POSIX shared memory through :class:`multiprocessing.shared_memory.SharedMemory`
  (``create(name)`` / ``attach(name)``; on Linux it is the file ``/dev/shm/<name>``);
- a file or device-file window (``from_file(path)``), e.g. on hardware the dual-port RAM
  window mapped from a device file.

**The segment** (open, close, remove; the resource_tracker workaround) is
:mod:`bit3.segment`'s, shared with the controller's world model. The buffer is never
removed automatically: the creator removes it with ``close(unlink=True)`` or
:meth:`Bit3Buffer.unlink`.

**Sequence lock**: :mod:`bit3.seqlock` (its memory-ordering conditions are stated there).

**Ownership.** A writer claims its role's areas (layout.WRITER_ROLES): an open-file-
description lock (``F_OFD_SETLK``, Linux) on one byte per area of the backing file, plus
the owner slot in the header (pid, name, claim time, heartbeat). The lock dies with the
process, so a dead owner's claim is taken over (and counted in ``takeovers``); a live
owner's lock refuses a second writer with an :class:`OwnershipError` naming it. OFD
locks, unlike POSIX ``lockf`` locks, also refuse a second claim from another
attachment in the same process. A forked child inherits the parent's lock.
"""

from __future__ import annotations

import errno
import fcntl
import mmap
import os
import struct
import time
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Literal

import numpy as np

from bit3.layout import (
    AREA_MAP, BUFFER_SIZE, LAYOUT_VERSION, MAGIC, MESSAGE_CONTINUED, MESSAGE_CONTINUES, MESSAGE_DTYPE,
    MESSAGE_MAX_ENTRIES, MESSAGE_SEVERITY_MASK, QUEUE_LEN, MESSAGE_TEXT_BYTES,
    OWNER_DTYPE, OWNER_FLAG_CLAIMED, OWNER_FLAG_SIMULATED, OWNER_NAME_BYTES, WRITER_ROLES, AreaSpec, Layout,
    ServiceState,
    Severity, _header, default_layout, resolve_role, struct_field, struct_names,
)
from bit3 import access, futex, space
from bit3.segment import Segment, shm_fd
from bit3.segment import open_shm as _open_shm
from bit3.seqlock import (  # noqa: F401  (the errors and constants are part of the buffer's API)
    DEFAULT_READ_TIMEOUT_S, TRY_READ_ATTEMPTS, Bit3Error, LayoutMismatchError, OwnershipError, SeqLock,
    SeqLockTimeout,
)

#: struct formats of the single header/queue words (:meth:`Bit3Buffer._word`)
WordFormat = Literal["Q", "I", "i", "d"]

_F_OFD_SETLK = getattr(fcntl, "F_OFD_SETLK", None)  # Linux >= 3.15, Python >= 3.9
_F_OFD_GETLK = getattr(fcntl, "F_OFD_GETLK", None)
_FLOCK = "hhqqi4x"  # struct flock on Linux x86-64/arm64 (native alignment)


# ----------------------------------------------------------------------------------------
# header helpers


@dataclass(frozen=True)
class OwnerInfo:
    """One area's owner slot."""

    area: str
    pid: int
    name: str
    claimed_ns: int
    heartbeat: int
    heartbeat_t_s: float
    takeovers: int
    flags: int = 0  #: ``OWNER_FLAG_*`` bits (bit3/layout.py)

    @property
    def simulated(self) -> bool:
        """The claimer runs on the simulated rack (``OWNER_FLAG_SIMULATED``)."""
        return bool(self.flags & OWNER_FLAG_SIMULATED)

    @property
    def alive(self) -> bool:
        """The owner's process exists (on this host)."""
        return self.pid > 0 and _pid_alive(self.pid)

    def describe(self) -> str:
        if self.pid <= 0:
            return "nobody"
        return f"{self.name!r} (pid {self.pid}{'' if self.alive else ', not running'})"


@dataclass(frozen=True)
class HeaderInfo:
    magic: bytes
    layout_version: int
    buffer_size: int
    layout_hash: bytes
    calibration_hash: bytes
    created_ns: int
    service_state: ServiceState
    frame: int
    frame_t_s: float
    rack_name: str
    owners: tuple[OwnerInfo, ...]

    @property
    def rack_kind(self) -> str:
        """Whether the service's rack is simulated, from the ``inputs`` owner slot's flags:
        ``"simulated"`` (the register-level fakes), ``"real"`` (a hardware bus: the service
        cannot see what is behind it, so this is "not simulated by the service") or
        ``"unknown"`` (no service has claimed the buffer, or the owner slots are not
        available, as over the Zenoh bridge)."""
        o = next((o for o in self.owners if o.area == "inputs"), None)
        if o is None or o.pid <= 0:
            return "unknown"
        if o.flags & OWNER_FLAG_SIMULATED:
            return "simulated"
        return "real" if o.flags & OWNER_FLAG_CLAIMED else "unknown"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _lock_byte(fd: int, index: int, lock: bool) -> None:
    """Non-blocking OFD write lock (or unlock) of byte ``index`` of the backing file."""
    kind = fcntl.F_WRLCK if lock else fcntl.F_UNLCK
    if _F_OFD_SETLK is not None:
        fcntl.fcntl(fd, _F_OFD_SETLK, struct.pack("hhqqi4x", kind, os.SEEK_SET, index, 1, 0))
    else:  # POSIX record locks: per process, see module docstring
        fcntl.lockf(fd, (fcntl.LOCK_EX | fcntl.LOCK_NB) if lock else fcntl.LOCK_UN, 1, index)


def _byte_locked(fd: int, index: int) -> bool:
    """Someone holds a lock on byte ``index`` of the backing file (a test only: nothing is
    taken, so a service claiming at this instant is not disturbed)."""
    cmd = _F_OFD_GETLK if _F_OFD_GETLK is not None else fcntl.F_GETLK
    res = fcntl.fcntl(fd, cmd, struct.pack(_FLOCK, fcntl.F_WRLCK, os.SEEK_SET, index, 1, 0))
    return struct.unpack(_FLOCK, res)[0] != fcntl.F_UNLCK


#: the header's field offsets: the same for every rack (only the area bodies differ)
_HEADER_OFF: dict[str, int] | None = None


def _header_offsets() -> dict[str, int]:
    global _HEADER_OFF
    if _HEADER_OFF is None:
        name, offset, size, writer, seqlocked, doc = AREA_MAP[0]
        _HEADER_OFF = {f.name: f.offset for f in _header(AreaSpec(name, 0, offset, size, writer, seqlocked,
                                                                   doc)).specs}
    return _HEADER_OFF


#: public names of the helpers above, for other shared-memory segments (the world model)
open_shm = _open_shm
pid_alive = _pid_alive
lock_byte = _lock_byte


# ----------------------------------------------------------------------------------------
# area writer / reader


class AreaWriter:
    """Publishes one area: fill :attr:`record` (a private numpy record), then :meth:`publish`.

    ``record`` is a 0-d structured array of the area's body dtype; ``record["t_s"] = t``
    and ``record["adc_value"][:] = volts`` write into it without allocating.
    """

    def __init__(self, buf: "Bit3Buffer", area: AreaSpec, lock: SeqLock, owner_index: int) -> None:
        self.area = area
        self._buf = buf
        self._lock = lock
        self.raw = bytearray(area.body_size)
        self._src = memoryview(self.raw)
        self.record: np.ndarray = np.ndarray((), area.body_dtype, buffer=self.raw)
        self._hb = buf._word(buf._owner_offset(owner_index, "heartbeat"), "Q")
        self._hbt = buf._word(buf._owner_offset(owner_index, "heartbeat_t_s"), "d")
        self._now = buf.clock_now
        self.load()

    def load(self) -> int:
        """Start from what is in the buffer (after a takeover, keep the last published values)."""
        return self._lock.read_into(self._src)

    def publish(self) -> int:
        """Copy :attr:`record` into the buffer under the sequence lock; bump the heartbeat."""
        s = self._lock.write(self._src)
        self._hb[0] = self._hb[0] + 1
        self._hbt[0] = self._now()
        return s


class AreaReader:
    """Reads one area into a private, preallocated :attr:`record`."""

    def __init__(self, buf: "Bit3Buffer", area: AreaSpec, lock: SeqLock) -> None:
        self.area = area
        self._lock = lock
        self.raw = bytearray(area.body_size)
        self._dst = memoryview(self.raw)
        self._scratch = memoryview(bytearray(area.body_size))  # try_read's landing place
        self.record: np.ndarray = np.ndarray((), area.body_dtype, buffer=self.raw)
        self.last_seq = -1  #: counter of the copy in :attr:`record` (-1: never read)
        self.try_failures = 0  #: :meth:`try_read` calls that got no stable copy

    def read(self) -> int:
        """Refresh :attr:`record` with a whole, consistent copy; returns its sequence number.

        :raises SeqLockTimeout: no stable copy within the lock's ``timeout_s`` (it waits that long)
        """
        s = self._lock.read_into(self._dst)
        self.last_seq = s
        return s

    def try_read(self) -> bool:
        """Refresh :attr:`record` without waiting: at most ``TRY_READ_ATTEMPTS`` copies (no
        clock, no sleep, no allocation). False when none was stable (the writer is mid-write
        or died mid-write): :attr:`record` and :attr:`last_seq` keep the last good copy and
        :attr:`try_failures` counts the call. True: :attr:`last_seq` is the new copy's."""
        s = self._lock.try_read_into(self._dst, self._scratch)
        if s < 0:
            self.try_failures += 1
            return False
        self.last_seq = s
        return True

    @property
    def seq(self) -> int:
        return self._lock.seq

    def changed(self) -> bool:
        """A newer copy has been published since the last :meth:`read` (cheap poll)."""
        return self._lock.seq != self.last_seq

    @property
    def retries(self) -> int:
        return self._lock.retries


@dataclass(frozen=True)
class Message:
    """One message-queue entry."""

    queue: str
    seq: int  #: sequence number of its last entry (read on from here: ``read(since_seq=seq)``)
    t_s: float
    severity: Severity
    source: int
    code: int
    text: str  #: the whole text (a long message takes several entries, joined here)
    first_seq: int = 0  #: sequence number of its first entry (== seq for a one-entry message)

    def format(self) -> str:
        return (f"{self.t_s:12.6f} {self.queue:<20} #{self.seq:<6} {self.severity.name:<7} "
                f"src={self.source} code={self.code} {self.text}")


def _char_cut(raw: bytes, at: int) -> int:
    """The largest cut <= ``at`` that is not inside a UTF-8 character of ``raw``."""
    while 0 < at < len(raw) and (raw[at] & 0xC0) == 0x80:
        at -= 1
    return at


def split_text(raw: bytes) -> list[bytes]:
    """UTF-8 ``raw`` in entry-sized pieces, cut only between characters; at most
    ``MESSAGE_MAX_ENTRIES`` pieces (``MESSAGE_MAX_BYTES``, the bound stated in
    bit3/layout.py), the last ending "~" when the text was longer."""
    size = MESSAGE_TEXT_BYTES
    pieces: list[bytes] = []
    while len(raw) > size and len(pieces) <= MESSAGE_MAX_ENTRIES:
        cut = _char_cut(raw, size)
        pieces.append(raw[:cut])
        raw = raw[cut:]
    pieces.append(raw)
    if len(pieces) > MESSAGE_MAX_ENTRIES:
        last = pieces[MESSAGE_MAX_ENTRIES - 1]
        pieces = pieces[:MESSAGE_MAX_ENTRIES - 1] + [last[:_char_cut(last, size - 1)] + b"~"]
    return pieces


def decode_messages(queue: str, rec: np.ndarray, since_seq: int = 0) -> list[Message]:
    """The messages newer than ``since_seq`` in a consistent copy ``rec`` of a message-queue
    body (what :meth:`MessageQueue.read` returns; also for a copy that came from elsewhere,
    e.g. the body bytes the Zenoh bridge publishes). Only whole messages: the entries of a
    message whose first entry the ring has already overwritten (``MESSAGE_CONTINUED`` on
    the oldest entry read) are skipped, so the first message returned then starts after
    ``since_seq + 1`` (its ``first_seq`` says where; the gap counts the entries lost)."""
    head = int(rec["head_seq"])
    entries = rec["entries"]
    n = len(entries)
    first = max(since_seq + 1, head - n + 1, 1)
    out = []
    parts: list[bytes] = []  # the pieces of a message whose last entry is still to come
    start = first
    orphan = False  # inside a message whose beginning is gone: skipped up to its last entry
    for s in range(first, head + 1):
        e = entries[(s - 1) % n]
        if int(e["seq"]) != s:  # cannot happen with a stable copy; be strict anyway
            parts = []
            continue
        sev_byte = int(e["severity"])
        if not parts:
            start = s
            orphan = bool(sev_byte & MESSAGE_CONTINUED)
        if orphan:
            if not sev_byte & MESSAGE_CONTINUES:
                orphan = False  # its last entry: the next one starts a message
            continue
        parts.append(bytes(e["text"]))
        if sev_byte & MESSAGE_CONTINUES and s < head:
            continue
        try:
            sev = Severity(sev_byte & MESSAGE_SEVERITY_MASK)
        except ValueError:
            sev = Severity.ERROR
        first_e = entries[(start - 1) % n]
        out.append(Message(queue, s, float(first_e["t_s"]), sev, int(first_e["source"]),
                           int(first_e["code"]), b"".join(parts).decode("utf-8", "replace"), start))
        parts = []
    return out


class MessageQueue:
    """A circular message queue area (like each IRSS processor card's): 50 entries for the
    service, :data:`~bit3.layout.CONTROLLER_QUEUE_LEN` for the controller.

    Message ``s`` (1, 2, ...) lives in ``entries[(s - 1) % capacity]``; ``head_seq`` is the newest.
    Only the area's owner may :meth:`post`; anyone may :meth:`read`.
    """

    def __init__(self, buf: "Bit3Buffer", area: AreaSpec, lock: SeqLock) -> None:
        self.area = area
        self._lock = lock
        self._reader = AreaReader(buf, area, lock)
        self._entries_off = struct_field(area.body_dtype, "entries")[1]
        self.capacity = QUEUE_LEN[area.name]  #: entries in the ring
        self._entry_raw = bytearray(MESSAGE_DTYPE.itemsize)
        self._entry_mv = memoryview(self._entry_raw)
        self._entry = np.ndarray((), MESSAGE_DTYPE, buffer=self._entry_raw)
        self._body = lock._body  # in-place posting, under begin()/end()
        self._head: memoryview[Any] | None = None  #: head_seq word, once claimed (post)
        self._now = buf.clock_now

    def _attach_writer(self, buf: "Bit3Buffer") -> None:
        off = self.area.body_offset
        self._head = buf._word(off + struct_field(self.area.body_dtype, "head_seq")[1], "Q")
        buf._word(off + struct_field(self.area.body_dtype, "capacity")[1], "I")[0] = self.capacity

    def post(self, text: str, severity: Severity | int = Severity.INFO, code: int = 0,
             source: int = 0, t_s: float | None = None) -> int:
        """Append a message, whole: a text longer than one entry's 56 bytes of UTF-8 takes
        the next entries too (at most ``MESSAGE_MAX_ENTRIES``, ``MESSAGE_MAX_BYTES`` of
        text; beyond, it is cut and ends "~"), written in one sequence-lock section; returns
        the sequence number of its last entry."""
        if self._head is None:
            raise Bit3Error(f"Bit3 area {self.area.name}: not claimed by this attachment; "
                            f"only its owner may post")
        pieces = split_text(text.encode("utf-8", "replace"))
        n0 = self._head[0]
        e = self._entry
        e["t_s"] = self._now() if t_s is None else t_s
        e["source"] = source
        e["code"] = code
        last = len(pieces) - 1
        self._lock.begin()
        for i, raw in enumerate(pieces):
            n = n0 + 1 + i
            e["seq"] = n
            e["severity"] = (int(severity) | (MESSAGE_CONTINUES if i < last else 0)
                             | (MESSAGE_CONTINUED if i > 0 else 0))
            e["text"] = raw
            off = self._entries_off + ((n - 1) % self.capacity) * MESSAGE_DTYPE.itemsize
            self._body[off:off + MESSAGE_DTYPE.itemsize] = self._entry_mv
        self._head[0] = n0 + len(pieces)
        self._lock.end()
        return n0 + len(pieces)

    def read(self, since_seq: int = 0) -> list[Message]:
        """Messages newer than ``since_seq`` still in the ring, oldest first."""
        self._reader.read()
        return decode_messages(self.area.name, self._reader.record, since_seq)

    @property
    def head_seq(self) -> int:
        self._reader.read()
        return int(self._reader.record["head_seq"])

    def copy(self) -> np.ndarray:
        """A whole, consistent copy of the queue's body, to decode later or elsewhere
        (:func:`decode_messages`; the recorder's capture thread takes these)."""
        self._reader.read()
        return self._reader.record.copy()


# ----------------------------------------------------------------------------------------
# the buffer


class Bit3Buffer(Segment):
    """The 32 KB buffer. Use :meth:`create`, :meth:`attach` or :meth:`from_file`.

    The segment's lifecycle is :class:`bit3.segment.Segment`'s (``_shm`` is set by
    create/attach only)."""

    name: str

    def __init__(self, mem, layout: Layout, *, name: str, fd: int, readonly: bool,
                 closer, clock_now=time.monotonic) -> None:
        if len(mem) != BUFFER_SIZE:
            closer()
            raise LayoutMismatchError(f"Bit3 buffer {name}: size {len(mem)} bytes, "
                                      f"expected {BUFFER_SIZE}")
        self.layout = layout
        self.name = name
        self.readonly = readonly
        self.clock_now = clock_now
        self._mem = mem
        self._fd = fd
        self._closer = closer
        mv = memoryview(mem)
        self._mv = mv.toreadonly() if readonly else mv
        self._root = mv
        self._views: list[memoryview[Any]] = []
        self._locks: dict[str, SeqLock] = {}
        self._claimed: dict[str, str] = {}  # area -> owner name
        self._writers: dict[str, AreaWriter] = {}
        self._queues: dict[str, MessageQueue] = {}
        self._owner_views: dict[str, tuple[memoryview, memoryview, memoryview]] = {}
        self._hdr_off = {f.name: f.offset for f in layout.fields if f.area == "header"}
        me = weakref.ref(self)

        def owner_of(area: str) -> Callable[[], str]:
            def lookup() -> str:
                buf = me()
                if buf is None:  # the buffer is gone: SeqLock reports the writer as "?"
                    raise Bit3Error("Bit3 buffer closed")
                return buf.owner(area).describe()
            return lookup

        for a in layout.areas:
            if a.seqlocked:
                lk = self._locks[a.name] = SeqLock(self._mv, a.offset, a.body_size, a.name)
                lk.owner_lookup = owner_of(a.name)

    # --- opening ---------------------------------------------------------------------

    @classmethod
    def create(cls, name: str = "pfma", layout: Layout | None = None, *,
               exist_ok: bool = False, group: str | int | None = None) -> "Bit3Buffer":
        """Create and initialise POSIX shared memory ``name`` (``/dev/shm/<name>``).

        With ``exist_ok`` an existing segment is attached writable instead (and must match).

        :param group: None: mode 0600 (private to this user); a group name or gid: mode
            0640 and that group, so its members can attach read-only (bit3/access.py)
        :raises Bit3Error: unknown group, or this user is not a member of it (nothing left behind)
        :raises ShmFullError: /dev/shm has no room for the buffer (nothing left behind)
        """
        layout = layout or default_layout()
        try:
            shm = _open_shm(name, create=True, size=BUFFER_SIZE)
        except FileExistsError:
            if not exist_ok:
                raise Bit3Error(f"Bit3 buffer {name!r} already exists (/dev/shm/{name}); attach "
                                f"to it, or remove it with Bit3Buffer.unlink({name!r}) when no "
                                f"process uses it") from None
            return cls.attach(name, readonly=False, layout=layout)
        try:
            # every page now (bit3/space.py): a full /dev/shm is a one-line error here, not a
            # SIGBUS at the first write. SharedMemory has mapped the file but touched no page
            space.reserve(shm_fd(shm), BUFFER_SIZE, f"/dev/shm/{name}", f"the Bit3 buffer {name!r}")
            access.apply_access(shm_fd(shm), f"/dev/shm/{name}", group)
        except BaseException:
            shm.close()
            Bit3Buffer.unlink(name)
            raise
        buf = cls(shm.buf, layout, name=name, fd=shm_fd(shm), readonly=False, closer=shm.close)
        buf._shm = shm
        buf._initialise()
        return buf

    @classmethod
    def attach(cls, name: str = "pfma", readonly: bool = True,
               layout: Layout | None = None) -> "Bit3Buffer":
        """Attach to an existing segment; refused unless magic, version, size and hash match.

        Read-only, a segment this user may only read (the group model, bit3/access.py) is
        mapped read-only. No permission: :class:`~bit3.access.Bit3AccessError`, one message.
        """
        layout = layout or default_layout()
        missing = Bit3Error(f"no Bit3 buffer {name!r} (/dev/shm/{name}); is the I/O service running?")
        try:
            shm = _open_shm(name, create=False)
        except FileNotFoundError:
            raise missing from None
        except PermissionError:
            if not readonly:
                raise access.access_error(f"/dev/shm/{name}", writing=True) from None
            try:
                mm, fd = access.open_readonly(name)
            except FileNotFoundError:
                raise missing from None
            except PermissionError:
                raise access.access_error(f"/dev/shm/{name}", writing=False) from None

            def closer() -> None:
                mm.close()
                os.close(fd)
            buf = cls(mm, layout, name=name, fd=fd, readonly=True, closer=closer)
        else:
            buf = cls(shm.buf, layout, name=name, fd=shm_fd(shm), readonly=readonly, closer=shm.close)
            buf._shm = shm
        try:
            buf._verify()
        except BaseException:
            buf.close()
            raise
        return buf

    @classmethod
    def from_file(cls, path: str | Path, layout: Layout | None = None, *, readonly: bool = False,
                  create: bool = False) -> "Bit3Buffer":
        """Map a file or device-file window of 32768 bytes.

        ``create``: make a regular file of the right size if missing, and initialise the
        header if the magic is absent.
        """
        layout = layout or default_layout()
        p = Path(path)
        flags = os.O_RDONLY if readonly else os.O_RDWR
        if create and not readonly:
            flags |= os.O_CREAT
        try:
            fd = os.open(p, flags, 0o600)
        except OSError as err:
            raise Bit3Error(f"cannot open Bit3 window {p}: {err.strerror}") from err
        try:
            st = os.fstat(fd)
            import stat as _stat
            if _stat.S_ISREG(st.st_mode):
                if st.st_size == 0 and create:
                    os.ftruncate(fd, BUFFER_SIZE)
                elif st.st_size != BUFFER_SIZE:
                    raise LayoutMismatchError(f"Bit3 window {p}: size {st.st_size} bytes, expected "
                                              f"{BUFFER_SIZE}")
            mm = mmap.mmap(fd, BUFFER_SIZE, access=mmap.ACCESS_READ if readonly else mmap.ACCESS_WRITE)
        except BaseException:
            os.close(fd)
            raise

        def closer() -> None:
            mm.close()
            os.close(fd)

        buf = cls(mm, layout, name=str(p), fd=fd, readonly=readonly, closer=closer)
        try:
            if create and bytes(buf._mv[0:8]) != MAGIC:
                buf._initialise()
            buf._verify()
        except BaseException:
            buf.close()
            raise
        return buf

    @staticmethod
    def owner_alive(name: str = "pfma", area: str = "inputs") -> tuple[bool, str]:
        """Is the writer of ``area`` (default: the service) of POSIX shared memory ``name``
        alive? Decided without attaching, so for a buffer of any layout (another rack file),
        and without writing or locking anything.

        Alive means the writer holds its claim lock (the OFD byte lock :meth:`claim` takes;
        it dies with the process), not that the pid in the owner record runs: a dead
        owner's pid may belong to another process by now. A segment that cannot be opened
        counts as alive (it cannot be proved unused).

        :returns: ``(alive, description)``; the description names the owner (name, pid)
            from the header's owner record when the segment is a Bit3 buffer
        """
        import _posixshmem  # the C module multiprocessing.shared_memory uses on POSIX
        path = f"/dev/shm/{name}"
        index = next((i for i, a in enumerate(AREA_MAP) if a[0] == area and a[3]), None)
        if index is None:
            raise Bit3Error(f"Bit3 area {area!r} has no owner (no writer role writes it)")
        try:
            fd = _posixshmem.shm_open("/" + name, os.O_RDONLY, mode=0o600)
        except FileNotFoundError:
            return False, f"no buffer {path}"
        except OSError as err:
            return True, f"{path} cannot be inspected ({err.strerror}), so it may be in use"
        try:
            head = os.pread(fd, 1024, 0)
            try:
                locked = _byte_locked(fd, index)
            except OSError as err:
                return True, f"{path}: cannot test its claim lock ({err.strerror}), so it may be in use"
        finally:
            os.close(fd)
        if len(head) < 1024 or head[:8] != MAGIC:
            what = f"{path} is not a Bit3 buffer"
            return locked, what + (" and a process holds a lock on it" if locked else " (nobody holds it)")
        h = _header_offsets()
        rec = np.frombuffer(head, OWNER_DTYPE, 1, h["owners"] + index * OWNER_DTYPE.itemsize)[0]
        pid = int(rec["pid"])
        owner = bytes(rec["name"]).rstrip(b"\0").decode("utf-8", "replace")
        rack = head[h["rack_name"]:h["rack_name"] + 16].rstrip(b"\0").decode("utf-8", "replace")
        hash_hex = head[h["layout_hash"]:h["layout_hash"] + 8].hex()
        where = f"rack {rack!r}, layout {hash_hex}"
        if locked:
            return True, f"owned by {owner!r} (pid {pid}), which holds its claim lock ({where})"
        if pid > 0:
            return False, f"last owner {owner!r} (pid {pid}) is gone: it holds no claim lock ({where})"
        return False, f"no owner{f' (last: {owner!r})' if owner else ''} ({where})"

    @staticmethod
    def unlink(name: str = "pfma") -> bool:
        """Remove POSIX shared memory ``name``; False if it did not exist."""
        return Segment.remove_segment(name)

    def _initialise(self) -> None:
        lay = self.layout
        mv = self._root
        mv[:] = bytes(BUFFER_SIZE)
        h = self._hdr_off
        struct.pack_into("<IIII", mv, h["layout_version"], LAYOUT_VERSION, lay.area("header").size,
                         BUFFER_SIZE, len(lay.areas))
        mv[h["layout_hash"]:h["layout_hash"] + 8] = lay.hash
        struct.pack_into("<Q", mv, h["created_ns"], time.time_ns())
        name = lay.rack_name.encode()[:16]
        mv[h["rack_name"]:h["rack_name"] + len(name)] = name
        at = h["area_table"]
        for a in lay.areas:
            n = a.name.encode()[:16]
            e = at + 32 * a.index
            mv[e:e + len(n)] = n
            struct.pack_into("<IIII", mv, e + 16, a.offset, a.size, a.body_offset, a.body_size)
        mv[0:8] = MAGIC  # last: a buffer without magic is "not initialised yet"

    def _verify(self) -> None:
        mv = self._mv
        h = self._hdr_off
        magic = bytes(mv[0:8])
        if magic != MAGIC:
            # all zero: a service is still writing the header (the magic goes last); anything
            # else is not a Bit3 buffer (tools wait out the first, never the second)
            raise LayoutMismatchError(f"Bit3 buffer {self.name}: magic {magic!r}, expected "
                                      f"{MAGIC!r} " + ("(not initialised yet)" if magic == bytes(8)
                                                       else "(not a Bit3 buffer)"))
        version, _hsize, size, _n = struct.unpack_from("<IIII", mv, h["layout_version"])
        if version != LAYOUT_VERSION:
            raise LayoutMismatchError(f"Bit3 buffer {self.name}: layout version {version}, this "
                                      f"program speaks {LAYOUT_VERSION}")
        if size != BUFFER_SIZE:
            raise LayoutMismatchError(f"Bit3 buffer {self.name}: header says {size} bytes, "
                                      f"expected {BUFFER_SIZE}")
        got = bytes(mv[h["layout_hash"]:h["layout_hash"] + 8])
        if got != self.layout.hash:
            rack = bytes(mv[h["rack_name"]:h["rack_name"] + 16]).rstrip(b"\0").decode(errors="replace")
            raise LayoutMismatchError(
                f"Bit3 buffer {self.name}: layout hash {got.hex()} (rack {rack!r}) differs from "
                f"this program's {self.layout.hash_hex} (rack {self.layout.rack_name!r}); both "
                f"sides must use the same rack file and ioservice version")

    # --- low-level words -------------------------------------------------------------

    def _word(self, offset: int, fmt: WordFormat) -> memoryview[Any]:
        """A 1-element typed view (aligned single load/store) of the buffer."""
        size = struct.calcsize(fmt)
        if offset % size:
            raise Bit3Error(f"Bit3 word at {offset} is not {size}-byte aligned")
        v = self._mv[offset:offset + size].cast(fmt)
        self._views.append(v)
        return v

    def _owner_offset(self, index: int, fld: str) -> int:
        return self._hdr_off["owners"] + index * OWNER_DTYPE.itemsize + struct_field(OWNER_DTYPE, fld)[1]

    # --- header ------------------------------------------------------------------------

    def owner(self, area: str) -> OwnerInfo:
        """The owner slot of an area (read consistently under the slot's counter)."""
        a = self.layout.area(area)
        base = self._owner_offset(a.index, "seq")
        for _ in range(1000):
            s1 = struct.unpack_from("<Q", self._mv, base)[0]
            raw = bytes(self._mv[base:base + OWNER_DTYPE.itemsize])
            if not s1 & 1 and struct.unpack_from("<Q", self._mv, base)[0] == s1:
                break
            os.sched_yield()
        rec = np.frombuffer(raw, OWNER_DTYPE)[0]
        return OwnerInfo(area, int(rec["pid"]), bytes(rec["name"]).decode("utf-8", "replace"),
                         int(rec["claimed_ns"]), int(rec["heartbeat"]), float(rec["heartbeat_t_s"]),
                         int(rec["takeovers"]), int(rec["flags"]))

    def owner_pid_token(self, area: str) -> tuple[int, int]:
        """``(pid, token)`` of an area's owner, cheap enough for every frame: aligned loads
        from views cached on first use, consistent under the owner record's counter.
        The token is the record's ``claimed_ns``, rewritten (strictly increasing) by every
        :meth:`claim` and release, so a new claim -- even by the same pid -- changes it.
        ``pid`` is 0 when nobody owns the area; ``(0, 0)`` also when no stable copy came in
        ``TRY_READ_ATTEMPTS`` tries (a claim being written right now, or a claimer killed
        inside it): no owner this time."""
        v = self._owner_views.get(area)
        if v is None:
            a = self.layout.area(area)
            if not a.writer:
                raise Bit3Error(f"Bit3 area {area!r} has no owner (no writer role writes it)")
            v = self._owner_views[area] = (
                self._word(self._owner_offset(a.index, "seq"), "Q"),
                self._word(self._owner_offset(a.index, "pid"), "i"),
                self._word(self._owner_offset(a.index, "claimed_ns"), "Q"))
        seq, pid, token = v
        for _ in range(TRY_READ_ATTEMPTS):
            s1 = seq[0]
            if not s1 & 1:
                p, t = pid[0], token[0]
                if seq[0] == s1:
                    return p, t
        return 0, 0

    def header(self) -> HeaderInfo:
        """A copy of the header's identification, state, frame and owners."""
        mv, h = self._mv, self._hdr_off
        version, _hs, size, _n = struct.unpack_from("<IIII", mv, h["layout_version"])
        state = struct.unpack_from("<I", mv, h["service_state"])[0]
        try:
            state = ServiceState(state)
        except ValueError:
            state = ServiceState.FAULT
        return HeaderInfo(
            magic=bytes(mv[0:8]), layout_version=version, buffer_size=size,
            layout_hash=bytes(mv[h["layout_hash"]:h["layout_hash"] + 8]),
            calibration_hash=bytes(mv[h["calibration_hash"]:h["calibration_hash"] + 8]),
            created_ns=struct.unpack_from("<Q", mv, h["created_ns"])[0],
            service_state=state,
            frame=self._read_q(h["frame"]),
            frame_t_s=struct.unpack_from("<d", mv, h["frame_t_s"])[0],
            rack_name=bytes(mv[h["rack_name"]:h["rack_name"] + 16]).rstrip(b"\0").decode(),
            owners=tuple(self.owner(a.name) for a in self.layout.areas if a.writer))

    def _read_q(self, offset: int) -> int:
        v = self._mv[offset:offset + 8].cast("Q")
        try:
            return v[0]
        finally:
            v.release()

    @property
    def service_state(self) -> ServiceState:
        return self.header().service_state

    def _require(self, area: str) -> None:
        if area not in self._claimed:
            raise OwnershipError(f"Bit3 buffer {self.name}: this attachment does not own area "
                                 f"{area!r} (owner: {self.owner(area).describe()})")

    def set_service_state(self, state: ServiceState) -> None:
        """Header service state (inputs owner only)."""
        self._require("inputs")
        self._word_cached("service_state", "I")[0] = int(ServiceState(state))

    def set_frame(self, frame: int, t_s: float) -> None:
        """Header frame counter and time (inputs owner only; two aligned 8-byte stores)."""
        self._require("inputs")
        self._word_cached("frame_t_s", "d")[0] = t_s
        self._word_cached("frame", "Q")[0] = frame

    # --- frame notification (bit3.futex) ------------------------------------------------

    def _frame_addr(self) -> int:
        """This mapping's address of the header frame counter's low 32-bit word (the futex
        word; little-endian, 8-byte aligned). Taken through a numpy view released at once:
        it holds no export of the mapping, so close() is unaffected."""
        a = self.__dict__.get("_frame_word_addr")
        if a is None:
            view = np.frombuffer(self._mv, dtype=np.uint8, count=1, offset=self._hdr_off["frame"])
            a = self.__dict__["_frame_word_addr"] = int(view.ctypes.data)
            del view
        return a

    def frame_word(self) -> int:
        """The low 32 bits of the header frame counter now (what :meth:`wait_frame` compares)."""
        return int(self._word_cached("frame", "Q")[0]) & 0xFFFFFFFF

    def wake_frame_waiters(self) -> int:
        """After :meth:`set_frame`: wake every process waiting in :meth:`wait_frame` (one futex
        wake); returns how many were waiting (-1 where futexes are not available)."""
        if futex.AVAILABLE:
            return futex.wake(self._frame_addr())
        return -1

    def wait_frame(self, seen_word: int, timeout_s: float) -> str:
        """Sleep until the header frame counter's low word differs from ``seen_word`` (a
        frame was published since) or ``timeout_s`` passes; returns ``bit3.futex`` WOKEN,
        CHANGED or TIMED_OUT. Where futexes are not available: one sleep of ``timeout_s``."""
        if not futex.AVAILABLE:
            time.sleep(max(0.0, timeout_s))
            return futex.TIMED_OUT
        return futex.wait(self._frame_addr(), seen_word, timeout_s)

    def set_calibration_hash(self, digest: bytes) -> None:
        """Header calibration hash slot, 8 bytes (inputs owner only)."""
        self._require("inputs")
        if len(digest) < 8:
            raise Bit3Error(f"calibration hash needs 8 bytes, got {len(digest)}")
        off = self._hdr_off["calibration_hash"]
        self._mv[off:off + 8] = digest[:8]

    def _word_cached(self, field: str, fmt: WordFormat) -> memoryview[Any]:
        key = "_w_" + field
        v = self.__dict__.get(key)
        if v is None:
            v = self.__dict__[key] = self._word(self._hdr_off[field], fmt)
        return v

    # --- ownership ---------------------------------------------------------------------

    def claim(self, writer: str, owner: str, *, simulated: bool = False) -> list[OwnerInfo]:
        """Claim every area of a writer role (``"service"``/``"inputs"`` or
        ``"controller"``/``"commands"``) for ``owner``.

        :param simulated: the claimer runs on the simulated rack: ``OWNER_FLAG_SIMULATED`` is
            written in its owner slots with the claim (bit3/layout.py)

        :returns: the previous owners whose (dead) claims were taken over
        :raises OwnershipError: an area has a live owner (named in the message)
        """
        role = resolve_role(writer)
        if self.readonly:
            raise Bit3Error(f"Bit3 buffer {self.name} is attached read-only; attach with "
                            f"readonly=False to write {role} areas")
        name = owner.encode("utf-8")[:OWNER_NAME_BYTES]
        taken: list[str] = []
        previous: list[OwnerInfo] = []
        try:
            for area_name in WRITER_ROLES[role]:
                a = self.layout.area(area_name)
                if area_name in self._claimed:
                    raise OwnershipError(f"Bit3 buffer {self.name}: area {area_name!r} already "
                                         f"claimed by this attachment ({self._claimed[area_name]!r})")
                try:
                    _lock_byte(self._fd, a.index, True)
                except OSError as err:
                    if err.errno not in (errno.EAGAIN, errno.EACCES):
                        raise
                    cur = self.owner(area_name)
                    raise OwnershipError(
                        f"Bit3 buffer {self.name}: area {area_name!r} is owned by {cur.name!r} "
                        f"(pid {cur.pid}); refusing second writer {owner!r} (one writer per "
                        f"area)") from None
                taken.append(area_name)
                prev = self.owner(area_name)
                if prev.pid > 0:
                    previous.append(prev)
                self._write_owner(a.index, os.getpid(), name, prev.takeovers + (prev.pid > 0),
                                  OWNER_FLAG_SIMULATED if simulated else 0)
                self._claimed[area_name] = owner
                lock = self._locks[area_name]
                lock.take_over()
        except BaseException:
            for area_name in taken:
                self._release_area(area_name)
            raise
        return previous

    def _write_owner(self, index: int, pid: int, name: bytes, takeovers: int, flags: int = 0) -> None:
        """One owner slot, under its counter; ``flags`` beside ``OWNER_FLAG_CLAIMED``, which a
        claim (``pid`` > 0) always has and a release (``pid`` 0) clears with the rest."""
        base = self._owner_offset(index, "seq")
        seq = self._mv[base:base + 8].cast("Q")
        try:
            s = seq[0]
            seq[0] = s + 1 + (s & 1)
            struct.pack_into("<iI", self._mv, base + struct_field(OWNER_DTYPE, "pid")[1], pid,
                             (OWNER_FLAG_CLAIMED | flags) if pid else 0)
            no = base + struct_field(OWNER_DTYPE, "name")[1]
            self._mv[no:no + OWNER_NAME_BYTES] = name.ljust(OWNER_NAME_BYTES, b"\0")
            cns = base + struct_field(OWNER_DTYPE, "claimed_ns")[1]
            # the claim token (owner_pid_token): strictly increasing, also within one clock tick
            struct.pack_into("<Q", self._mv, cns, max(time.time_ns(), struct.unpack_from("<Q", self._mv, cns)[0] + 1))
            struct.pack_into("<I", self._mv, base + struct_field(OWNER_DTYPE, "takeovers")[1], takeovers)
            seq[0] = s + 2 + (s & 1)
        finally:
            seq.release()

    def _release_area(self, area_name: str) -> None:
        a = self.layout.area(area_name)
        if area_name in self._claimed:
            cur = self.owner(area_name)
            if cur.pid == os.getpid():
                self._write_owner(a.index, 0, cur.name.encode()[:OWNER_NAME_BYTES], cur.takeovers)
            del self._claimed[area_name]
        try:
            _lock_byte(self._fd, a.index, False)
        except OSError:
            pass

    def release(self) -> None:
        """Give up every claimed area (the owner slot keeps the name, pid becomes 0)."""
        for area_name in list(self._claimed):
            self._release_area(area_name)
        self._writers.clear()

    @property
    def claimed(self) -> tuple[str, ...]:
        return tuple(self._claimed)

    # --- areas ---------------------------------------------------------------------------

    def writer(self, area: str) -> AreaWriter:
        """The writer of a claimed area (one per attachment and area)."""
        self._require(area)
        w = self._writers.get(area)
        if w is None:
            a = self.layout.area(area)
            w = self._writers[area] = AreaWriter(self, a, self._locks[area], a.index)
        return w

    def reader(self, area: str) -> AreaReader:
        """A new reader of an area (each has its own preallocated record)."""
        a = self.layout.area(area)
        if not a.seqlocked or a.body_dtype is None:
            raise Bit3Error(f"Bit3 area {area!r} is not a data area")
        return AreaReader(self, a, self._locks[area])

    def queue(self, area: str) -> MessageQueue:
        """A message-queue area (``service_messages``/``controller_messages``)."""
        q = self._queues.get(area)
        if q is None:
            a = self.layout.area(area)
            if a.body_dtype is None or "entries" not in struct_names(a.body_dtype):
                raise Bit3Error(f"Bit3 area {area!r} is not a message queue")
            q = self._queues[area] = MessageQueue(self, a, self._locks[area])
        if area in self._claimed and q._head is None:
            q._attach_writer(self)
        return q

    def lock(self, area: str) -> SeqLock:
        """The raw sequence lock of an area (benchmarks, C accelerators)."""
        return self._locks[area]

    # --- closing -------------------------------------------------------------------------

    def _release_views(self) -> None:
        self._writers.clear()
        self._queues.clear()
        self._owner_views.clear()
        for v in self._views:
            v.release()
        self._views.clear()
        for lk in self._locks.values():
            lk.release()
        self._locks.clear()
        if self._mv is not self._root:
            self._mv.release()
        self._root.release()

    def _unmap(self) -> None:
        self.release()
        self._release_views()

    def close(self, unlink: bool = False) -> None:
        """Release claims, unmap; with ``unlink`` also remove the shared-memory name."""
        if self._closer is None:
            return
        super().close()
        if unlink and self._shm is not None:
            Bit3Buffer.unlink(self.name)

    def __repr__(self) -> str:
        return (f"<Bit3Buffer {self.name} {'ro' if self.readonly else 'rw'} "
                f"hash={self.layout.hash_hex} claimed={list(self._claimed)}>")
