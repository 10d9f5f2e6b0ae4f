"""The script handle's gripper (bit3/handle.py ``Rack.gripper_*``, docs/python.md) against the
simulated rack in simulated time: the keep-alive (run before every service frame) updates
the gripper's motion; ``rack.sleep`` runs the rig."""

from __future__ import annotations

import pytest

from bit3.handle import Rack, RackError
from fakes.arm_params import SimErrors
from pfma.arm import GRIPPER
from pfma.gripper import GripperState
from sim.rig import SimRig

CH_GRIP, CH_LIMIT = 6, 13


@pytest.fixture
def rig():
    r = SimRig(prefix="pfma-hdg-")
    try:
        yield r
    finally:
        r.close()


def _handle(rig: SimRig) -> tuple[Rack, list[str]]:
    notes: list[str] = []
    period = rig.svc.schedule.period_s
    rack = Rack(rig.controller("test-script"), rack=rig.rack, now=rig.clock.now,
                sleep=lambda s: rig.run_frames(max(1, round(s / period))), keepalive=False, say=notes.append)
    rig.on_frame.append(lambda info: rack.keepalive_step())
    return rack, notes


def _dac(rig: SimRig) -> list[float]:
    return [float(v) for v in rig.world.bus["dac"].output_volts_all()]


def test_open_close_on_a_part_hold_the_force_and_stop_from_a_script(rig):
    rack, notes = _handle(rig)
    arm = rig.world.sim.arm
    rack.arm(current_limit_a=2.0)
    assert rack.gripper_state is GripperState.STOPPED
    arm.q[6] = 0.09
    assert rack.gripper_open() == "OPENING at 20 mm/s, 40 N"
    assert rack.gripper_wait().startswith("OPEN: at the open stop after")
    assert arm.q[6] == pytest.approx(GRIPPER.travel_m, abs=2e-4)
    arm.place_jaw_object(0.08)
    rack.gripper_close(force_n=80)
    done = rack.gripper_wait()
    assert done.startswith("GRIPPING after") and "holding at 80 N; jaw ~80 mm" in done
    rack.sleep(0.5)  # the hold: the jaw presses with the force the current limit sets
    assert rack.gripper_state is GripperState.GRIPPING
    assert abs(arm.jaw_force_n - 80.0) <= GRIPPER.coulomb_n + 0.5
    dac = _dac(rig)
    assert dac[CH_GRIP] == pytest.approx(-10.0) and dac[CH_LIMIT] == pytest.approx(80 / 40 / 0.5, abs=0.01)
    assert rack.gripper_force(120.0) == "grip force 120 N, current limit 3 A"
    rack.sleep(0.3)
    assert abs(arm.jaw_force_n - 120.0) <= GRIPPER.coulomb_n + 0.5
    assert rack.gripper_stop() == "stopped (GRIPPING ended), jaw ~80 mm"
    rack.sleep(0.1)
    assert _dac(rig)[CH_GRIP] == 0.0
    rack.close()
    assert _dac(rig)[CH_LIMIT] == 0.0 and notes == []


def test_the_gripper_refuses_what_it_cannot_do_in_one_line(rig):
    rack, _ = _handle(rig)
    with pytest.raises(RackError, match=r"the service is SAFE, not ARMED: gripper close not sent; rack.arm\(...\) first"):
        rack.gripper_close()
    rack.arm(current_limit_a=2.0)
    with pytest.raises(RackError, match=r"gripper close: grip force 500 N is outside 10..200 N .*\(nothing sent\)"):
        rack.gripper_close(force_n=500)
    assert rack.gripper_state is GripperState.STOPPED and _dac(rig)[CH_GRIP] == 0.0
    rack.close()


def test_a_drive_that_does_not_answer_fails_the_wait_and_is_said(rig):
    rack, notes = _handle(rig)
    rig.world.sim.set_errors(SimErrors(amp_off=tuple(i == 6 for i in range(7))))
    rack.arm(current_limit_a=2.0)
    rack.gripper_open()
    with pytest.raises(RackError, match="gripper: OPENING: the jaw did not move .* the drive does not answer"):
        rack.gripper_wait()
    assert rack.gripper_state is GripperState.STALLED
    assert len(notes) == 1 and "the drive does not answer" in notes[0]
    rack.close()
