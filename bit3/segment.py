"""The lifecycle of one POSIX shared-memory segment (``/dev/shm/<name>``), shared by the
Bit3 buffer (:class:`bit3.buffer.Bit3Buffer`) and the controller's world model
(:class:`controller.worldmodel.WorldModel`): open or create it without the resource
tracker (:func:`open_shm`), hold it (:meth:`Segment._hold`), unmap it once
(:meth:`Segment.close`, also on garbage collection and at the end of a ``with``), remove
its name (:meth:`Segment.remove_segment`).

**resource_tracker workaround.** On Python < 3.13 ``SharedMemory`` registers every
segment it opens -- also one it merely attaches to -- with multiprocessing's resource
tracker, which unlinks the segment when that process exits (CPython gh-82300). A tool
that attached, read and quit would delete the service's buffer. So every open is
followed by ``resource_tracker.unregister`` (3.13+: ``track=False``). A segment is
therefore never removed automatically: its creator removes it by name. (If two
processes open the same name at the same instant, the tracker may print a harmless
KeyError.)

What each kind of segment keeps in it (layout, owner records, locks) is its own business.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Callable, Self

if TYPE_CHECKING:
    from multiprocessing.shared_memory import SharedMemory

__all__ = ["Segment", "open_shm", "shm_fd"]


def open_shm(name: str, create: bool, size: int = 0) -> SharedMemory:
    """Open (or create, ``size`` bytes) POSIX shared memory ``name`` without
    resource-tracker registration (module docstring).

    :raises FileExistsError: ``create`` and the name exists
    :raises FileNotFoundError: not ``create`` and no such name, or the name exists but is
        still empty: its creator has opened it and not yet sized it (``shm_open`` then
        ``ftruncate``), so there is nothing to attach to yet
    :raises PermissionError: this user may not open it read-write
    """
    from multiprocessing import shared_memory
    try:
        if sys.version_info >= (3, 13):
            return shared_memory.SharedMemory(name, create=create, size=size if create else 0,
                                              track=False)
        shm = shared_memory.SharedMemory(name, create=create, size=size if create else 0)
    except ValueError as e:  # mmap of the empty segment: "cannot mmap an empty file"
        if create:
            raise
        raise FileNotFoundError(f"/dev/shm/{name} exists but is still empty (being created)") from e
    from multiprocessing import resource_tracker
    # _name: the "/name" the tracker registered (typeshed lists only the public name)
    resource_tracker.unregister(shm._name, "shared_memory")  # type: ignore[attr-defined]
    return shm


def shm_fd(shm: SharedMemory) -> int:
    """The file descriptor of an open segment (locks, permissions, space)."""
    return shm._fd  # type: ignore[attr-defined]  # (typeshed lists no _fd)


class Segment:
    """Base of an object mapped on one shared-memory segment (or on other memory: a file
    window, private memory; then ``_shm`` stays None and the closer is the subclass's).

    A subclass sets ``_closer`` (what unmaps the memory) when it maps it, by
    :meth:`_hold` for a segment, and releases its own views of the memory in
    :meth:`_unmap`, which :meth:`close` calls once, before the closer.
    """

    name: str | None = None
    _shm: SharedMemory | None = None  #: the POSIX segment held, when the memory is one
    _fd: int = -1  #: its file descriptor (locks, permissions)
    _closer: Callable[[], None] | None = None  #: None once closed (or never mapped)

    def _hold(self, shm: SharedMemory) -> memoryview:
        """Hold an opened segment: :meth:`close` closes it. Returns its memory."""
        assert shm.buf is not None  # an open segment's memory
        self._shm = shm
        self._fd = shm_fd(shm)
        self._closer = shm.close
        return shm.buf

    @staticmethod
    def remove_segment(name: str) -> bool:
        """Remove POSIX shared memory ``name`` (processes that have it mapped keep their
        mapping); False if it did not exist."""
        import _posixshmem  # the C module multiprocessing.shared_memory uses on POSIX
        try:
            _posixshmem.shm_unlink("/" + name)  # no tracker round trip
        except FileNotFoundError:
            return False
        return True

    @property
    def closed(self) -> bool:
        return self._closer is None

    def _unmap(self) -> None:
        """Release every view of the memory (the subclass's; called once, by :meth:`close`)."""

    def close(self) -> None:
        """Release the views and unmap; the segment's name stays (:meth:`remove_segment`)."""
        if self._closer is None:
            return
        self._unmap()
        closer, self._closer = self._closer, None
        closer()

    def __del__(self) -> None:
        # release the views before SharedMemory's own finaliser tries to unmap
        if getattr(self, "_closer", None) is not None:
            try:
                self.close()
            except Exception:
                pass

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
