"""The I/O service's frame allocates nothing that survives it (issue 16 item 6).

The whole system runs powered up in the system simulator (the service ARMED, driving
the DAC from the controller's commands: every task of the service's frame at work).
After a warm-up traced from its start, 1,000 service frames run under ``tracemalloc``;
the net growth of the memory allocated while ``ioservice/`` or ``bit3/`` code was on the
stack, leaving out what the controller's frame and the fake boards allocate (the rig
calls both from inside the service's loop), must be about zero. Objects replaced every
frame (the latest F/T record, the hand controllers' latest state) make a few hundred
bytes of noise either way; a per-frame list append of one float would be about 32 KB.
"""

from __future__ import annotations

import os
import tracemalloc

import pytest

import bit3
import controller
import fakes
import ioservice
from tests._alloc import growth, running_system

FRAMES = 1000
#: frames of the demonstration that the check can fail (shorter: it only has to exceed the limit)
LEAK_FRAMES = 400
#: net growth allowed over FRAMES frames (noise of replaced objects; measured 0.4 KB)
ALLOWED_BYTES = 4096


def _under(pkg) -> str:
    """A filename pattern for a package's own files (its directory: these tests live in
    tests/ioservice/, which a pattern like */ioservice/* would match too)."""
    return os.path.join(os.path.dirname(pkg.__file__), "*")


SERVICE = [tracemalloc.Filter(True, _under(ioservice), all_frames=True),
           tracemalloc.Filter(True, _under(bit3), all_frames=True),
           tracemalloc.Filter(False, _under(controller), all_frames=True),
           tracemalloc.Filter(False, _under(fakes), all_frames=True)]


@pytest.fixture
def running():
    yield from running_system()


def test_service_frame_allocates_nothing_that_survives(running):
    grown, objects, top = growth(running, FRAMES, SERVICE)
    assert grown <= ALLOWED_BYTES, (f"service frames kept {grown} B ({objects} objects) over {FRAMES} frames; "
                                    f"largest: " + "; ".join(map(str, top)))


def test_the_check_sees_a_per_frame_append_in_the_service(running):
    """A service task that appends one float per frame to a list is caught (the check can fail)."""
    kept: list[float] = []
    svc = running.svc
    publish = svc._publish

    def leaky_publish(info) -> None:
        publish(info)
        kept.append(svc.clock.now() * 1.5)  # a new float every frame, kept

    svc._publish = leaky_publish
    grown, _, _ = growth(running, LEAK_FRAMES, SERVICE)
    assert kept
    assert grown > 2 * ALLOWED_BYTES  # ~32 B a frame: ~13 KB
