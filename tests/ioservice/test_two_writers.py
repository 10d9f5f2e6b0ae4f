"""Two writers on one claim (issue 28 item 6): a forger that copies the claim holder's pid
and token from the buffer.

Simulated time (``SimRig``): the holder writes right before each service frame, the
forger (in this process, or a real second OS process answering over a pipe) right after
it on the frames a test chooses, so every interleaving is exact and repeatable.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bit3.layout import CMD_FOREIGN, ServiceState
from ioservice.commandcheck import TWO_WRITER_HOLD_S, ClaimStreamCheck
from ioservice.service import FAULT_FOREIGN
from tests.ioservice._forger import Forger, forger_process
from tests.ioservice.test_command_path import LIMITS, armed, texts, volts

RATE = 0.3  # the forged joint-0 rate (rad/s): within its limit, so only the writer is wrong


def _forge_on(rig, forge, frames: set[int]) -> list[int]:
    """Call ``forge()`` right after the holder's write before each service frame whose
    index (counted from now) is in ``frames``; returns the list the indices are counted in."""
    seen: list[int] = []

    def hook(info) -> None:
        seen.append(info.index)
        if len(seen) - 1 in frames:
            forge()
    rig.on_frame.append(hook)
    return seen


def _two_writer_messages(rig) -> list[str]:
    return [t for t in texts(rig) if "two writers on the claim" in t]


@pytest.mark.parametrize("mode", ["own", "follow"])
def test_a_forger_copying_pid_and_token_puts_the_service_safe_and_names_it(rig, mode):
    ctl = armed(rig)  # the holder: arm request 1, zero rates, every frame
    f = Forger(rig.name, rig.layout)
    try:
        foreign0 = rig.reader.read_inputs().foreign_writes
        _forge_on(rig, lambda: f.forge(mode, RATE), set(range(0, 40, 2)))  # every other frame
        rig.run_frames(3)
        s = rig.reader.read_inputs()
        assert s.service_state == ServiceState.SAFE and s.fault_code == FAULT_FOREIGN
        assert s.command_status & CMD_FOREIGN and s.foreign_writes > foreign0
        assert np.all(volts(rig) == 0.0)
        msgs = _two_writer_messages(rig)
        assert len(msgs) == 1, texts(rig)  # one message, from the guard's refusal
        assert f"two writers on the claim of pid {ctl.client.command['writer_pid']}" in msgs[0]
        # the holder asks to re-arm while the forger still writes: refused, outputs stay 0 V
        ctl.cmd["rearm_counter"] = 1
        rig.run_frames(30)
        s = rig.reader.read_inputs()
        assert s.service_state == ServiceState.SAFE and np.all(volts(rig) == 0.0)
        assert any(t.startswith("arm refused: two writers on the claim") for t in texts(rig)), texts(rig)
    finally:
        f.close()


def test_while_safe_two_writers_are_said_once_until_the_next_arm(rig):
    ctl = armed(rig)
    ctl.cmd["arm_request"] = 0  # disarmed by the holder: SAFE, still writing
    rig.run_frames(3)
    assert rig.reader.read_inputs().service_state == ServiceState.SAFE
    f = Forger(rig.name, rig.layout)
    try:
        _forge_on(rig, lambda: f.forge("own", RATE), set(range(0, 60, 2)))
        rig.run_frames(60)
        s = rig.reader.read_inputs()
        assert s.foreign_writes >= 2 and s.command_status & CMD_FOREIGN and s.fault_code == 0
        assert len(_two_writer_messages(rig)) == 1, texts(rig)  # not once per detection
        assert np.all(volts(rig) == 0.0)
    finally:
        f.close()


def test_the_forged_rate_never_reaches_the_dac_for_more_than_one_frame(rig):
    """The issue's reproduction (+9.75 V for 4 s): the forger's rate is obeyed at most in
    the frame before its stream meets the holder's."""
    armed(rig)
    f = Forger(rig.name, rig.layout)
    driven = []
    rig.after_frame.append(lambda info: driven.append(float(volts(rig)[0]) != 0.0))
    try:
        _forge_on(rig, lambda: f.forge("own", RATE), set(range(0, 320, 3)))
        rig.run(1.0)
        assert sum(driven) <= 1 and not any(driven[3:])
        assert rig.reader.read_inputs().service_state == ServiceState.SAFE
    finally:
        f.close()


def test_after_the_forger_stops_an_explicit_re_arm_arms_again(rig):
    ctl = armed(rig)
    f = Forger(rig.name, rig.layout)
    try:
        _forge_on(rig, lambda: f.forge("own", RATE), {0, 2})
        rig.run_frames(4)
        assert rig.reader.read_inputs().service_state == ServiceState.SAFE
        rig.run(TWO_WRITER_HOLD_S + 0.1)  # the holder writes on, arm request unchanged
        assert rig.reader.read_inputs().service_state == ServiceState.SAFE  # no re-arm: stays SAFE
        ctl.cmd["rearm_counter"] = 7
        rig.run_frames(3)
        s = rig.reader.read_inputs()
        assert s.service_state == ServiceState.ARMED and s.fault_code == 0
        assert len(_two_writer_messages(rig)) == 1
    finally:
        f.close()


def test_a_controller_restart_is_a_new_claim_not_a_second_writer(rig):
    ctl = armed(rig)
    rig.run_frames(5)
    ctl.enabled = False
    rig.ctl.close()  # the controller exits; a new one claims (a new token, its own counters)
    rig.ctl = None
    armed(rig, rearm_counter=2)  # (asserts ARMED)
    assert rig.reader.read_inputs().foreign_writes == 0
    assert _two_writer_messages(rig) == []


def test_keep_alives_and_open_loop_and_halted_writers_are_one_writer(rig):
    ctl = armed(rig)
    client = ctl.client
    ctl.enabled = False

    def several(info) -> None:  # 0-3 publishes per frame: writes, keep-alives, controller_frame
        n = info.index % 4
        for i in range(n):
            if i % 2:
                client.publish_commands()
            else:
                client.write_commands(controller_frame=info.index, arm_request=1)
    rig.on_frame.append(several)
    rig.run(0.5)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.ARMED and s.foreign_writes == 0
    rig.on_frame.remove(several)
    # a Data Acquisition layer started again on the same claim writes controller_frame 0 first
    ctl.cmd["controller_frame"] = 0
    ctl.enabled = True
    rig.run(0.05)
    assert rig.reader.read_inputs().service_state == ServiceState.ARMED
    # halted: 0 rates, 0 limits, no arm request, mode HALTED
    from bit3.layout import MODE_HALTED
    ctl.cmd.update(arm_request=0, mode=MODE_HALTED, current_limit_a=[0.0] * 7)
    rig.run(0.05)
    s = rig.reader.read_inputs()
    assert s.service_state == ServiceState.HALTED and s.foreign_writes == 0
    assert _two_writer_messages(rig) == []
    assert LIMITS  # (the armed() helper's limits: the holder armed with them)


@pytest.mark.parametrize("mode", ["inplace", "follow"])
def test_a_forger_overwriting_each_holder_body_before_the_service_reads_it_is_not_detectable(rig, mode):
    """The limit, documented in docs/safety.md: a forger that overwrites every one of the
    holder's bodies before the service reads it, continuing the holder's counters (bytes
    rewritten in place, or published through the lock with the next numbers), is one
    stream to the service: obeyed."""
    armed(rig)
    f = Forger(rig.name, rig.layout)
    try:
        _forge_on(rig, lambda: f.forge(mode, RATE), set(range(10)))
        rig.run_frames(10)
        s = rig.reader.read_inputs()
        assert s.service_state == ServiceState.ARMED and s.foreign_writes == 0
        assert float(volts(rig)[0]) != 0.0  # the forged rate drives the arm
    finally:
        f.close()


def test_a_forger_writing_while_the_holder_is_silent_is_not_detectable(rig):
    """The other limit: the holder writes nothing (stopped with SIGSTOP by the same user);
    a forger continuing its counters is the only stream, and is obeyed."""
    ctl = armed(rig)
    ctl.enabled = False  # the holder is stopped
    f = Forger(rig.name, rig.layout)
    try:
        _forge_on(rig, lambda: f.forge("follow", RATE), set(range(20)))
        rig.run_frames(20)
        s = rig.reader.read_inputs()
        assert s.service_state == ServiceState.ARMED and s.foreign_writes == 0
        assert float(volts(rig)[0]) != 0.0
    finally:
        f.close()


# --- the stream check alone: a single writer is never taken for two -----------------------

@st.composite
def _one_writer_runs(draw):
    """Reads of one writer's stream: between two reads 0-5 publishes (writes or keep-alives,
    controller_frame unchanged, counting up or back to 0), now and then a new claim."""
    steps = draw(st.lists(st.tuples(st.integers(0, 5), st.sampled_from(["same", "up", "zero", "claim"])),
                          min_size=1, max_size=60))
    return steps


@settings(max_examples=200, deadline=None)
@given(_one_writer_runs())
def test_one_writer_through_its_own_counters_is_never_two(steps):
    raw = bytearray(16)
    chk = ClaimStreamCheck(raw, hold_frames=320)
    pid, token, seq, hb, cf = 100, 1, 0, 0, 0
    for n, what in steps:
        if what == "claim":  # a new claim: new token; the new writer's counters continue the area's
            token += 1
            hb = 0
        for _ in range(n):
            seq += 2
            hb += 1
            if what == "up":
                cf += 1
            elif what == "zero":
                cf = 0
            raw[:8] = hb.to_bytes(8, "little")
            raw[8:] = cf.to_bytes(8, "little")
        assert not chk.note(pid, token, seq, hb, cf), chk.reason
    assert chk.detections == 0


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.sampled_from("HF"), st.integers(1, 3)), min_size=2, max_size=30))
def test_interleaved_streams_with_own_counters_are_seen_when_both_are_read(runs):
    """Two writers, each with its own sequence counter and heartbeat whose counters do not
    line up (sequence - 2 x heartbeat: 0 for one, -4 for the other), publishing in any
    interleaving; the service reads after each run. Whenever it has read a body of each, it
    has seen a second writer. (Counters that line up are the undetectable case above.)"""
    raw = bytearray(16)
    chk = ClaimStreamCheck(raw, hold_frames=320)
    own = {"H": [1000, 500], "F": [1010, 507]}  # [seq, heartbeat] per writer
    read_from = set()
    for who, n in runs:
        s = own[who]
        s[0] += 2 * n
        s[1] += n
        raw[:8] = s[1].to_bytes(8, "little")
        raw[8:] = (1 if who == "F" else 0).to_bytes(8, "little")
        chk.note(1, 1, s[0], s[1], 0)
        read_from.add(who)
    if read_from == {"H", "F"}:
        assert chk.detections >= 1


# --- a real second OS process ---------------------------------------------------------------

@pytest.mark.realtime
def test_a_forger_in_a_second_process_is_refused_and_named(rig, mp):
    ctl = armed(rig)
    parent, child_end = mp.Pipe()
    child = mp.Process(target=forger_process, args=(rig.name, child_end))
    child.start()
    try:
        pids = []

        def forge() -> None:
            parent.send(("forge", "own", RATE))
            assert parent.poll(30.0), "forger process did not answer"
            pids.append(parent.recv()[1])
        _forge_on(rig, forge, set(range(0, 20, 2)))
        rig.run_frames(20)
        s = rig.reader.read_inputs()
        assert pids and pids[0] == child.pid and child.pid != ctl.client.command["writer_pid"]
        assert s.service_state == ServiceState.SAFE and s.fault_code == FAULT_FOREIGN
        assert s.foreign_writes >= 1 and np.all(volts(rig) == 0.0)
        assert len(_two_writer_messages(rig)) == 1, texts(rig)
        ctl.cmd["rearm_counter"] = 3  # re-arm while the second process still writes: refused
        rig.run_frames(4)
        assert rig.reader.read_inputs().service_state == ServiceState.SAFE
    finally:
        parent.send(("bye",))
        child.join(30.0)
        if child.is_alive():
            child.kill()


def test_the_arm_refusal_holds_one_second_at_any_frame_rate(rig):
    from ioservice.schedule import Schedule
    assert rig.svc._claim_check.hold_frames == round(TWO_WRITER_HOLD_S * 320)
    rig.svc.reschedule(Schedule(frame_rate_hz=160))
    assert rig.svc._claim_check.hold_frames == round(TWO_WRITER_HOLD_S * 160)
