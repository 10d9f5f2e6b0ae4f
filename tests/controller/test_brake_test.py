"""The power-up brake test (issue 30 item 3): before START UP COMPLETE each joint moves a
little out and back, so the sensors prove its brake released and its drive answering; a
joint that does not fails the power-up, named with its likely cause, every current limit
0. System simulator (simulated time): the faults act on the arm model, the servo layer
reads only the published inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.decision import Status
from controller.params import JOINT_NAMES
from controller.servo import BRAKE_TEST_MAX_S, ERR_BRAKE_TEST, SUPERVISION_CODES
from controller.supervision import BRAKE_PROVEN, BRAKE_UNPROVEN, CAUSE_AMP_OFF, CAUSE_BRAKE


def _sim():
    from sim.system import SystemSimulator
    sim = SystemSimulator()
    sim.step(10)
    return sim


def _texts(sim) -> list[str]:
    return [m.text for m in sim.rt.messages.recent(500)]


def _power_up_until_done_or_error(sim, frames: int = 800) -> None:
    from controller.layers import Request
    sim.rt.request(Request.POWER_UP)
    sim.run_until(lambda: sim.rt.all_status(Status.START_UP_COMPLETE) or sim.rt.servo.fault, frames)


def test_every_joint_proves_its_brake_then_the_loop_closes_on_the_power_up_pose():
    with _sim() as sim:
        q0 = np.array(sim.joint_angles_rad()[:6], dtype=float)
        _power_up_until_done_or_error(sim)
        assert sim.rt.all_status(Status.START_UP_COMPLETE), _texts(sim)[-5:]
        assert [int(x) for x in sim.rt.wm.get("servo.brake_state")] == [BRAKE_PROVEN] * 6
        said = [t for t in _texts(sim) if "brake test passed" in t]
        assert len(said) == 1 and "every joint moved as told" in said[0], _texts(sim)[-5:]
        furthest = float(said[0].split("furthest ")[1].split(" deg")[0])
        assert 0.0 < furthest < 2.0  # a small motion: out and back, at most a couple of degrees
        sim.step(320)  # a second of holding: back at the pose the power-up started from, within
        # the position loop's friction dead band (K = 8 1/s against the wrist roll's Coulomb
        # friction leaves about 0.7 deg, the dead band of pfma-model 8.4)
        q = np.array(sim.joint_angles_rad()[:6], dtype=float)
        assert np.max(np.abs(q - q0)) < math.radians(1.0), np.degrees(q - q0)


@pytest.mark.parametrize("spec, joint, cause, words", [
    ("brake-held:elbow_pitch", "elbow_pitch", CAUSE_BRAKE, "brake not released"),
    ("amp-off:wrist_roll", "wrist_roll", CAUSE_AMP_OFF, "amplifier, PWM stage or current limit off"),
    # the servo chassis panel (IRSS 3.6): a joint's brake-release switch, a PWM stage left off
    ("panel-off:brake:shoulder_yaw", "shoulder_yaw", CAUSE_BRAKE, "brake not released"),
    ("panel-off:pwm:wrist_pitch", "wrist_pitch", CAUSE_AMP_OFF, "amplifier, PWM stage or current limit off"),
])
def test_a_joint_that_does_not_prove_itself_fails_the_power_up_named(spec, joint, cause, words):
    from sim.faults import FaultSet
    with _sim() as sim:
        FaultSet(sim.world).inject(spec)
        _power_up_until_done_or_error(sim)
        servo = sim.rt.servo
        assert servo.fault and servo.error_code == ERR_BRAKE_TEST, _texts(sim)[-5:]
        assert not sim.rt.all_status(Status.START_UP_COMPLETE)
        k = JOINT_NAMES.index(joint)
        assert int(sim.rt.wm.get("servo.trip_joint")) == k and int(sim.rt.wm.get("servo.trip_cause")) == cause
        text = servo.fault_text
        assert text.startswith("brake test: ") and f"{joint} did not move as told" in text and words in text, text
        assert f"not within {BRAKE_TEST_MAX_S * 1e3:.0f} ms" in text
        assert [JOINT_NAMES[j] for j in range(6) if f"{JOINT_NAMES[j]} did not" in text] == [joint]  # only it
        sim.step(40)
        assert np.all(np.asarray(sim.rt.wm.get("servo.current_limit_cmd_a")) == 0.0)
        assert int(sim.rt.wm.get("servo.brake_state")[k]) != BRAKE_PROVEN


def test_a_reversed_tach_trips_in_the_brake_test_before_any_commanded_motion():
    """The same small motion is the direction check: a tach reversed into positive
    feedback trips a supervision check while the joint is proved, not at the first move."""
    from sim.faults import FaultSet
    with _sim() as sim:
        k = JOINT_NAMES.index("shoulder_yaw")
        q0 = sim.joint_angles_rad()[k]
        FaultSet(sim.world).inject("tach-reversed:shoulder_yaw")
        _power_up_until_done_or_error(sim)
        servo = sim.rt.servo
        assert servo.fault and servo.error_code in (SUPERVISION_CODES["tach against resolver"],
                                                    SUPERVISION_CODES["overspeed"], ERR_BRAKE_TEST), _texts(sim)[-5:]
        assert servo.trip is not None and servo.trip.joint == k, servo.fault_text
        assert not sim.rt.all_status(Status.START_UP_COMPLETE)
        sim.step(320)
        assert abs(math.degrees(sim.joint_angles_rad()[k] - q0)) < 5.0  # stopped within a few degrees


def test_the_test_off_powers_up_without_moving_and_the_brakes_stay_unproven():
    with _sim() as sim:
        wm = sim.rt.wm
        assert wm.spec("servo.brake_test").protected
        wm.set_user("servo.brake_test", 0, wm.access_key)
        _power_up_until_done_or_error(sim)
        assert sim.rt.all_status(Status.START_UP_COMPLETE)
        assert not any("brake test passed" in t for t in _texts(sim))
        assert any("brake test off" in t for t in _texts(sim))
        assert [int(x) for x in wm.get("servo.brake_state")] == [BRAKE_UNPROVEN] * 6


@pytest.mark.parametrize("bit", [0, 1])
def test_a_dac_that_drives_one_way_only_fails_the_brake_test_within_its_bound(bit):
    """A DAC data bit stuck (the offset-binary MSB of shoulder yaw's rate channel): the
    command reaches the joint one way only. The test's way back is the direction check: the
    joint fails at power-up, named with the DAC, within the test's 2 degrees."""
    from sim.faults import FaultSet
    from controller.servo import BRAKE_TEST_MAX_EXCURSION_RAD
    from controller.supervision import CAUSE_DAC
    with _sim() as sim:
        k = JOINT_NAMES.index("shoulder_yaw")
        e = sim.client.layout.joint_entry("dac", "shoulder_yaw", "rate_command")
        q0 = sim.joint_angles_rad()[k]
        FaultSet(sim.world).inject(f"stuck-bit:{e.board}@DAC[{e.channel}]:11={bit}")
        _power_up_until_done_or_error(sim)
        servo = sim.rt.servo
        assert servo.fault and servo.error_code == ERR_BRAKE_TEST, _texts(sim)[-5:]
        assert int(sim.rt.wm.get("servo.trip_joint")) == k and int(sim.rt.wm.get("servo.trip_cause")) == CAUSE_DAC
        assert "shoulder_yaw did not move as told" in servo.fault_text, servo.fault_text
        sim.step(320)
        moved = abs(sim.joint_angles_rad()[k] - q0)
        assert moved < BRAKE_TEST_MAX_EXCURSION_RAD + math.radians(1.0), math.degrees(moved)  # stopped near the bound


@pytest.mark.parametrize("switch", ["28v", "15v"])
def test_the_chassis_supply_off_fails_the_power_up_naming_every_joint(switch):
    """+28 V (or the +-15 V converter) off on the servo chassis panel: nothing drives, every
    brake stays set; the brake test names all six joints, none moves."""
    from sim.faults import FaultSet
    with _sim() as sim:
        q0 = np.array(sim.joint_angles_rad()[:6])
        FaultSet(sim.world).inject(f"panel-off:{switch}")
        _power_up_until_done_or_error(sim)
        servo = sim.rt.servo
        assert servo.fault and servo.error_code == ERR_BRAKE_TEST, _texts(sim)[-5:]
        assert all(f"{j} did not move as told" in servo.fault_text for j in JOINT_NAMES), servo.fault_text
        sim.step(160)
        assert np.max(np.abs(np.array(sim.joint_angles_rad()[:6]) - q0)) < math.radians(0.1)

