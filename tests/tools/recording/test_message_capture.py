"""The message queues are read by the capture thread, not after the writer's backlog.

The service's queue keeps its last 50 entries (IRSS report: "up to 50 messages per
processor"), the controller's 127; a power-up posts ~130 controller entries in half a
second and a trip ~40 in one frame (simulated time). CI's soak lost 7 entries when the recorder's writing thread, behind on frames after
a host stall, looked at the queues too late. The capture thread now copies a queue's body
whenever its head moved (``MessagesCopy``) and the writer decodes the copies in order."""

import json

from mcap.reader import make_reader

from bit3.client import Client
from bit3.ring import FrameRing
from sim.rig import SimRig
from tools.recording import InputsCapture, Recorder


def _recorded_texts(path) -> list[str]:
    with open(path, "rb") as f:
        return [json.loads(m.data)["text"] for _, _, m in make_reader(f).iter_messages(topics=["/pfma/messages"])]


def _burst(ctl, start: int, n: int) -> None:
    for i in range(start, start + n):
        ctl.post_message(f"m{i}")


def _rig_with_ring():
    rig = SimRig(prefix="pfma-test-", ring=True)
    rig.run(0.05)
    return rig


def test_copies_taken_between_bursts_keep_every_entry_though_the_writer_drains_late(tmp_path):
    rig = _rig_with_ring()
    try:
        ctl = rig.controller()
        client = Client.attach(rig.name, layout=rig.layout, clock_now=rig.clock.now)
        cap = InputsCapture(client, ring=FrameRing.attach(rig.name, rig.layout.hash), messages=True)
        rec = Recorder(client, tmp_path / "r.mcap")
        rec.messages_captured = True
        assert cap.take_messages(force=True) == 2  # the queues as they are: history, not recorded
        for b in range(3):  # 300 entries, 100 between two looks of the capture thread
            _burst(ctl, 100 * b, 100)
            rig.run_frames(8)
            cap.take_from_ring()
            assert cap.take_messages(force=True) == 1  # only the controller queue moved
        cap.drain(rec)  # the writer, late: 173 of the 300 were overwritten in the queue by now
        rec.poll(inputs=False)  # reads no queue itself while the capture does
        c = rec.close()
        assert c.messages_missed == 0 and not rec.notes
        assert [t for t in _recorded_texts(tmp_path / "r.mcap") if t.startswith("m")] == \
            [f"m{i}" for i in range(300)]
        cap.stop()
        client.close()
    finally:
        rig.close()


def test_a_recorder_that_looks_after_the_queue_wrapped_counts_and_says_the_lost_entries(tmp_path):
    """The same bursts read by the writing thread itself, once at the end: 173 of the 300
    entries were overwritten (the controller's queue holds 127); counted, said as it happens, and the recording not lossless."""
    rig = _rig_with_ring()
    try:
        ctl = rig.controller()
        client = Client.attach(rig.name, layout=rig.layout, clock_now=rig.clock.now)
        rec = Recorder(client, tmp_path / "r.mcap")
        _burst(ctl, 0, 300)
        rec.poll(inputs=False)
        assert rec.counters.messages_missed == 173
        assert rec.notes == ["173 controller message entries (1..173) were overwritten before the recorder "
                             "read them (the queue holds 127); the recording is not lossless"]
        assert not rec.close().lossless
        assert [t for t in _recorded_texts(tmp_path / "r.mcap") if t.startswith("m")] == \
            [f"m{i}" for i in range(173, 300)]
        client.close()
    finally:
        rig.close()


def test_at_a_ring_switch_the_old_queues_are_copied_last_and_none_until_the_new_client_is_named(tmp_path):
    """The service restarts (a new ring file): the capture copies the old buffer's queues
    once more before the switch, then none (the recorder closes the old client) until
    ``messages_from`` names the new service's client."""
    rig = _rig_with_ring()
    try:
        ctl = rig.controller()
        body, h = rig.layout.area("inputs").body_size, rig.layout.hash
        client = Client.attach(rig.name, layout=rig.layout, clock_now=rig.clock.now)
        cap = InputsCapture(client, ring=FrameRing.attach(rig.name, h), messages=True)
        rec = Recorder(client, tmp_path / "r.mcap")
        rec.messages_captured = True
        cap.take_messages(force=True)
        _burst(ctl, 0, 3)
        old = rig.svc.ring
        rig.svc.ring = rig.ring = FrameRing.create(rig.name, body, h)
        old.close()
        assert cap.check_ring()
        _burst(ctl, 3, 2)
        assert cap.take_messages(force=True) == 0  # paused: no client named yet
        cap.drain(rec)  # up to the switch: the old buffer's 3 messages
        rec.attach(client)  # what `pfma record` does at the note (the new service's client)
        cap.messages_from(client)
        _burst(ctl, 5, 1)
        assert cap.take_messages(force=True) == 2  # heads forgotten: both queues copied again
        cap.replaced_note = None
        cap.drain(rec)
        rec.close()
        assert [t for t in _recorded_texts(tmp_path / "r.mcap") if t.startswith("m")] == ["m0", "m1", "m2", "m5"]
        cap.stop()
        client.close()
    finally:
        rig.close()
