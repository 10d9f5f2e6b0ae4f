"""A recorder or scope waiting for a service meets the new buffer of a restarting service
before its header is written (all zeros): it waits, saying so, instead of ending the
recording as "a different layout" (the kill matrix met this in 3 of 100 service kills).
A buffer of another layout still raises at once."""

from __future__ import annotations

import os
import uuid

import pytest

from bit3.buffer import BUFFER_SIZE
from bit3.seqlock import LayoutMismatchError
from tools.attach import SHM_WORDS, service_status


@pytest.fixture
def zero_buffer():
    name = "pfma-test-uninit-" + uuid.uuid4().hex[:6]
    with open(f"/dev/shm/{name}", "wb") as f:
        f.write(bytes(BUFFER_SIZE))
    yield name
    os.unlink(f"/dev/shm/{name}")


def test_a_buffer_whose_header_is_not_written_yet_is_waited_for(zero_buffer):
    c, why = service_status(zero_buffer, words=SHM_WORDS)
    assert c is None and why == "buffer not initialised yet"


def test_a_buffer_of_another_kind_still_raises_at_once(zero_buffer):
    with open(f"/dev/shm/{zero_buffer}", "r+b") as f:
        f.write(b"NOTBIT3!")  # a magic, but not ours
    with pytest.raises(LayoutMismatchError, match="magic"):
        service_status(zero_buffer, words=SHM_WORDS)
