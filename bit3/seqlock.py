"""The sequence lock: one writer, any number of readers, never a torn copy.

**Sequence lock, memory ordering** (the conditions of perf-limits.md 4.4, checked here):

- the counter is one naturally aligned 8-byte word accessed only through
  ``memoryview.cast("Q")[0]`` -- one ``mov`` on x86-64, never torn (never
  ``struct.pack_into``/``int.from_bytes``, which go byte by byte);
- writer: ``seq = s+1`` (odd), copy the body, ``seq = s+2``. x86-64 is TSO: stores
  become visible in program order; ``memcpy``'s fast-string stores are not reordered
  with the stores around them, and glibc uses non-temporal stores only for copies of
  megabytes, never for <= 12 KB;
- reader: load seq (retry while odd), copy the body into a private record, load seq
  again and accept only if unchanged; x86 does not reorder loads with loads;
- every Python statement is a separate opaque C call, so the C compiler cannot move
  the copy across the counter accesses;
- exactly one writer per area (enforced by :meth:`Bit3Buffer.claim`); 64-bit counters
  never wrap;
- a writer that dies mid-write leaves the counter odd: readers give up after a bounded
  time with :class:`SeqLockTimeout` (never hang); the next owner makes it even again.
  A reader that must not wait at all (the service reading the commands every frame)
  uses the non-blocking :meth:`AreaReader.try_read` / :meth:`SeqLock.try_read_into`:
  at most ``TRY_READ_ATTEMPTS`` copies, no clock, no yield, and ``False`` when none was
  stable (the record keeps its last good copy).

This is **not** correct on weakly ordered CPUs (ARM64) without barriers; there the
``SeqLock.write``/``read_into`` pair is the place to drop in a C11-atomics version.
"""

from __future__ import annotations

import os
import time
from typing import Callable

from bit3.layout import SEQ_BLOCK
from pfma.errors import PfmaError, PfmaTimeoutError


class Bit3Error(PfmaError):
    """A Bit3 buffer problem (not initialised, read-only, wrong area ...)."""


class LayoutMismatchError(Bit3Error):
    """The buffer's magic, version, size or layout hash is not the one expected."""


class OwnershipError(Bit3Error):
    """An area already has a live writer."""


class SeqLockTimeout(Bit3Error, PfmaTimeoutError):
    """A reader could not get a stable copy in time (writer stuck or dead mid-write)."""


DEFAULT_READ_TIMEOUT_S = 0.1
#: fast retries before a reader starts yielding the CPU to a (maybe descheduled) writer
_SPIN_RETRIES = 64
#: copy attempts of one non-blocking read (SeqLock.try_read_into, AreaReader.try_read)
TRY_READ_ATTEMPTS = 3

# ----------------------------------------------------------------------------------------
# the sequence lock


class SeqLock:
    """One sequence-locked region: an 8-byte counter at ``offset``, the body at +64.

    ``write(src)`` and ``read_into(dst) -> seq`` take byte memoryviews of exactly the body
    size; nothing is allocated per call.
    """

    __slots__ = ("name", "_seq", "_body", "_s", "body_size", "retries", "timeout_s", "owner_lookup")

    #: what the lock protects, for error messages (subclasses for other segments override it)
    kind = "Bit3 area"

    def __init__(self, buf: memoryview, offset: int, body_size: int, name: str = "area",
                 timeout_s: float = DEFAULT_READ_TIMEOUT_S) -> None:
        if offset % 8:
            raise Bit3Error(f"seqlock {name}: counter offset {offset} is not 8-byte aligned")
        self.name = name
        self._seq = buf[offset:offset + 8].cast("Q")
        self._body = buf[offset + SEQ_BLOCK:offset + SEQ_BLOCK + body_size]
        self._s = self._seq[0]
        self.body_size = body_size
        self.retries = 0  #: failed read attempts (torn or in-progress), for statistics
        self.timeout_s = timeout_s
        #: callable -> "name (pid N)" of the writer, for error messages
        self.owner_lookup: Callable[[], str] | None = None

    @property
    def seq(self) -> int:
        """The current counter (even = stable)."""
        return self._seq[0]

    def take_over(self) -> None:
        """Become the writer: continue from the counter, making it even if a dead writer left it odd."""
        s = self._seq[0]
        if s & 1:
            s += 1
            self._seq[0] = s
        self._s = s

    def begin(self) -> None:
        """Start an in-place update (writer only); pair with :meth:`end`."""
        self._seq[0] = self._s + 1

    def end(self) -> int:
        s = self._s + 2
        self._seq[0] = s
        self._s = s
        return s

    def write(self, src: memoryview) -> int:
        """Publish ``src`` (the whole body) under the lock; returns the new (even) counter."""
        s = self._s
        seq = self._seq
        seq[0] = s + 1
        self._body[:] = src
        seq[0] = s + 2
        self._s = s + 2
        return s + 2

    def read_into(self, dst: memoryview) -> int:
        """Copy a stable body into ``dst``; returns the counter it was stable at.

        :raises SeqLockTimeout: no stable copy within ``timeout_s``
        """
        seq = self._seq
        s1 = seq[0]
        if not s1 & 1:
            dst[:] = self._body
            if seq[0] == s1:
                return s1
        return self._read_retry(dst)

    def read_part_into(self, dst: memoryview, start: int) -> int:
        """Copy a stable ``body[start:start + len(dst)]`` into ``dst`` (one field, not the
        whole body); returns the counter it was stable at. Same rules as :meth:`read_into`."""
        part = self._body[start:start + len(dst)]
        seq = self._seq
        s1 = seq[0]
        if not s1 & 1:
            dst[:] = part
            if seq[0] == s1:
                return s1
        return self._read_retry(dst, part)

    def try_read_into(self, dst: memoryview, scratch: memoryview, attempts: int = TRY_READ_ATTEMPTS) -> int:
        """Non-blocking read: at most ``attempts`` copies of the body into ``scratch`` (no
        clock, no yield); the first stable one is copied on into ``dst``. Returns the
        counter it was stable at, or -1 when none was (counter odd: a write in progress or
        a writer dead mid-write; or it changed during the copy) -- then ``dst`` is left as
        it was. ``scratch`` and ``dst`` are caller-preallocated views of the body size."""
        seq, body = self._seq, self._body
        for _ in range(attempts):
            s1 = seq[0]
            if not s1 & 1:
                scratch[:] = body
                if seq[0] == s1:
                    dst[:] = scratch
                    return s1
            self.retries += 1
        return -1

    def _read_retry(self, dst: memoryview, body: memoryview | None = None) -> int:
        seq = self._seq
        body = self._body if body is None else body
        deadline = time.perf_counter() + self.timeout_s
        n = 0
        while True:
            self.retries += 1
            n += 1
            s1 = seq[0]
            if not s1 & 1:
                dst[:] = body
                if seq[0] == s1:
                    return s1
            if n > _SPIN_RETRIES:
                if time.perf_counter() > deadline:
                    try:
                        who = self.owner_lookup() if self.owner_lookup else "?"
                    except Exception:  # the message must not hide the timeout
                        who = "?"
                    raise SeqLockTimeout(
                        f"{self.kind} {self.name}: no stable copy in {self.timeout_s * 1e3:.0f} ms "
                        f"(sequence {s1}{', odd: write in progress' if s1 & 1 else ''}); "
                        f"writer {who} stuck or dead mid-write")
                os.sched_yield()

    def release(self) -> None:
        self._seq.release()
        self._body.release()
