"""A segment caught between its creator's ``shm_open`` and ``ftruncate`` is empty: attaching
to it is "not there yet" (one clear error), not a ValueError from mmap. CI's realtime pass once
failed this way: a test polling a world model attached in that instant."""

import os

import pytest

from bit3.buffer import Bit3Buffer, Bit3Error
from bit3.segment import Segment, open_shm
from controller.worldmodel import WorldModel, WorldModelError


@pytest.fixture
def empty_segment(shm_name):
    import _posixshmem
    fd = _posixshmem.shm_open("/" + shm_name, os.O_CREAT | os.O_EXCL | os.O_RDWR, mode=0o600)
    os.close(fd)  # created, never sized: what a creator has between its two system calls
    yield shm_name
    Segment.remove_segment(shm_name)


def test_open_shm_calls_an_empty_segment_not_found(empty_segment):
    with pytest.raises(FileNotFoundError, match="still empty"):
        open_shm(empty_segment, create=False)


def test_the_buffer_and_the_world_model_say_not_running_for_an_empty_segment(empty_segment):
    with pytest.raises(Bit3Error, match="is the I/O service running"):
        Bit3Buffer.attach(empty_segment)
    with pytest.raises(WorldModelError, match="is the controller running"):
        WorldModel.attach(empty_segment)


def test_read_only_attach_of_an_empty_segment_is_not_found(empty_segment):
    from bit3 import access
    with pytest.raises(FileNotFoundError, match="still empty"):
        access.open_readonly(empty_segment)
