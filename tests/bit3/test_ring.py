"""bit3.ring.FrameRing and the recorder reading from it (simulated time)."""

import struct
import uuid

import pytest

from bit3.client import Client
from tools.recording import InputsCapture, Recorder, read_frames
from bit3.ring import HEADER, FrameRing, RingError
from sim.rig import SimRig


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


def test_ring_file_has_the_buffer_segment_mode(name):
    import os
    import stat

    from bit3.ring import ring_path
    FrameRing.create(name, body_size=8, layout_hash=b"aaaaaaaa").close()
    assert stat.S_IMODE(os.stat(ring_path(name)).st_mode) == 0o600
    FrameRing.create(name, body_size=8, layout_hash=b"aaaaaaaa").close()  # replaced: still 0600
    assert stat.S_IMODE(os.stat(ring_path(name)).st_mode) == 0o600


@pytest.mark.realtime
def test_replacing_the_ring_never_pulls_the_memory_from_under_a_reader(name, mp):
    """A reader in another process maps ring A (256 slots); the service "restarts" and
    creates ring B (4 slots, a smaller file) at the same path. Truncating A's file would
    kill the reader with SIGBUS when it touches A's pages; a new file leaves A's memory
    whole, and the reader sees the replacement and attaches B."""
    import signal

    from tests.bit3 import _workers
    a = FrameRing.create(name, body_size=100, layout_hash=b"aaaaaaaa")
    for k in range(10):
        a.write(bytes([k]) * 100)
    parent, child_end = mp.Pipe()
    child = mp.Process(target=_workers.ring_reader_across_replacement, args=(name, b"aaaaaaaa", child_end))
    child.start()
    try:
        assert parent.poll(60.0), "reader did not start"
        assert parent.recv() == ("attached", 10, False)
        b = FrameRing.create(name, body_size=100, layout_hash=b"aaaaaaaa", n_slots=4)
        b.write(bytes([200]) * 100)
        parent.send("replaced")
        child.join(60.0)
        assert child.exitcode != -signal.SIGBUS, "the reader died of SIGBUS: its ring was truncated"
        assert child.exitcode == 0
        tag, size, count, last, replaced, n_new, count_new, first_new, new_replaced = parent.recv()
        assert size == a._mm.size() and count == 10 and last == bytes([9]) * 100  # A, whole
        assert replaced and not new_replaced
        assert (n_new, count_new, first_new) == (4, 1, bytes([200]) * 100)
        b.close()
    finally:
        if child.is_alive():
            child.kill()
        a.close()


def test_capture_reattaches_to_a_replaced_ring_and_says_so(tmp_path):
    """The service restarts (a new ring file at the same path): the capture finishes the
    old ring, attaches the new one, takes it from its first frame, and the drain stops
    at the switch with a note so the recorder can start a new session there."""
    rig = SimRig(prefix="pfma-test-")
    try:
        body, h = rig.layout.area("inputs").body_size, rig.layout.hash
        rig.svc.ring = FrameRing.create(rig.name, body, h)
        client = Client.attach(rig.name, layout=rig.layout, clock_now=rig.clock.now)
        cap = InputsCapture(client, ring=FrameRing.attach(rig.name, h))
        rec = Recorder(client, tmp_path / "r.mcap")
        assert cap.take_from_ring() == 0
        rig.svc.loop.run(frames=10)
        assert not cap.check_ring()  # the same file: nothing to do
        assert cap.take_from_ring() == 10
        rig.svc.loop.run(frames=3)  # not yet taken when the service "restarts"
        old = rig.svc.ring
        rig.svc.ring = FrameRing.create(rig.name, body, h)
        old.close()
        rig.svc.loop.run(frames=5)
        assert cap.check_ring() and cap.ring_reattached == 1
        assert cap.take_from_ring() == 5 and cap.ring_lost == 0
        assert cap.drain(rec) == 13  # the old ring's frames, up to the switch
        assert "replaced" in cap.replaced_note and cap.ring.path == rig.svc.ring.path
        cap.replaced_note = None
        rec.attach(client)  # what `pfma record` does at the note (with the new service's client)
        assert cap.drain(rec) == 5
        c = rec.counters
        assert c.sessions == 2 and c.frames_recorded == 18 and c.recorder_missed == 0
        rec.close()
        cap.stop()
        client.close()
    finally:
        rig.close()
        FrameRing.unlink(rig.name)
