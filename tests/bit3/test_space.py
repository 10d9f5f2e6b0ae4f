"""A full /dev/shm is a one-line error at creation that leaves nothing behind (issue 29
item 8: a /dev/shm too small for the buffer ended `pfma serve` in SIGBUS, exit 135, no
message, leaving the buffer, ring and faults files behind).

A full /dev/shm is simulated by making ``os.posix_fallocate`` fail with ENOSPC, as the
kernel does on a tmpfs with no room (nothing here fills the real /dev/shm)."""

from __future__ import annotations

import errno
import os
import uuid

import pytest

from bit3.buffer import Bit3Buffer
from bit3.layout import BUFFER_SIZE, default_layout
from bit3.ring import FrameRing
from bit3.space import ShmFullError, reserve

_real = os.posix_fallocate


def _left(name: str) -> list[str]:
    return sorted(f for f in os.listdir("/dev/shm") if f.startswith(name))


def _full_for(monkeypatch, marker: str) -> list[str]:
    """posix_fallocate fails with ENOSPC for files whose path contains ``marker``."""
    seen: list[str] = []

    def fallocate(fd: int, offset: int, length: int) -> None:
        path = os.readlink(f"/proc/self/fd/{fd}")
        seen.append(path)
        if marker in path:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        _real(fd, offset, length)
    monkeypatch.setattr(os, "posix_fallocate", fallocate)
    return seen


def test_the_buffer_on_a_full_dev_shm_is_one_line_and_nothing_is_left(monkeypatch):
    name = "pfma-full-" + uuid.uuid4().hex[:6]
    seen = _full_for(monkeypatch, name)
    with pytest.raises(ShmFullError) as e:
        Bit3Buffer.create(name, default_layout())
    text = str(e.value)
    assert "\n" not in text and seen == [f"/dev/shm/{name}"]
    assert text.startswith(f"no room for the Bit3 buffer '{name}' (/dev/shm/{name}): it needs 32 KiB, /dev/shm has ")
    assert _left(name) == []


def test_the_ring_on_a_full_dev_shm_is_one_line_and_its_temporary_file_is_removed(monkeypatch):
    name = "pfma-full-" + uuid.uuid4().hex[:6]
    _full_for(monkeypatch, ".ring")
    with pytest.raises(ShmFullError, match=rf"no room for the frame ring of '{name}' \(/dev/shm/{name}.ring\): it needs "):
        FrameRing.create(name, 1024, b"12345678")
    assert _left(name) == []


def test_reserve_allocates_every_page_of_a_shm_file():
    path = f"/dev/shm/pfma-space-{uuid.uuid4().hex[:6]}"
    fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.ftruncate(fd, BUFFER_SIZE)
        assert os.fstat(fd).st_blocks == 0  # truncated only: no page yet (what SIGBUS came from)
        reserve(fd, BUFFER_SIZE, path, "a test file")
        assert os.fstat(fd).st_blocks * 512 >= BUFFER_SIZE
    finally:
        os.close(fd)
        os.unlink(path)


def test_without_posix_fallocate_the_pages_are_written_instead(monkeypatch, tmp_path):
    def unsupported(fd, offset, length):
        raise OSError(errno.EOPNOTSUPP, os.strerror(errno.EOPNOTSUPP))
    monkeypatch.setattr(os, "posix_fallocate", unsupported)
    path = str(tmp_path / "f")
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        os.ftruncate(fd, 100_000)
        reserve(fd, 100_000, path, "a test file")
        assert os.fstat(fd).st_size == 100_000 and os.fstat(fd).st_blocks * 512 >= 100_000
    finally:
        os.close(fd)
