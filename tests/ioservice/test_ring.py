"""ioservice.ring.FrameRing and the recorder reading from it (simulated time)."""

import struct
import uuid

import pytest

from ioservice.client import Client
from ioservice.recorder import InputsCapture, Recorder, read_frames
from ioservice.ring import HEADER, FrameRing, RingError
from ioservice.simrig import SimRig


@pytest.fixture
def name():
    n = "pfma-test-" + uuid.uuid4().hex[:8]
    yield n
    FrameRing.unlink(n)


def test_frames_round_trip_and_overwritten_frames_are_refused(name):
    w = FrameRing.create(name, body_size=100, layout_hash=b"12345678", n_slots=4)
    r = FrameRing.attach(name, b"12345678")
    for k in range(6):
        w.write(bytes([k]) * 100)
    assert r.count() == 6
    assert r.read(5) == bytes([5]) * 100 and r.read(2) == bytes([2]) * 100
    assert r.read(1) is None  # overwritten by frame 5 (4 slots)
    assert r.read(6) is None  # not written yet
    # a slot being written (odd stamp) is not whole
    struct.pack_into("<Q", w._mm, HEADER + (6 % 4) * w.slot_size, 2 * 6 + 1)
    assert r.read(6) is None
    r.close()
    w.close()


def test_missing_ring_and_other_layout_are_refused(name):
    with pytest.raises(RingError, match="no frame ring"):
        FrameRing.attach(name)
    FrameRing.create(name, body_size=8, layout_hash=b"aaaaaaaa").close()
    with pytest.raises(RingError, match="layout 6161616161616161, expected"):
        FrameRing.attach(name, b"bbbbbbbb")


def test_recorder_behind_by_less_than_the_ring_loses_nothing(tmp_path):
    """A recorder that is not scheduled for 100 frames (312 ms) catches up from the ring
    with nothing missed; one that is 300 frames behind (more than 255) misses exactly
    the frames the ring no longer holds, and says so."""
    rig = SimRig(prefix="pfma-test-")
    try:
        ring = FrameRing.create(rig.name, rig.layout.area("inputs").body_size, rig.layout.hash)
        rig.svc.ring = ring
        rig.run(0.1)
        client = Client.attach(rig.name, layout=rig.layout, clock_now=rig.clock.now)
        cap = InputsCapture(client, ring=FrameRing.attach(rig.name, rig.layout.hash))
        rec = Recorder(client, tmp_path / "r.mcap")
        assert cap.take_from_ring() == 0  # what was there before is history
        rig.svc.loop.run(frames=100)
        assert cap.take_from_ring() == 100
        assert cap.drain(rec) == 100
        assert rec.counters.recorder_missed == 0 and rec.counters.frame_gaps == 0
        rig.svc.loop.run(frames=300)
        assert cap.take_from_ring() == 255 and cap.ring_lost == 45
        cap.drain(rec)
        assert rec.counters.recorder_missed == 45 and rec.counters.frames_recorded == 355
        c = rec.close()
        assert not c.lossless
        frames = [int(r["frame"]) for _, _, r in read_frames(tmp_path / "r.mcap")]
        assert len(frames) == 355 and frames[99] + 46 == frames[100]  # the 45 lost frames
        client.close()
    finally:
        rig.close()
        FrameRing.unlink(rig.name)
