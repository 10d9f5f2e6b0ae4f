"""The script handle (bit3/handle.py) against the simulated rack, in simulated time.

The keep-alive thread is replaced by :meth:`Rack.keepalive_step` run before every service
frame on the rig's clock (what the thread does every 5 ms, at the frame rate), and the
handle's ``sleep`` runs the rig: a script's ``rack.sleep(0.5)`` is 0.5 s of simulated time.
"""

from __future__ import annotations

import math

import pytest

from bit3.handle import RATE_EXPIRY_S, Rack, RackError
from bit3.layout import ServiceState
from pfma.arm import joint
from sim.rig import SimRig


@pytest.fixture
def rig():
    r = SimRig(prefix="pfma-hdl-")
    try:
        yield r
    finally:
        r.close()


def _handle(rig: SimRig, *, keepalive: bool = True) -> tuple[Rack, list[str]]:
    notes: list[str] = []
    period = rig.svc.schedule.period_s

    def sleep(s: float) -> None:
        rig.run_frames(max(1, round(s / period)))

    rack = Rack(rig.controller("test-script"), rack=rig.rack, now=rig.clock.now, sleep=sleep,
                keepalive=False, say=notes.append)
    if keepalive:
        rig.on_frame.append(lambda info: rack.keepalive_step())
    return rack, notes


def _commanded(rig: SimRig, name: str) -> float:
    return float(rig.reader.read_commands().joint_rate_rad_s[rig.layout.joint_names.index(name)])


def test_arm_takes_a_new_rearm_number_each_time_and_the_service_arms(rig):
    rack, _ = _handle(rig)
    before = int(rig.reader.read_commands().rearm_counter)
    rack.arm(current_limit_a=2.0)
    assert rack.state is ServiceState.ARMED and f"{rack.state}" == str(rack.state) == "ARMED"  # a name, not 2
    assert int(rig.reader.read_commands().rearm_counter) == before + 1
    rack.disarm()
    rack.sleep(0.02)
    assert rack.state is ServiceState.SAFE
    rack.arm(current_limit_a=2.0)  # a re-arm: the counter moves on, the service arms again
    assert rack.state is ServiceState.ARMED
    assert int(rig.reader.read_commands().rearm_counter) == before + 2


def test_the_keepalive_holds_the_heartbeat_through_a_sleep_and_without_it_the_service_trips(rig):
    rack, _ = _handle(rig)
    rack.arm(current_limit_a=2.0)
    rack.sleep(0.5)  # the finding: time.sleep(0.5) after arming tripped the 15 ms watchdog
    assert rack.state is ServiceState.ARMED
    rig.on_frame.clear()  # the keep-alive gone (a dead script): the watchdog trips
    rack.sleep(0.05)
    assert rack.state is ServiceState.FAULT
    # a rate command now is a one-line error with the service's reason, not silently ignored
    with pytest.raises(RackError, match=r"the service is FAULT, not ARMED: rates not sent \(outputs safe: stale heartbeat"):
        rack.rates(elbow_pitch=-0.1)
    rig.on_frame.append(lambda info: rack.keepalive_step())
    rack.arm(current_limit_a=2.0)  # re-armed with a new number
    rack.rates(elbow_pitch=-0.1)


def test_a_rate_command_drives_until_it_expires_then_the_keepalive_sends_zero_not_the_last(rig):
    rack, notes = _handle(rig)
    rack.arm(current_limit_a=2.0)
    angle0 = rack.read().angle("elbow_pitch").value
    rack.rates(elbow_pitch=-0.2)
    rack.sleep(RATE_EXPIRY_S - 0.05)
    assert _commanded(rig, "elbow_pitch") == -0.2 and rack.expired == 0
    moved = rack.read().angle("elbow_pitch").value - angle0
    assert moved < -0.01  # the arm follows the command
    rack.sleep(0.1)  # past the expiry without a renewal
    assert _commanded(rig, "elbow_pitch") == 0.0 and rack.expired == 1
    assert rack.state is ServiceState.ARMED  # zero rates, still armed: not a trip
    assert sum("expired" in n for n in notes) == 1
    rack.sleep(0.5)
    assert sum("expired" in n for n in notes) == 1  # said once per expiry


def test_renewing_the_rate_command_keeps_it(rig):
    rack, _ = _handle(rig)
    rack.arm(current_limit_a=2.0)
    for _ in range(10):  # 1 s of renewals every 0.1 s
        rack.rates(elbow_pitch=-0.1)
        rack.sleep(0.1)
    assert rack.expired == 0 and _commanded(rig, "elbow_pitch") == -0.1


def test_a_rate_below_breakaway_is_said_once_and_the_joint_indeed_does_not_move(rig):
    rack, notes = _handle(rig)
    rack.arm(current_limit_a=2.0)
    roll = joint("wrist_roll")
    assert 0.1 < roll.breakaway_rate_rad_s  # the finding's 0.1 rad/s on wrist roll
    a0 = rack.read().angle("wrist_roll").value
    for _ in range(3):
        rack.rates(wrist_roll=0.1)
        rack.sleep(0.1)
    still = rack.read().angle("wrist_roll").value - a0
    said = [n for n in notes if "breakaway" in n]
    assert len(said) == 1 and said[0].startswith("wrist_roll: 0.1 rad/s is below its breakaway rate 0.312")
    assert abs(still) < 0.005  # what the note says is what the (simulated) arm does
    for _ in range(3):
        rack.rates(wrist_roll=0.6)  # above breakaway: it moves, nothing more said
        rack.sleep(0.1)
    assert rack.read().angle("wrist_roll").value - a0 > 0.02
    assert len([n for n in notes if "breakaway" in n]) == 1


def test_a_rate_with_the_brake_set_is_said(rig):
    rack, notes = _handle(rig)
    rack.arm(current_limit_a=0.0)
    rack.rates(elbow_pitch=0.1)
    assert any(n.startswith("elbow_pitch: current limit 0 A (brake set)") for n in notes)


def test_mistakes_are_one_line_refusals_and_nothing_is_sent(rig):
    rack, _ = _handle(rig)
    rack.arm(current_limit_a=2.0)
    hb = int(rig.reader.read_commands().heartbeat)
    with pytest.raises(RackError, match="elbow_pitch: 0.9 rad/s is beyond its rate limit 0.5 rad/s"):
        rack.rates(elbow_pitch=0.9)
    with pytest.raises(RackError, match="no joint 'elbow'; joints: shoulder_pitch"):
        rack.rates(elbow=0.1)
    with pytest.raises(RackError, match="not finite"):
        rack.rates(elbow_pitch=float("nan"))
    with pytest.raises(RackError, match="shoulder_pitch: current limit -1.0 A: a limit is a finite number >= 0"):
        rack.current_limits(-1.0)
    with pytest.raises(RackError, match="wrist_roll: current limit 6 A is beyond its limit 5 A"):
        rack.current_limits(wrist_roll=6.0)
    assert int(rig.reader.read_commands().heartbeat) == hb
    rack.sleep(0.02)
    assert rack.state is ServiceState.ARMED


def test_inputs_are_named_and_carry_their_status(rig):
    rack, _ = _handle(rig)
    rack.sleep(0.05)
    inputs = rack.read()
    a = inputs.angle("elbow_pitch")
    assert a.name == "elbow_pitch_angle" and a.units == "rad" and a.status == "ok" and a.ok
    assert str(a).endswith("rad (ok)")
    raw = inputs.snapshot.elbow_pitch_angle  # the resolver's 0..2 pi as the buffer holds it
    assert raw > math.pi and a.value == pytest.approx(raw - 2 * math.pi)  # shown in (-pi, pi], as every tool
    assert inputs["elbow_pitch_angle"] == a
    assert inputs.service_state is ServiceState.SAFE
    with pytest.raises(RackError, match="no input 'elbow'; inputs: "):
        inputs["elbow"]


def test_an_exception_in_the_with_block_disarms(rig):
    rack, _ = _handle(rig)
    rack.arm(current_limit_a=2.0)
    rack.rates(elbow_pitch=-0.1)
    with pytest.raises(ZeroDivisionError):
        with rack:
            1 / 0
    rig.on_frame.clear()
    rig.ctl = None  # closed by the handle
    cmd = rig.reader.read_commands()
    assert int(cmd.arm_request) == 0 and not any(cmd.joint_rate_rad_s) and not any(cmd.current_limit_a)
    rig.run_frames(3)
    assert rig.reader.service_state is ServiceState.SAFE  # disarmed by command, not a trip


def test_a_second_writer_is_refused_in_one_line_naming_the_holder(rig):
    rig.controller("the-controller")
    with pytest.raises(RackError) as e:
        Rack.open(rig.name, owner="my-script")
    assert "the-controller" in str(e.value) and "\n" not in str(e.value)


def test_a_resolver_in_loss_of_signal_reads_with_that_status_not_as_a_plain_angle(rig):
    rack, _ = _handle(rig)
    rig.world.bus["rtd1"].inject("loss_of_signal", channel=0)
    rack.sleep(0.05)
    inputs = rack.read()
    statuses = {j: inputs.angle(j).status for j in rack.joints}
    bad = {j: st for j, st in statuses.items() if st != "ok"}
    assert list(bad.values()) == ["LOS"], statuses
    j = next(iter(bad))
    assert not inputs.angle(j).ok and str(inputs.angle(j)).endswith("rad (LOS)")


def test_current_limits_by_name_keep_the_others(rig):
    rack, notes = _handle(rig)
    rack.arm(current_limit_a=[1.0, 1.0, 1.0, 0.5, 0.5, 0.5, 0.8])  # the six joints and the gripper
    rack.current_limits(wrist_roll=0.2)
    lim = [float(x) for x in rig.reader.read_commands().current_limit_a]
    assert lim == [1.0, 1.0, 1.0, 0.5, 0.5, 0.2, 0.8]
    assert any(n.startswith("wrist_roll: current limit 0.2 A is below its breakaway current 0.347 A") for n in notes)
    with pytest.raises(RackError, match="not both"):
        rack.current_limits(1.0, wrist_roll=0.5)
