"""The simulated gripper jaw (fakes/arm.py axis 6): travel between its stops, an object between
the jaws, and a stall at the force the amplifier's current limit sets. Simulated time."""

from __future__ import annotations

import numpy as np
import pytest

from fakes.arm import ArmModel
from fakes.arm_params import AXES, N_AXES
from pfma.arm import GRIPPER

GR = 6
DT = 1 / 320


def _drive(arm: ArmModel, volts: float, limit_a: float, seconds: float) -> None:
    cmd, ilim = np.zeros(N_AXES), np.zeros(N_AXES)
    cmd[GR] = volts
    ilim[GR] = limit_a / GRIPPER.i_max_a * 10.0  # the current-limit input, V (10 V = I_max)
    for _ in range(int(round(seconds / DT))):
        arm.step(DT, cmd, ilim)


def test_the_gripper_row_is_the_nominal_jaw():
    a = AXES[GR]
    assert (a.name, a.hard_lo, a.hard_hi, a.omega_fs, a.i_max_a, a.inertia) == (
        "GR", 0.0, GRIPPER.travel_m, GRIPPER.omega_fs_m_s, GRIPPER.i_max_a, GRIPPER.mass_kg)
    assert a.torque_per_amp == pytest.approx(GRIPPER.force_per_amp) == pytest.approx(40.0)
    assert not a.brake and not a.has_angle


@pytest.mark.parametrize("limit_a", [0.5, 1.5, 4.0])
def test_a_close_onto_an_object_stalls_at_the_force_the_current_limit_sets(limit_a):
    arm = ArmModel()
    arm.place_jaw_object(0.04)
    _drive(arm, -4.0, limit_a, 1.5)  # 20 mm/s closing: 10 mm to the object
    _drive(arm, -10.0, limit_a, 0.5)  # full scale: the amplifier saturates at its limit
    assert arm.q[GR] == pytest.approx(0.04, abs=1e-4)  # stalled on the object
    assert abs(arm.qdot[GR]) < 1e-6
    assert arm.current_a[GR] == pytest.approx(-limit_a)
    # the object's force = the motor's, less what the jaw's Coulomb friction holds at rest
    assert arm.jaw_force_n == pytest.approx(GRIPPER.force_per_amp * limit_a, abs=GRIPPER.coulomb_n + 0.01)
    assert arm.state().jaw_force_n == arm.jaw_force_n


def test_the_jaw_travels_between_its_stops_and_an_open_jaw_lets_go():
    arm = ArmModel()
    _drive(arm, 4.0, 2.0, 4.0)
    assert arm.q[GR] == pytest.approx(GRIPPER.travel_m, abs=1e-4) and arm.jaw_force_n == 0.0
    arm.place_jaw_object(0.06)
    _drive(arm, -10.0, 2.0, 3.0)
    assert arm.q[GR] == pytest.approx(0.06, abs=1e-4) and arm.jaw_force_n > 70.0
    _drive(arm, 4.0, 2.0, 0.5)  # opening: the object no longer pressed
    assert arm.q[GR] > 0.065 and arm.jaw_force_n == 0.0
    arm.place_jaw_object(None)
    _drive(arm, -10.0, 1.0, 3.0)  # closed on itself: the closed stop presses back
    assert arm.q[GR] == pytest.approx(0.0, abs=1e-4) and arm.jaw_force_n == pytest.approx(40.0, abs=2.1)


@pytest.mark.parametrize("width, says", [
    (0.08, "the jaw is open 50.0 mm, narrower than the 80.0 mm object: open it first"),
    (0.0, "does not fit the jaw's travel 0..0.1 m"),
    (0.2, "does not fit the jaw's travel"),
    (float("nan"), "does not fit the jaw's travel"),
])
def test_an_object_that_cannot_be_between_the_jaws_is_refused(width, says):
    arm = ArmModel()  # the jaw starts half open (50 mm)
    with pytest.raises(ValueError, match=says):
        arm.place_jaw_object(width)
    assert arm.jaw_object_m is None
