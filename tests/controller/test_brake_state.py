"""Each joint's brake as the sensors show it (issue 30 item 3, ``servo.brake_state``): SET
while its current limit is 0 and the joint is still, UNPROVEN until the joint has moved the
way it was told since its limit was raised, PROVEN RELEASED after; a held brake never
proves released, whatever the command said. System simulator (simulated time): the held
brake acts on the arm model, the supervision reads only the published inputs."""

from __future__ import annotations

import numpy as np

from controller.decision import Status
from controller.layers import Request
from controller.params import JOINT_NAMES
from controller.supervision import BRAKE_PROVEN, BRAKE_SET, BRAKE_UNPROVEN, JointSupervisor

DT = 1 / 160


def _state(sim) -> list[int]:
    return [int(x) for x in sim.rt.wm.get("servo.brake_state")]


def test_the_power_up_brake_test_proves_every_brake_a_power_down_sets_them(powered):
    sim = powered
    assert _state(sim) == [BRAKE_PROVEN] * 6  # the power-up's brake test moved each out and back
    assert "2 PROVEN RELEASED" in sim.rt.wm.spec("servo.brake_state").doc
    sim.rt.request(Request.POWER_DOWN)
    sim.step(600)
    assert sim.rt.all_status(Status.SHUT_DOWN)
    assert _state(sim) == [BRAKE_SET] * 6  # limits 0 and every joint still: the last thing sensed


def test_without_the_brake_test_holding_is_unproven_a_move_proves_it(sim):
    wm = sim.rt.wm
    wm.set_user("servo.brake_test", 0, wm.access_key)
    sim.power_up(max_frames=400)
    sim.step(20)
    assert _state(sim) == [BRAKE_UNPROVEN] * 6  # limits raised, no commanded motion yet
    k = JOINT_NAMES.index("elbow_pitch")
    goal = np.array(sim.rt.wm.get("daq.joint_angle_rad"))
    goal[k] -= 0.2
    sim.rt.set_joint_goal(goal)
    sim.step(320)
    st = _state(sim)
    assert st[k] == BRAKE_PROVEN and st.count(BRAKE_PROVEN) == 1, st  # only the joint that moved
    sim.rt.request(Request.POWER_DOWN)
    sim.step(600)
    assert sim.rt.all_status(Status.SHUT_DOWN)
    assert _state(sim) == [BRAKE_SET] * 6  # limits 0 and every joint still: the last thing sensed


def _held_brake_after_power_up(brake_test: int) -> list[int]:
    """Power up (the brake test on or off), then hold shoulder yaw's brake and tell it to move:
    its brake state, sample by sample, until the stall check trips it."""
    from sim.faults import FaultSet
    from sim.system import SystemSimulator
    with SystemSimulator() as sim:
        sim.rt.wm.set_user("servo.brake_test", brake_test, sim.rt.wm.access_key)
        sim.step(10)
        sim.power_up(400)
        sim.step(20)
        k = JOINT_NAMES.index("shoulder_yaw")
        FaultSet(sim.world).inject("brake-held:shoulder_yaw")
        goal = np.array(sim.rt.wm.get("daq.joint_angle_rad"))
        goal[k] += 0.3
        sim.rt.set_joint_goal(goal)
        seen = []
        for _ in range(200):
            sim.step(1)
            seen.append(_state(sim)[k])
            if sim.rt.servo.trip is not None:
                break
        assert sim.rt.servo.trip is not None and sim.rt.servo.trip.joint == k  # the stall check stops it
        return seen


def test_a_held_brake_never_proves_released():
    seen = _held_brake_after_power_up(brake_test=0)
    assert BRAKE_PROVEN not in seen and BRAKE_UNPROVEN in seen


def test_a_proven_brake_that_then_holds_is_proven_no_more_before_the_trip():
    """Proven at power-up by the brake test, then held (a seized brake): told to move and
    not moving for half the stall time, it is UNPROVEN again, before the stall trip."""
    seen = _held_brake_after_power_up(brake_test=1)
    assert seen[0] == BRAKE_PROVEN and BRAKE_UNPROVEN in seen
    assert seen[seen.index(BRAKE_UNPROVEN):] == [BRAKE_UNPROVEN] * (len(seen) - seen.index(BRAKE_UNPROVEN))


def test_the_rule_on_made_up_samples():
    sup = JointSupervisor()
    q = [0.0] * 6
    z = [0.0] * 6
    lim = [5.0] * 7
    sup.update(DT, q, z, z, z, lim, False)  # primes
    sup.update(DT, q, z, z, z, lim, False)
    assert sup.brake_state == [BRAKE_UNPROVEN] * 6
    # joint 0 moves +0.1 rad/s with +0.1 commanded (0.03 x 0.4 = 0.012 rad/s is the least)
    for n in range(1, 40):
        sup.update(DT, [0.1 * DT * n] + [0.0] * 5, [0.1] + [0.0] * 5, z, [0.1] + [0.0] * 5, lim, False)
    assert sup.brake_state[0] == BRAKE_PROVEN and sup.brake_state[1:] == [BRAKE_UNPROVEN] * 5
    # moving the other way from the command proves nothing
    sup2 = JointSupervisor()
    sup2.update(DT, q, z, z, z, lim, False)
    for n in range(1, 40):
        sup2.update(DT, [-0.1 * DT * n] + [0.0] * 5, [-0.1] + [0.0] * 5, z, [0.1] + [0.0] * 5, lim, False)
    assert sup2.brake_state[0] == BRAKE_UNPROVEN
    # limits 0: still is SET, moving is UNPROVEN (a set brake would hold it)
    zero = [0.0] * 7
    sup.update(DT, [sup._q[0]] + [0.0] * 5, z, z, z, zero, False)
    assert sup.brake_state[1:] == [BRAKE_SET] * 5


def test_powered_down_a_one_count_flicker_is_still_and_a_slipping_joint_is_unproven():
    sup = JointSupervisor()
    zero = [0.0] * 7
    count = 2 * np.pi / 65536  # one resolver count (16 bits a turn)
    t = 0.0
    for n in range(40):
        t += DT
        q = [count * (n % 2)] * 6
        q[1] = 0.05 * t  # shoulder yaw slips at 0.05 rad/s (omega_fs 0.4: 0.012 is the least)
        sup.observe_brakes(t, q, zero)
    assert sup.brake_state == [BRAKE_SET, BRAKE_UNPROVEN] + [BRAKE_SET] * 4
