"""Recorder, recover, scope and replay on the simulated-time rig (tests/ioservice/conftest.py).

Recordings are read back independently with ``mcap.reader.make_reader`` and decoded from
the schema stored in the file, not with the recorder's own state.
"""

from __future__ import annotations

import io
import json
import math
import os
import random
import select
import signal
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from tools.recording import RAW_TOPIC, Recorder, decode_raw, recover
from bit3.buffer import Bit3Buffer
from tools.replay import replay_through_fakes, republish
from tools.scope import ScopeCapture, load, render, save, save_png
from sim.rig import SimRig as Rig

REPO = Path(__file__).resolve().parents[3]
OFFSET_NS = 1_700_000_000_000_000_000


@pytest.fixture
def rig():
    r = Rig(name="pfma-rec-" + uuid.uuid4().hex[:8])
    yield r
    r.close()


class _Wall:
    """A wall clock the test moves: one tick per poll."""

    def __init__(self, step_s: float) -> None:
        self.t, self.step = 0.0, step_s

    def __call__(self) -> float:
        self.t += self.step
        return self.t


def _record(rig: Rig, path, seconds: float, every: int = 1, keep: list | None = None, **kw) -> Recorder:
    """Record while the rig runs; the recorder polls before every ``every``-th frame.
    ``keep`` collects a copy of what the service published in each frame."""
    rec = Recorder(rig.reader, path, rack=rig.world.rack_config, epoch_offset_ns=OFFSET_NS, **kw)

    def hook(info):
        if keep is not None and rig.svc.loop_stats.n:
            keep.append(rig.svc.inputs.record.copy())
        if info.index % every == 0:
            rec.poll()
    rig.on_frame.append(hook)
    rig.run(seconds)
    if keep is not None:
        keep.append(rig.svc.inputs.record.copy())
    rig.on_frame.remove(hook)
    return rec


def _read(path) -> tuple[dict, list]:
    """(per-topic counts from the summary, [(topic, log_time, decoded)]) via make_reader."""
    with open(path, "rb") as f:
        r = make_reader(f)
        s = r.get_summary()
        counts = {s.channels[c].topic: n for c, n in s.statistics.channel_message_counts.items()}
        out = []
        for schema, ch, m in r.iter_messages(log_time_order=False):
            if ch.message_encoding == "pfma-bit3-v1":
                out.append((ch.topic, m.log_time, decode_raw(schema.data, m.data)))
            else:
                out.append((ch.topic, m.log_time, json.loads(m.data)))
        return counts, out


def test_every_frame_recorded_and_read_back_independently(rig, tmp_path):
    published: list[np.ndarray] = []
    path = tmp_path / "rec.mcap"
    rec = _record(rig, path, 1.0, keep=published)
    cnt = rec.close()
    n = rig.svc.loop_stats.n
    assert n == 320 and len(published) == n
    counts, msgs = _read(path)
    raw = [(t, v) for topic, t, v in msgs if topic == RAW_TOPIC]
    assert counts[RAW_TOPIC] == len(raw) == n
    # zero drops by the recorder's own counters, and the window matches the service's count
    assert cnt.frames_recorded == n and cnt.recorder_missed == 0 and cnt.frame_gaps == 0
    assert cnt.window_service_frames > 0 and cnt.window_recorded == cnt.window_service_frames
    assert cnt.lossless
    # values equal the buffer's, byte for byte (the stored part of the body)
    by_frame = {int(v["frame"]): v for _, v in raw}
    for p in published:
        got = by_frame[int(p["frame"])]
        for name in p.dtype.names:
            assert np.array_equal(got[name], p[name]), name
    # log_time = offset + service time
    for t, v in raw:
        assert t == OFFSET_NS + int(round(float(v["t_s"]) * 1e9))
    # JSON channels at native rates, with engineering values equal to the buffer's
    assert counts["/pfma/status"] == n
    assert counts["/pfma/joints"] == n // 2 and counts["/pfma/adc"] == n // 2
    assert counts["/pfma/ft"] > 0 and counts["/pfma/pio"] == n // 8
    joints = [v for topic, _, v in msgs if topic == "/pfma/joints"]
    lay = rig.reader.layout
    slot = lay.channel("elbow_pitch_angle").slot
    j = joints[-1]
    assert j["elbow_pitch_angle"]["angle_rad"] == float(by_frame[j["frame"]]["rtd_angle_rad"][slot])
    # the summary record and the context metadata are in the file
    with open(path, "rb") as f:
        r = make_reader(f)
        meta = {m.name: m.metadata for m in r.iter_metadata()}
        atts = {a.name: a for a in r.iter_attachments()}
    assert meta["pfma.layout"]["hash"] == lay.hash_hex
    assert meta["pfma.recorder.summary"]["lossless"] == "True"
    assert meta["pfma.recorder.summary"]["recorder_missed"] == "0"
    assert "calibration" in "".join(meta)
    assert json.loads(atts["bit3-layout.json"].data)["hash"] == lay.hash_hex
    assert any(c["signal"] == "elbow_pitch_angle" for c in json.loads(atts["rack-channels.json"].data))


def test_missed_publishes_are_counted(rig):
    rec = _record(rig, io.BytesIO(), 1.2, every=2)  # the recorder looks only every other frame
    cnt = rec.close()
    assert cnt.frames_recorded == 192
    assert cnt.recorder_missed == 191 and cnt.frame_gaps == 191 and cnt.service_skipped == 0
    assert cnt.window_service_frames == 160 and cnt.window_recorded == 80
    assert not cnt.lossless


def test_service_skipped_frames_are_not_recorder_losses(rig):
    period = rig.svc.schedule.period_s

    def stall(info):
        if info.index == 100:
            rig.clock.advance(3.5 * period)  # the service wakes late: it drops two frames
    rig.on_frame.append(stall)
    rec = _record(rig, io.BytesIO(), 1.0)
    cnt = rec.close()
    assert rig.svc.loop_stats.dropped == 2
    assert cnt.service_skipped == 2 and cnt.frame_gaps == 2 and cnt.recorder_missed == 0
    assert cnt.window_service_dropped == 2 and cnt.window_recorded == cnt.window_service_frames
    assert cnt.lossless


def test_truncated_file_is_made_whole(rig, tmp_path):
    path = tmp_path / "full.mcap"
    rec = _record(rig, path, 1.0, wall=_Wall(0.01), flush_every_s=0.1)  # a chunk every 10 polls
    rec.close()
    total = _read(path)[0][RAW_TOPIC]
    data = path.read_bytes()
    rng = random.Random(8)
    last = -1
    for cut in sorted(rng.randrange(200, len(data) - 1) for _ in range(6)):
        broken = tmp_path / f"cut{cut}.mcap"
        broken.write_bytes(data[:cut])
        with pytest.raises(Exception):
            with open(broken, "rb") as f:
                make_reader(f).get_summary().statistics  # noqa: B018 - unreadable as it is
        rep = recover(broken, tmp_path / f"fixed{cut}.mcap")
        assert not rep.had_footer and rep.stopped_by
        counts = _read(rep.output)[0]
        raw = counts.get(RAW_TOPIC, 0)
        assert raw == rep.frames and rep.frame_gaps == 0
        assert last <= raw <= total
        last = raw
    assert last > 0


_CHILD = r"""
import sys, time, uuid
sys.path.insert(0, sys.argv[2])
from sim.rig import SimRig as Rig
from tools.recording.writer import Recorder
rig = Rig(name="pfma-kill-" + uuid.uuid4().hex[:8])
rec = Recorder(rig.reader, sys.argv[1], rack=rig.world.rack_config, flush_every_s=1e9)
n = [0]
def hook(info):
    rec.poll()
    n[0] += 1
    if n[0] % 64 == 0:
        rec.flush()
        print(rec.counters.frames_recorded, flush=True)
rig.on_frame.append(hook)
rig.run(3600)
"""


@pytest.mark.realtime
def test_recorder_killed_with_sigkill_is_recovered(tmp_path):
    path = tmp_path / "killed.mcap"
    p = subprocess.Popen([sys.executable, "-c", _CHILD, str(path), str(REPO)], cwd=REPO,
                         stdout=subprocess.PIPE, text=True)
    flushed = 0
    try:
        while flushed < 300:
            ready, _, _ = select.select([p.stdout], [], [], 30)
            assert ready, "recorder child printed nothing within 30 s"
            line = p.stdout.readline()
            assert line, "recorder child ended early"
            flushed = int(line)
        os.kill(p.pid, signal.SIGKILL)
    finally:
        p.kill()
        p.wait(10)
        p.stdout.close()
    rep = recover(path, tmp_path / "fixed.mcap")
    assert rep.frames >= flushed and rep.frame_gaps == 0
    counts = _read(rep.output)[0]
    assert counts[RAW_TOPIC] == rep.frames
    for name in os.listdir("/dev/shm"):  # the child's buffer (killed, never unlinked)
        if name.startswith("pfma-kill-"):
            Bit3Buffer.unlink(name)


def test_scope_trigger_and_pre_trigger_on_a_step(rig, tmp_path):
    period = rig.svc.schedule.period_s
    step_frame = 200

    def step(info):
        if info.index == step_frame:
            rig.world.sim.hold_adc_volts("adc_spare_25", 2.5)
    rig.on_frame.append(step)
    sc = ScopeCapture(rig.reader.layout, ["adc_spare_25", "frame"], "adc_spare_25>1.0",
                      pre_s=0.05, post_s=0.1)

    def feed(info):
        if rig.reader.changed("inputs"):
            sc.feed(rig.reader.read_inputs().record)
    rig.on_frame.append(feed)
    rig.run(1.0)
    assert sc.done
    cap = sc.capture
    ti = cap.trigger_index
    # the ADC is scanned in frames of one phase; the first scan after the step triggers
    assert step_frame <= cap.trigger_frame <= step_frame + 2
    assert cap.values[ti][0] == pytest.approx(2.5, abs=0.01)
    assert all(v[0] == pytest.approx(0.0, abs=0.01) for v in cap.values[:ti])
    assert ti == pytest.approx(0.05 / period, abs=1)          # pre-trigger frames
    assert len(cap.t_s) - ti - 1 == pytest.approx(0.1 / period, abs=1)
    assert np.all(np.diff(cap.frames) == 1)                  # native rate, no gaps
    out = tmp_path / "cap.mcap"
    assert save(cap, out, epoch_offset_ns=OFFSET_NS) == len(cap.t_s)
    back = load(out)
    assert back.frames == cap.frames and back.trigger_frame == cap.trigger_frame
    assert back.values == cap.values
    text = render(back)
    assert "adc_spare_25 [V]" in text and "t - trigger (ms)" in text  # the terminal plot's title and axis
    assert "\x1b[" not in text  # no colour codes in a log
    png = save_png(back, tmp_path / "cap.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 2000


def test_replay_round_trip_is_byte_identical(rig, tmp_path):
    first = tmp_path / "a.mcap"
    _record(rig, first, 0.5).close()
    name = "pfma-rep-" + uuid.uuid4().hex[:8]
    buf = Bit3Buffer.create(name, rig.reader.layout)
    from bit3.client import Client
    reader = Client.attach(name)
    try:
        second = tmp_path / "b.mcap"
        rec = Recorder(reader, second, epoch_offset_ns=OFFSET_NS)
        # the replay's pacing sleep is where the recorder polls: one poll between publishes
        n = republish(str(first), buf, sleep=lambda dt: rec.poll(), now=lambda: 0.0)
        cnt = rec.close()
    finally:
        reader.close()
        buf.close()
        Bit3Buffer.unlink(name)
    assert n == 160 and cnt.frames_recorded == 160 and cnt.recorder_missed == 0
    a = [v.tobytes() for t, _, v in _read(first)[1] if t == RAW_TOPIC]
    b = [v.tobytes() for t, _, v in _read(second)[1] if t == RAW_TOPIC]
    assert a == b


def test_replay_through_the_fakes_matches_the_recording(rig, tmp_path):
    def wiggle(info):  # CAE axes move: ADC channels that change every scan
        x = math.sin(info.index / 20.0)
        rig.world.set_cae([x, -x, 0.5 * x, 0.0, 0.2, -0.2])
    rig.on_frame.append(wiggle)
    path = tmp_path / "rec.mcap"
    _record(rig, path, 0.5).close()
    rep = replay_through_fakes(str(path), rack=rig.world.rack_config)
    assert rep.frames_compared >= 150
    assert "cae_up_down.adc_counts" in rep.channels
    assert not rep.mismatches, rep.describe()


def _record_with_a_skip(rig: Rig, path) -> None:
    """A lossless recording in which the service skipped frames 101 and 102 (its wake-up at
    frame 100 came 3.5 periods late) and the CAE axes moving (ADC channels that change every
    scan): what ``pfma record`` makes of a host stall."""
    period = rig.svc.schedule.period_s

    def wiggle(info):
        x = math.sin(info.index / 20.0)
        rig.world.set_cae([x, -x, 0.5 * x, 0.0, 0.2, -0.2])
        if info.index == 100:
            rig.clock.advance(3.5 * period)
    rig.on_frame.append(wiggle)
    cnt = _record(rig, path, 0.5).close()
    rig.on_frame.remove(wiggle)
    assert cnt.service_skipped == 2 and cnt.recorder_missed == 0 and cnt.lossless


def test_replay_through_the_fakes_skips_the_frames_the_service_skipped(rig, tmp_path, monkeypatch, capsys):
    """Issue 32: a LOSSLESS recording with a frame the service skipped replayed with "10 with
    mismatches", all there. The replay now skips that frame too (the next one runs its tasks,
    as the service did), counts and says it, and compares the rest; ``pfma record info``
    and ``pfma replay`` agree."""
    import tools.replay as replay_mod
    from tools.cli import main
    path = tmp_path / "skip.mcap"
    _record_with_a_skip(rig, path)
    rep = replay_through_fakes(str(path), rack=rig.world.rack_config)
    assert rep.skipped_frames == [101, 102] and rep.lost_frames == []
    assert not rep.mismatches, rep.describe()
    assert rep.frames_compared == rep.frames_recorded - 8  # all but the first major frame (settling)
    assert rep.describe().splitlines()[1] == (
        "  2 frames the service skipped (101-102): not compared, and skipped here too (as the service did)")
    assert main(["replay", str(path), "--through-fakes"]) == 0
    assert "2 frames the service skipped (101-102)" in capsys.readouterr().out
    assert main(["record", "info", str(path)]) == 0
    assert "service_skipped=2" in capsys.readouterr().out

    # what the replay did before: the gap run as frames without their inputs; the frame
    # after it then differs from the recording (why the skip is reproduced, not excused)
    monkeypatch.setattr(replay_mod, "missing_frames",
                        lambda order, meta: ([], [f for f in range(order[0], order[-1]) if f not in order],
                                             "test"))
    old = replay_through_fakes(str(path), rack=rig.world.rack_config)
    assert old.lost_frames == [101, 102] and old.mismatches
    assert {d.first_frame for d in old.mismatches.values()} <= {103, 104}
    assert "2 frames missing from the recording (101-102; test)" in old.describe()


def test_replay_through_the_fakes_still_finds_a_real_mismatch_next_to_a_skip(rig, tmp_path, monkeypatch, capsys):
    import tools.replay as replay_mod
    from tools.cli import main
    path = tmp_path / "skip.mcap"
    _record_with_a_skip(rig, path)
    slot = rig.reader.layout.channel("cae_up_down").slot
    real = replay_mod.read_frames

    def tampered(p, topics):  # the recording's ADC counts at frame 140 off by 5 (its volts not)
        for topic, t_ns, rec in real(p, topics):
            if topic == RAW_TOPIC and int(rec["frame"]) == 140:
                rec = rec.copy()
                rec["adc_counts"][slot] += 5
            yield topic, t_ns, rec
    monkeypatch.setattr(replay_mod, "read_frames", tampered)
    rep = replay_through_fakes(str(path), rack=rig.world.rack_config)
    assert rep.skipped_frames == [101, 102]
    bad = rep.mismatches
    assert list(bad) == ["cae_up_down.adc_counts"]
    assert bad["cae_up_down.adc_counts"].first_frame == 140 and bad["cae_up_down.adc_counts"].mismatched == 1
    assert main(["replay", str(path), "--through-fakes"]) == 1
    out = capsys.readouterr().out
    assert "1 with mismatches" in out and "MISMATCH cae_up_down.adc_counts: 1/" in out
    assert "2 frames the service skipped (101-102)" in out


def test_missing_frames_are_attributed_from_what_the_recording_says():
    from tools.replay import missing_frames
    order = [1, 2, 5, 6, 9]
    assert missing_frames(order, {"pfma.recorder.summary": {"recorder_missed": "0", "service_skipped": "4"}}) \
        == ([3, 4, 7, 8], [], "")
    assert missing_frames(order, {"pfma.recorder.summary": {"recorder_missed": "4", "service_skipped": "0"}}) \
        == ([], [3, 4, 7, 8], "the recorder missed them")
    skipped, lost, why = missing_frames(order, {"pfma.recorder.summary": {"recorder_missed": "2",
                                                                           "service_skipped": "2"}})
    assert skipped == [] and lost == [3, 4, 7, 8] and "cannot tell" in why
    assert missing_frames(order, {})[1] == [3, 4, 7, 8]  # a recovered file: no summary
    assert missing_frames(order, {"pfma.link": {"lost_ranges": "[[7, 8]]"}}) == ([3, 4], [7, 8], "the link lost them")
    assert missing_frames([1, 2, 3], {}) == ([], [], "")


@pytest.mark.realtime
def test_record_cli_waits_with_a_message_and_gives_up(tmp_path):
    name = "pfma-none-" + uuid.uuid4().hex[:8]
    p = subprocess.run([sys.executable, "-m", "tools.cli", "record", str(tmp_path / "x.mcap"), "--buffer", name,
                        "--wait", "0.5"], cwd=REPO, capture_output=True, text=True, timeout=30)
    assert p.returncode == 1
    assert f"waiting for service on /dev/shm/{name}" in p.stderr
    assert "nothing recorded" in p.stderr
    assert not (tmp_path / "x.mcap").exists()


def test_nothing_is_stamped_before_the_service_time_the_recording_starts_at(rig, tmp_path):
    """A command area nobody has written yet (t_s = 0) used to be stamped at the service
    clock's zero (host boot time, live): a viewer's timeline then began ~2,000 s before the
    data. It is stamped at the service's newest frame when the recorder attaches."""
    rig.run(0.5)
    path = tmp_path / "late.mcap"
    rec = Recorder(rig.reader, path, rack=rig.world.rack_config, epoch_offset_ns=OFFSET_NS)
    rec.poll(inputs=False)  # as `pfma record` does: its capture thread takes the inputs
    rig.run(0.1)
    rec.poll()
    rec.close()
    _, msgs = _read(path)
    cmd = [t for topic, t, _ in msgs if topic == "/pfma/commands"]
    # at the service time the recorder attached (0.5 s), not at the clock's zero
    assert cmd and min(cmd) >= OFFSET_NS + 490_000_000
    # (messages posted before the recording started keep their own times: they are history)
