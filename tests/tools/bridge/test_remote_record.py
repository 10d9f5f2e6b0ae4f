"""Remote tools, issue 19 item 2: ``pfma record``, ``scope``, ``watch`` and ``console`` with
``--buffer zenoh://HOST:PORT/NAME`` against a bridge on a simulated service over
tcp/127.0.0.1. A remote recording equals a local one frame by frame, and the frames it
lost are named exactly (:class:`tools.recording.remote.LinkLoss`)."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from controller.worldmodel import WorldModel

from sim.rig import SimRig
from tests.tools.bridge.test_bridge import free_port, until
from tools.bridge.bridge import Bridge
from tools.recording.remote import LinkLoss, RemoteRecording
from tools.bridge.remote import RemoteBuffer
from tools.bridge.session import open_session
from tools.cli import main
from tools.recording import RAW_TOPIC, Recorder, read_frames, read_metadata

pytest.importorskip("zenoh")


# --- the loss account alone (no link) ------------------------------------------------------

def test_link_loss_names_lost_frames_and_keeps_service_skips_apart():
    loss = LinkLoss()
    for seq, frame in [(2, 10), (4, 11), (10, 14),   # seq +6: publishes of frames 12, 13 lost
                       (12, 17),                     # seq +2, frame +3: the service skipped 15, 16
                       (14, 18), (20, 21), (22, 22), (26, 24)]:  # 19-20 lost, then 23
        loss.feed(seq, frame)
    assert loss.frames_lost == 5 and loss.ranges == [[12, 13], [19, 20], [23, 23]]
    assert loss.service_skipped == 2 and loss.received == 8
    assert "LOST 5 frames: frames 12-13, 19-20, 23" in loss.line("zenoh://h:1/b")
    # without sequence numbers (an older bridge) every frame gap counts as lost
    old = LinkLoss()
    for frame in (1, 2, 5):
        old.feed(None, frame)
    assert old.frames_lost == 2 and old.ranges == [[3, 4]] and not old.sequenced
    assert "frame counters only" in old.metadata("u")["counted_from"]
    # a gap that also holds frames the service skipped: counted as publishes, said
    mixed = LinkLoss()
    for seq, frame in [(2, 1), (6, 5)]:  # one publish lost, frame numbers 2-4 missing
        mixed.feed(seq, frame)
    assert mixed.frames_lost == 1 and mixed.ranges == [[2, 4]]
    assert "2 frame numbers within those ranges the service itself skipped" in mixed.line("u")


def test_link_loss_holds_a_bounded_list_of_ranges(monkeypatch):
    """A link losing every other frame for a long time: past MAX_RANGES the gaps merge into
    the last range (still covering every lost frame), counted and said."""
    import tools.recording.remote as record
    monkeypatch.setattr(record, "MAX_RANGES", 5)
    loss = LinkLoss()
    for k in range(40):  # frames 0, 2, 4, ...: every odd frame lost
        loss.feed(2 * (2 * k) + 2, 2 * k)
    assert loss.frames_lost == 39 and len(loss.ranges) == 5 and loss.merged == 34
    assert loss.ranges[:4] == [[1, 1], [3, 3], [5, 5], [7, 7]] and loss.ranges[4] == [9, 77]
    assert "34 gaps past the first 5 ranges merged" in loss.metadata("u")["lost_ranges_merged"]
    assert "past 5 ranges the gaps are merged into the last one" in loss.line("u")


# --- a recording through a bridge, stepped frame by frame in simulated time ----------------

class LossyRemote(RemoteBuffer):
    """The subscriber's test double: drops the inputs bodies of the frames in ``drop`` (a
    link losing them), passes everything else on."""

    drop: set[int] = set()

    def _on_body(self, sample) -> None:
        if self.drop and str(sample.key_expr).endswith("/inputs"):
            body = sample.payload.to_bytes()
            if int(np.frombuffer(body, self.layout.area("inputs").body_dtype, count=1)[0]["frame"]) in self.drop:
                return
        super()._on_body(sample)


@pytest.fixture
def stepped():
    """(rig, bridge, remote): a read-only bridge on a SimRig and a queued RemoteBuffer on
    loopback; the test steps frames (simulated time) and waits, bounded, for delivery."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rig = SimRig(prefix="pfma-test-rrec-")
    here = open_session(listen=[endpoint])
    bridge = Bridge(here, rig.name, rig.reader)
    far = open_session(connect=[endpoint])
    remote = LossyRemote(far, rig.name, queue_inputs=True)
    try:
        # the subscription reaches the bridge: frames until one body has arrived, then
        # start from an empty queue
        until(lambda: (rig.run_frames(1), bridge.poll(), remote.received("inputs") > 0)[2], "a first body")
        yield rig, bridge, remote
    finally:
        remote.close()
        bridge.close()
        far.close()
        here.close()
        rig.close()


def _frames(path) -> dict[int, bytes]:
    return {int(r["frame"]): r.tobytes() for _, _, r in read_frames(path, (RAW_TOPIC,))}


@pytest.mark.realtime
def test_a_stopped_bridge_and_dropped_samples_are_reported_with_their_frames(stepped, tmp_path):
    """Frames the bridge never saw (it was not polled: "stopped briefly") and bodies the
    subscriber dropped (a test double of the link losing them) are both named, exactly;
    every other frame equals the local recording of the same frames."""
    rig, bridge, remote = stepped
    local = Recorder(rig.reader, tmp_path / "local.mcap")
    rec = RemoteRecording(remote, Recorder(remote, tmp_path / "remote.mcap"), "zenoh://test/" + rig.name)
    rec.pump()  # what arrived before the start (the settling frames)
    start = int(rig.reader.read_inputs().frame) + 1
    pause = set(range(start + 20, start + 25))   # the bridge is not polled: never published
    drop = {start + 40, start + 41, start + 60}  # published, lost on the way in
    remote.drop = drop
    for k in range(80):
        rig.run_frames(1)
        local.poll()
        frame = start + k
        if frame in pause:
            continue
        got = remote.received("inputs")
        bridge.poll()
        if frame not in drop:
            until(lambda: remote.received("inputs") > got, f"frame {frame} across the link")
        rec.pump()
    local.close()
    c = rec.close()
    lost = sorted(pause | drop)
    assert rec.loss.frames_lost == len(lost) == c.recorder_missed
    assert rec.loss.ranges == [[start + 20, start + 24], [start + 40, start + 41], [start + 60, start + 60]]
    assert bridge.missed == len(pause)
    meta = read_metadata(tmp_path / "remote.mcap")["pfma.link"]
    assert json.loads(meta["lost_ranges"]) == rec.loss.ranges and meta["frames_lost"] == str(len(lost))
    assert read_metadata(tmp_path / "remote.mcap")["pfma.recorder.summary"]["lossless"] == "False"
    a, b = _frames(tmp_path / "local.mcap"), _frames(tmp_path / "remote.mcap")
    window = set(range(start, start + 80))
    assert set(b) & window == window - set(lost)
    assert all(a[f] == b[f] for f in b if f in a)  # byte for byte, every frame both have


# --- the CLI verbs against a bridge on a service stepped in a thread -----------------------

@pytest.fixture
def served(tmp_path):
    """A SimRig stepped in a thread (simulated frames about 2 ms apart) with its bridge and
    a local recorder polled after every frame; yields (rig, url, finish): ``finish()``
    stops the stepping and closes the local recording, returning its path."""
    port = free_port()
    rig = SimRig(prefix="pfma-test-rtools-")
    session = open_session(listen=[f"tcp/127.0.0.1:{port}"])
    bridge = Bridge(session, rig.name, rig.reader)
    local = Recorder(rig.reader, tmp_path / "local.mcap")
    stop = threading.Event()

    def run() -> None:
        while not stop.is_set():
            rig.run_frames(1)
            local.poll()
            bridge.poll()
            time.sleep(0.002)
    t = threading.Thread(target=run, daemon=True)

    def finish():
        stop.set()
        t.join(timeout=10)
        local.close()
        return tmp_path / "local.mcap"
    t.start()
    try:
        yield rig, f"zenoh://127.0.0.1:{port}/{rig.name}", finish
    finally:
        finish()
        bridge.close()
        session.close()
        rig.close()


@pytest.mark.realtime
def test_pfma_record_and_scope_through_the_bridge(served, tmp_path, capsys):
    rig, url, finish = served
    out = tmp_path / "remote.mcap"
    assert main(["record", str(out), "--buffer", url, "--duration", "1.0", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert f"link from {url}:" in text
    meta = read_metadata(out)
    link = meta["pfma.link"]
    assert link["source"] == url and meta["pfma.recording"]["source"] == url
    # lossless when the link keeps up; whatever it lost is named, and is exactly what is missing
    b = _frames(out)
    assert len(b) > 10
    lost = {f for a, z in json.loads(link["lost_ranges"]) for f in range(a, z + 1)}
    assert set(range(min(b), max(b) + 1)) - set(b) == lost
    assert ("no frame lost" in text) == (not lost) and int(link["frames_lost"]) == len(lost)
    assert main(["record", "info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["link"]["source"] == url and info["link"]["frames_lost"] == len(lost)

    # the scope sees every frame of its window (queued), from the same bridge
    cap = tmp_path / "scope.mcap"
    assert main(["scope", "frame", "elbow_pitch_angle", "--post", "0.05", "--pre", "0",
                 "-o", str(cap), "--buffer", url, "--timeout", "10"]) == 0
    capsys.readouterr()
    assert main(["scope", "--open", str(cap), "--json"]) == 0
    frames = json.loads(capsys.readouterr().out)["frames"]
    assert len(frames) >= 2 and frames == list(range(frames[0], frames[-1] + 1))

    # the local recording of the same service: equal, byte for byte, where both have the frame
    a = _frames(finish())
    both = set(a) & set(b)
    assert len(both) > 10 and all(a[f] == b[f] for f in both)


@pytest.mark.realtime
def test_watch_and_console_read_a_remote_buffer(monkeypatch, capsys):
    """``pfma watch`` and ``pfma console`` through a bridge: a late joiner asks each area
    once, so nothing here waits for frames (the simulator is stepped before)."""
    from sim.system import SystemSimulator
    import uuid
    wm = "pfma_test_rwm_" + uuid.uuid4().hex[:6]
    sim = SystemSimulator(wm_name=wm)
    port = free_port()
    session = open_session(listen=[f"tcp/127.0.0.1:{port}"])
    try:
        sim.step(10)
        bridge = Bridge(session, sim.name, sim.rig.reader)
        url = f"zenoh://127.0.0.1:{port}/{sim.name}"
        assert main(["watch", "frame", "elbow_pitch_angle", "--count", "1", "--json", "--buffer", url]) == 0
        line = json.loads(capsys.readouterr().out)
        assert line["frame"] == int(sim.rig.reader.read_inputs().frame)

        seen = {}

        class App:  # the console's app, stubbed: its sources read once through the bridge
            def __init__(self, sources, link, menu=None):
                self.sources = sources

            def run(self):
                r = self.sources.read()
                seen.update(frame=r.frame, state=r.service_state, wm=r.wm)

            def stop_recording(self):
                pass
        monkeypatch.setattr("tools.cli.console._app", lambda sources, link, on_tick=None, menu=None:
                            App(sources, link))
        assert main(["console", "--buffer", url, "--wm", wm]) == 0
        assert seen["frame"] == line["frame"] and seen["state"] == "SAFE" and "updown.status" in seen["wm"]
        bridge.close()
    finally:
        session.close()
        sim.close()
        WorldModel.remove_segment(wm)  # a closed model's segment stays until removed


@pytest.mark.realtime
def test_a_bridge_on_the_frame_ring_loses_no_frame_while_descheduled(tmp_path):
    """With the service's frame ring (pfma serve keeps one) the bridge publishes every frame
    in order even when it is not polled for many frames; the remote recording is lossless
    and equal to the local one."""
    from bit3.ring import FrameRing
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    rig = SimRig(prefix="pfma-test-rring-")
    lay = rig.layout
    rig.svc.ring = FrameRing.create(rig.name, lay.area("inputs").body_size, lay.hash)
    here = open_session(listen=[endpoint])
    far = open_session(connect=[endpoint])
    bridge = Bridge(here, rig.name, rig.reader, ring=FrameRing.attach(rig.name, lay.hash))
    remote = RemoteBuffer(far, rig.name, queue_inputs=True)
    try:
        until(lambda: (rig.run_frames(1), bridge.poll(), remote.received("inputs") > 0)[2], "a first body")
        local = Recorder(rig.reader, tmp_path / "local.mcap")
        rec = RemoteRecording(remote, Recorder(remote, tmp_path / "remote.mcap"), "zenoh://test/" + rig.name)
        rec.pump()
        for k in range(60):
            rig.run_frames(1)
            local.poll()
            if 10 <= k < 40:  # descheduled for 30 frames (about 94 ms at 320 Hz)
                continue
            got, sent = remote.received("inputs"), bridge.published["inputs"]
            bridge.poll()
            n = bridge.published["inputs"] - sent
            assert n == (31 if k == 40 else 1)  # a descheduled bridge catches up from the ring
            until(lambda: remote.received("inputs") >= got + n, "the frames across the link")
            rec.pump()
        local.close()
        c = rec.close()
        assert bridge.missed == 0 and rec.loss.frames_lost == 0 and c.recorder_missed == 0
        a, b = _frames(tmp_path / "local.mcap"), _frames(tmp_path / "remote.mcap")
        assert set(a) <= set(b) and all(a[f] == b[f] for f in a)
        assert sorted(b) == list(range(min(b), max(b) + 1))
    finally:
        remote.close()
        bridge.ring.close()
        bridge.close()
        far.close()
        here.close()
        ring = rig.svc.ring
        rig.close()  # the service's stop writes its last frame into the ring
        ring.close()
        FrameRing.unlink(rig.name)
