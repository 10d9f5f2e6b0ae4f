import os
import struct

import numpy as np
import pytest

from bit3.client import Client
from bit3.layout import MAGIC, ServiceState, Severity, build_layout, default_layout
from bit3.buffer import (
    Bit3Buffer, Bit3Error, LayoutMismatchError, OwnershipError, SeqLockTimeout,
)
from pfma.errors import ConfigError
from pfma.rack import DEFAULT_RACK, parse_rack


def test_create_publish_and_read_back(buf, shm_name):
    lay = default_layout()
    assert buf.header().magic == MAGIC and buf.header().layout_hash == lay.hash
    assert buf.claim("service", "svc") == []
    w = buf.writer("inputs")
    w.record["frame"] = 12
    w.record["rtd_angle_rad"][lay.slot("rtd", "shoulder_pitch_angle")] = 0.75
    w.record["adc_value"][3] = -1.25
    w.record["ft_force_n"] = [1.0, 2.0, 3.0]
    w.record["hc_axes"][lay.slot("hc", "crl")] = [0.1, 0, 0, 0, 0, -0.1]
    s1 = w.publish()
    buf.set_frame(12, 0.0375)
    buf.set_service_state(ServiceState.SAFE)
    with Client.attach(shm_name) as c:
        snap = c.read_inputs()
        assert snap.seq == s1 and s1 % 2 == 0
        assert snap.frame == 12 and snap.shoulder_pitch_angle == 0.75
        assert snap.elbow_pitch_motor_current == -1.25
        assert snap.value("elbow_pitch_motor_current") == snap.adc_value[3]
        assert list(snap.ft_force_n) == [1.0, 2.0, 3.0]
        assert snap.channel("crl")["hc_axes"][5] == pytest.approx(-0.1)
        assert snap.channel("shoulder_pitch_angle")["rtd_angle_rad"] == 0.75
        with pytest.raises(AttributeError, match="no field or channel"):
            snap.no_such_thing
        h = c.header()
        assert h.frame == 12 and h.frame_t_s == 0.0375 and h.service_state is ServiceState.SAFE
        owners = c.owners()
        assert owners["inputs"].name == "svc" and owners["inputs"].pid == os.getpid()
        assert owners["inputs"].heartbeat == 1 and owners["commands"].pid == 0
        assert not c.changed("inputs")
        w.publish()
        assert c.changed("inputs")


def test_record_bytes_land_at_the_documented_offsets(buf):
    lay = default_layout()
    buf.claim("service", "svc")
    w = buf.writer("inputs")
    w.record["adc_value"][5] = 42.5
    w.publish()
    off = lay.channel("wrist_yaw_motor_current").fields[2][2]  # adc_value element
    assert struct.unpack_from("<d", buf._mv, off)[0] == 42.5
    seq_off = lay.area("inputs").offset
    assert struct.unpack_from("<Q", buf._mv, seq_off)[0] == 2


def test_wrong_layout_hash_is_refused(shm_name):
    other = build_layout(parse_rack(DEFAULT_RACK.read_text().replace(
        '"wrist_roll_angle"', '"wrist_roll_angle_x"'), "other.toml"))
    b = Bit3Buffer.create(shm_name, other)
    try:
        with pytest.raises(LayoutMismatchError, match=f"layout hash {other.hash_hex}.*"
                                                      f"{default_layout().hash_hex}"):
            Client.attach(shm_name)
        assert Bit3Buffer.attach(shm_name, layout=other).header().layout_hash == other.hash
    finally:
        b.close()


def test_missing_buffer_and_duplicate_create_are_clear(shm_name, buf):
    with pytest.raises(Bit3Error, match="no Bit3 buffer 'pfma_nope_x'"):
        Bit3Buffer.attach("pfma_nope_x")
    with pytest.raises(Bit3Error, match="already exists"):
        Bit3Buffer.create(shm_name)
    again = Bit3Buffer.create(shm_name, exist_ok=True)  # a restarting service re-attaches
    assert not again.readonly
    again.close()


def test_file_window_wrong_magic_version_and_size(tmp_path):
    p = tmp_path / "zero.bin"
    p.write_bytes(bytes(32768))
    with pytest.raises(LayoutMismatchError, match="magic"):
        Bit3Buffer.from_file(p)
    small = tmp_path / "small.bin"
    small.write_bytes(bytes(1000))
    with pytest.raises(LayoutMismatchError, match="size 1000 bytes, expected 32768"):
        Bit3Buffer.from_file(small)
    good = tmp_path / "win.bin"
    Bit3Buffer.from_file(good, create=True).close()
    data = bytearray(good.read_bytes())
    struct.pack_into("<I", data, 8, 99)
    good.write_bytes(bytes(data))
    with pytest.raises(LayoutMismatchError, match="layout version 99"):
        Bit3Buffer.from_file(good)


def test_file_window_round_trip(tmp_path):
    p = tmp_path / "dpram.bin"
    w = Bit3Buffer.from_file(p, create=True)
    w.claim("controller", "ctl")
    c = Client(w, "controller", "ctl")
    c.write_commands(matrix_route=0x0102, mode=3)
    ro = Client.attach(path=p)
    snap = ro.read_commands()
    assert snap.matrix_route == 0x0102 and snap.mode == 3 and snap.heartbeat == 1
    assert ro.owners()["commands"].name == "ctl"
    ro.close()
    w.close()


def test_second_live_writer_is_refused_naming_the_owner(buf, shm_name):
    first = Client.attach(shm_name, writer="commands", owner="ctl-A")
    try:
        with pytest.raises(OwnershipError, match=f"owned by 'ctl-A' \\(pid {os.getpid()}\\).*'ctl-B'"):
            Client.attach(shm_name, writer="controller", owner="ctl-B")
        with pytest.raises(OwnershipError, match="already claimed by this attachment"):
            first.buffer.claim("commands", "again")
    finally:
        first.close()
    # released cleanly: the next writer gets it and nothing was "taken over"
    second = Client.attach(shm_name, writer="commands", owner="ctl-B")
    assert second.owners()["commands"].name == "ctl-B"
    assert second.owners()["commands"].takeovers == 0
    second.close()


def test_a_failed_role_claim_keeps_nothing(buf, shm_name):
    other = Bit3Buffer.attach(shm_name, readonly=False)
    other.claim("service", "svc")
    # steal only the service queue lock, then try the whole role from another attachment
    other.release()
    q = Bit3Buffer.attach(shm_name, readonly=False)
    from bit3.buffer import _lock_byte
    _lock_byte(q._fd, default_layout().area("service_messages").index, True)
    with pytest.raises(OwnershipError, match="service_messages"):
        buf.claim("service", "svc2")
    assert buf.claimed == ()
    q.close()
    assert buf.claim("service", "svc2") == []  # "svc" had released: nothing taken over
    assert buf.claimed == ("inputs", "stats", "service_messages")
    other.close()


def test_read_only_clients_cannot_write(buf, shm_name):
    with Client.attach(shm_name) as c:
        with pytest.raises(Bit3Error, match="does not own the command area"):
            c.write_commands(arm_request=1)
        with pytest.raises(Bit3Error, match="read-only"):
            c.buffer.claim("commands", "x")
        with pytest.raises(Bit3Error, match="cannot post"):
            c.post_message("x")
        with pytest.raises(TypeError):
            c.buffer.lock("inputs").write(memoryview(bytearray(12224)))


def test_write_commands_validates_and_is_all_or_nothing(buf, shm_name):
    with Client.attach(shm_name, writer="commands", owner="ctl") as c:
        assert c.write_commands(wrist_roll_command=0.5) == 1
        with pytest.raises(Bit3Error, match="not finite"):
            c.write_commands(arm_request=1, gripper=float("inf"))
        with pytest.raises(Bit3Error, match="no command field or DAC command channel 'bogus'"):
            c.write_commands(bogus=1)
        with pytest.raises(Bit3Error, match="set by write_commands itself"):
            c.write_commands(heartbeat=5)
        with pytest.raises(Bit3Error, match="joint_rate_rad_s"):
            c.write_commands(joint_rate_rad_s=[1, 2, 3])
        snap = c.read_commands()
        assert snap.heartbeat == 1 and snap.arm_request == 0  # refused writes left no trace
        assert snap.joint_rate_rad_s[5] == 0.5
        t_before = snap.t_s
        assert c.write_commands() == 2 and c.read_commands().t_s >= t_before


def test_message_queue_wraps_at_50(buf, shm_name):
    buf.claim("service", "svc")
    q = buf.queue("service_messages")
    for i in range(1, 121):
        assert q.post(f"message {i}", Severity.WARNING if i % 2 else Severity.INFO, code=i,
                      source=2, t_s=float(i)) == i
    with Client.attach(shm_name) as c:
        got = c.messages()
        assert [m.seq for m in got] == list(range(71, 121))
        assert got[0].text == "message 71" and got[0].code == 71 and got[0].t_s == 71.0
        assert got[-1].severity is Severity.INFO and got[-1].source == 2
        assert [m.seq for m in c.messages(since_seq=110)] == list(range(111, 121))
        assert c.messages(since_seq=120) == []
        assert len(c.new_messages()) == 50 and c.new_messages() == []
        q.post("x" * 200)
        (m,) = c.new_messages()
        # whole: four 56-byte entries (tests/bit3/test_long_messages.py)
        assert (m.first_seq, m.seq) == (121, 124) and m.text == "x" * 200


def test_stuck_writer_gives_a_bounded_error_not_a_hang(buf, shm_name):
    buf.claim("service", "svc")
    buf.lock("inputs").begin()  # odd: a write "in progress" forever
    c = Client.attach(shm_name, timeout_s=0.02)
    with pytest.raises(SeqLockTimeout, match=f"inputs.*odd.*'svc' \\(pid {os.getpid()}\\)"):
        c.read_inputs()
    buf.lock("inputs").end()
    assert c.read_inputs().seq == 2
    c.close()


def test_header_writes_need_the_inputs_claim(buf):
    with pytest.raises(OwnershipError, match="does not own area 'inputs'"):
        buf.set_service_state(ServiceState.ARMED)
    buf.claim("inputs", "svc")
    buf.set_calibration_hash(bytes(range(8)))
    assert buf.header().calibration_hash == bytes(range(8))


def test_unknown_writer_role_is_refused(shm_name, buf):
    with pytest.raises(ConfigError, match="unknown Bit3 writer 'stats-tool'"):
        Client.attach(shm_name, writer="stats-tool", owner="x")
    with pytest.raises(Bit3Error, match="needs an owner name"):
        Client.attach(shm_name, writer="commands")


def test_snapshot_copy_is_independent(buf, shm_name):
    buf.claim("service", "svc")
    w = buf.writer("inputs")
    w.record["frame"] = 1
    w.publish()
    with Client.attach(shm_name) as c:
        kept = c.read_inputs().copy()
        w.record["frame"] = 2
        w.publish()
        assert c.read_inputs().frame == 2 and kept.frame == 1
        assert np.shares_memory(c.read_inputs().record, c.read_inputs().record)


# --- non-blocking reads: a stuck-odd counter costs one bounded attempt, never a wait


def _no_clock_no_yield(monkeypatch):
    """try_read must neither look at a clock nor yield the CPU (it is called every frame)."""
    import bit3.buffer as shm

    def boom(*_a):
        raise AssertionError("try_read waited (clock or sched_yield)")
    monkeypatch.setattr(shm.time, "perf_counter", boom)
    monkeypatch.setattr(shm.time, "monotonic", boom)
    monkeypatch.setattr(shm.os, "sched_yield", boom)


def test_try_read_of_a_stuck_odd_counter_fails_at_once_and_keeps_the_record(buf, shm_name, monkeypatch):
    from bit3.buffer import TRY_READ_ATTEMPTS
    buf.claim("controller", "ctl")
    w = buf.writer("commands")
    w.record["arm_request"] = 1
    w.publish()
    with Client.attach(shm_name) as c:
        r = c.buffer.reader("commands")
        assert r.try_read() and r.last_seq == 2 and int(r.record["arm_request"]) == 1
        # the controller is killed mid-write: counter odd forever, body half written
        seq_off = buf.layout.area("commands").offset
        struct.pack_into("<Q", buf._mv, seq_off, 3)
        w.record["arm_request"] = 7
        buf.lock("commands")._body[:] = memoryview(w.raw)
        _no_clock_no_yield(monkeypatch)
        retries0 = r.retries
        for i in range(1, 4):
            assert r.try_read() is False
            assert r.try_failures == i
        assert int(r.record["arm_request"]) == 1 and r.last_seq == 2  # the last good copy
        assert r.retries - retries0 == 3 * TRY_READ_ATTEMPTS  # bounded: a few copies per call
        monkeypatch.undo()
        with pytest.raises(SeqLockTimeout):  # the blocking read still reports it, after its wait
            c.buffer.lock("commands").timeout_s = 0.001
            r.read()
        struct.pack_into("<Q", buf._mv, seq_off, 4)  # a new owner makes it even again
        assert r.try_read() and r.last_seq == 4 and int(r.record["arm_request"]) == 7
        assert r.try_failures == 3


class _MovingCounter:
    """Stands in for a sequence counter that a writer bumps during every copy (each load
    sees the next even value), for ``changes`` copies; then it stays put."""

    def __init__(self, start: int, changes: int) -> None:
        self.value, self.changes, self.loads = start, changes, 0

    def __getitem__(self, i: int) -> int:
        self.loads += 1
        v = self.value
        if self.changes and self.loads % 2 == 1:  # the load before a copy: a write follows
            self.value += 2
            self.changes -= 1
        return v


def test_try_read_refuses_a_copy_during_which_the_counter_changed(buf, shm_name, monkeypatch):
    from bit3.buffer import TRY_READ_ATTEMPTS
    buf.claim("service", "svc")
    w = buf.writer("inputs")
    w.record["frame"] = 1
    w.publish()
    r = buf.reader("inputs")
    assert r.try_read() and int(r.record["frame"]) == 1
    w.record["frame"] = 2
    w.publish()  # the body now holds frame 2; every copy of it is "torn" by the fake counter
    lock = buf.lock("inputs")
    real = lock._seq
    try:
        lock._seq = moving = _MovingCounter(4, changes=TRY_READ_ATTEMPTS)
        _no_clock_no_yield(monkeypatch)
        assert r.try_read() is False and r.try_failures == 1
        assert moving.loads == 2 * TRY_READ_ATTEMPTS
        assert int(r.record["frame"]) == 1 and r.last_seq == 2  # nothing of the torn copies
        lock._seq = moving = _MovingCounter(8, changes=1)  # torn once, then stable
        assert r.try_read() is True and int(r.record["frame"]) == 2 and r.last_seq == 10
        assert moving.loads == 4 and r.try_failures == 1
    finally:
        lock._seq = real


@pytest.mark.realtime
def test_try_read_after_a_controller_died_mid_write(shm_name, mp):
    from tests.bit3 import _workers
    buf = Bit3Buffer.create(shm_name)
    try:
        child = mp.Process(target=_workers.die_holding_claim, args=(shm_name, True))
        child.start()
        child.join(30)
        assert child.exitcode == 0
        r = buf.reader("commands")
        assert buf.lock("commands").seq % 2 == 1
        assert r.try_read() is False and r.try_failures == 1 and r.last_seq == -1
    finally:
        buf.close()


# --- owner pid and claim token, for a per-frame check


def test_owner_pid_token_follows_claims_and_releases(buf, shm_name):
    assert buf.owner_pid_token("commands") == (0, 0)
    views = len(buf._views)
    buf.claim("controller", "ctl")
    pid, tok = buf.owner_pid_token("commands")
    o = buf.owner("commands")
    assert pid == os.getpid() == o.pid and tok == o.claimed_ns > 0
    assert buf.owner_pid_token("controller_messages")[0] == os.getpid()
    assert buf.owner_pid_token("inputs") == (0, 0)
    for _ in range(100):
        assert buf.owner_pid_token("commands") == (pid, tok)
    assert len(buf._views) - views <= 2 * 3  # cached per area on first use, not per call
    buf.release()
    pid2, tok2 = buf.owner_pid_token("commands")
    assert pid2 == 0 and tok2 > tok
    with Client.attach(shm_name, writer="commands", owner="ctl2") as c:
        pid3, tok3 = buf.owner_pid_token("commands")
        assert pid3 == os.getpid() and tok3 > tok2  # a new claim: a new token, even in one process
        assert c.buffer.owner_pid_token("commands") == (pid3, tok3)
    with pytest.raises(Bit3Error, match="no owner"):
        buf.owner_pid_token("header")


def test_owner_pid_token_of_a_record_being_written_reads_as_nobody(buf):
    buf.claim("controller", "ctl")
    base = buf._owner_offset(buf.layout.area("commands").index, "seq")
    s = struct.unpack_from("<Q", buf._mv, base)[0]
    struct.pack_into("<Q", buf._mv, base, s + 1)  # a claimer killed inside _write_owner
    assert buf.owner_pid_token("commands") == (0, 0)
    struct.pack_into("<Q", buf._mv, base, s + 2)
    assert buf.owner_pid_token("commands")[0] == os.getpid()
