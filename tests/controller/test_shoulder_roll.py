"""The shoulder-roll index (issue 30 item 2; docs/controller.md "The shoulder-roll index"),
on the system simulator in simulated time.

The shoulder roll is indexed by hand (pfma-model 8.1: -90..+90 deg in 45 deg steps) and has
no sensor. The controller takes it as the user parameter ``joint.shoulder_roll_deg`` (only the
index positions, only while powered down); power-up takes it for the kinematics of every
Cartesian mode and the F/T gravity compensation. The simulated arm is pinned at an index of
its own (``SystemSimulator(shoulder_roll_deg=...)``): when the two agree, the hand
controller's world axes are the tool's; when they do not, the motion goes wrong, which is
what these tests would see if the index were not used.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller.decision import Status
from controller.kinematics import fk
from controller.paths import MspMode, MspResult, PathStore, make_point
from controller.quat import q_angle
from controller.worldmodel import WorldModel, WorldModelError, WorldModelValueError
from sim.system import SystemSimulator
from tests.controller import _wm_support as sup
from tests.controller._cart_support import stick

FRAME_S = 1.0 / 320.0
RATE_M_S = 0.25 * 0.15  # u = 0.25 at V_QUARTER, default gain 0.15 m/s (pfma-model 8.5, 8.2)
STEPS = "-90, -45, 0, 45, 90"  #: how a refusal names the index positions (deg)


def _sim(arm_deg: int, controller_deg: int | None = None, **user) -> SystemSimulator:
    """A simulator whose arm is pinned at ``arm_deg`` and whose controller's index is
    ``controller_deg`` (default the same), with user variables set, powered up."""
    sim = SystemSimulator(shoulder_roll_deg=arm_deg)
    sim.step(10)
    wm = sim.rt.wm
    if controller_deg is not None and controller_deg != arm_deg:
        sim.rt.set_shoulder_roll(controller_deg)
    for name, value in user.items():
        wm.set_user(name.replace("__", "."), value, wm.access_key)
    sim.power_up()
    return sim


def _world_velocity(sim: SystemSimulator, axis: str) -> np.ndarray:
    """The true tool's mean world-frame velocity over the second second of a stick deflection
    along ``axis`` (u = 0.25: 0.0375 m/s commanded along that world axis)."""
    sim.step(20)
    stick(sim, axis)
    path = []
    for _ in range(640):
        sim.step(1)
        path.append(sim.tool_pose()[0])
    stick(sim, None, deadman=False)
    return (path[639] - path[319]) / (320 * FRAME_S)


def _off_axis_deg(v: np.ndarray, axis: str) -> float:
    """Angle between a velocity and the world axis it was commanded along, degrees."""
    i = "xyz".index(axis)
    return math.degrees(math.acos(max(-1.0, min(1.0, float(v[i]) / float(np.linalg.norm(v))))))


# --- the parameter ------------------------------------------------------------------------------
def test_the_index_is_a_parameter_of_the_index_positions_set_only_while_powered_down():
    with SystemSimulator() as sim:
        sim.step(5)
        wm = sim.rt.wm
        spec = wm.spec("joint.shoulder_roll_deg")
        assert (spec.user, spec.units, spec.choices) == ("powered_down", "deg", (-90.0, -45.0, 0.0, 45.0, 90.0))
        assert wm.get("joint.shoulder_roll_deg") == 0.0
        for bad in (30, 45.5, 135, -180):
            with pytest.raises(WorldModelValueError) as e:
                sim.rt.set_shoulder_roll(bad)
            assert str(e.value) == f"joint.shoulder_roll_deg: {bad:g} deg is not one of its values ({STEPS} deg)"
        sim.rt.set_shoulder_roll(-45)
        sim.step(1)
        assert wm.get("joint.shoulder_roll_deg") == -45.0
        sim.power_up()
        with pytest.raises(WorldModelError, match="only while powered down"):
            sim.rt.set_shoulder_roll(0)
        assert wm.get("joint.shoulder_roll_deg") == -45.0


def test_a_forged_ring_entry_of_another_index_is_rejected_by_the_owner():
    """The ring is shared memory: a process that skips set_user is checked again when the
    controller applies the write, against the same index positions."""
    name = sup.unique_name()
    try:
        with SystemSimulator(wm_name=name) as sim:
            sim.step(5)
            wm = sim.rt.wm
            bad = sup.forge_request(name, "joint.shoulder_roll_deg", 30.0, wm.access_key)
            good = sup.forge_request(name, "joint.shoulder_roll_deg", 90.0, wm.access_key)
            sim.step(1)
            r = wm.request(bad)
            assert (r.state, r.result) == ("rejected",
                                           f"joint.shoulder_roll_deg: 30 deg is not one of its values ({STEPS} deg)")
            assert wm.request(good).state == "applied" and wm.get("joint.shoulder_roll_deg") == 90.0
    finally:
        WorldModel.remove_segment(name)


def test_the_simulated_arm_takes_the_index():
    with SystemSimulator(shoulder_roll_deg=-90) as sim:
        assert sim.shoulder_roll_rad == pytest.approx(-math.pi / 2)
        q = sim.joint_angles_rad()
        p0, _ = fk(q)
        p, _ = sim.tool_pose()
        # world = base rotated about x by the index: y' = c y - s z, z' = s y + c z
        c, s = math.cos(-math.pi / 2), math.sin(-math.pi / 2)
        assert p == pytest.approx([p0[0], c * p0[1] - s * p0[2], s * p0[1] + c * p0[2]], abs=1e-12)
    with pytest.raises(ValueError, match="indexed by hand at -90 deg, -45 deg, 0 deg, \\+45 deg, \\+90 deg"):
        SystemSimulator(shoulder_roll_deg=30)


# --- power-up -----------------------------------------------------------------------------------
def test_power_up_takes_the_index_says_it_and_holds_the_tool_where_it_is():
    """The POWER UP answer and the Joint Planner name the index; the Cartesian engine holds
    the measured pose with it (with the index ignored there, the hold would be the tool's
    pose at index 0, 0.25 m away, and the arm would move there)."""
    with SystemSimulator(shoulder_roll_deg=45) as sim:
        sim.step(10)
        p0, _ = sim.tool_pose()
        sim.power_up()
        wm = sim.rt.wm
        assert wm.get("joint.shoulder_roll_rad") == pytest.approx(math.radians(45))
        texts = [m.text for m in sim.rt.messages.recent()]
        assert any("POWER UP (shoulder-roll index +45 deg: no sensor, as set in joint.shoulder_roll_deg) "
                   "-> IN PROGRESS" in t for t in texts), texts
        assert any(t.startswith("shoulder-roll index +45 deg (joint.shoulder_roll_deg") for t in texts)
        sim.step(320)
        assert sim.rt.all_status(Status.START_UP_COMPLETE)
        p, _ = sim.tool_pose()
        # the servo's sag under gravity and the brake test's out and back (back within the
        # joints' friction dead band, about 0.7 deg of wrist roll), nothing more: 0.25 m if the
        # index were ignored
        assert np.linalg.norm(p - p0) < 0.010
        assert np.linalg.norm(wm.get("cart.pos_cmd_m") - p0) < 0.010  # held where the tool was
        assert np.linalg.norm(wm.get("joint.tool_pos_m") - p) < 0.002  # measured with the index


@pytest.mark.parametrize("deg", [-90, 90])
def test_power_up_at_either_end_index_holds(deg):
    with _sim(deg) as sim:
        p0, _ = sim.tool_pose()
        sim.step(640)
        assert sim.rt.all_status(Status.START_UP_COMPLETE)
        assert np.linalg.norm(sim.tool_pose()[0] - p0) < 0.006


# --- Cartesian modes ----------------------------------------------------------------------------
@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_teleop_at_45_deg_moves_the_tool_along_the_world_axis(axis):
    """Arm and controller at +45 deg: the tool's world-frame velocity is the commanded world
    direction (within 2 degrees) at the commanded rate (within 3 %, as at index 0)."""
    with _sim(45, cart__mode=1) as sim:
        v = _world_velocity(sim, axis)
        assert _off_axis_deg(v, axis) < 2.0, v
        assert v["xyz".index(axis)] == pytest.approx(RATE_M_S, rel=0.03)
        assert sim.rt.all_status(Status.START_UP_COMPLETE)


@pytest.mark.parametrize("axis", ["y", "z"])
def test_a_controller_index_other_than_the_arms_sends_teleop_off_the_world_axis(axis):
    """The same check with the arm at +45 deg and the controller told 0: up and left come out
    tilted by the difference (x, the roll axis, is the same in both frames)."""
    with _sim(45, 0, cart__mode=1) as sim:
        v = _world_velocity(sim, axis)
        assert _off_axis_deg(v, axis) == pytest.approx(45.0, abs=3.0), v


def test_a_path_at_45_deg_moves_along_the_world_axis(tmp_path):
    """A one-segment path 4 cm up from the tool, played with arm and controller at +45 deg:
    the tool rises 4 cm along world z (the trajectory is world poses; the index is applied
    where the kinematics are)."""
    with _sim(45) as sim:
        wm, key = sim.rt.wm, sim.rt.wm.access_key
        msp = sim.rt.by_key["msp"]
        msp.store = PathStore(tmp_path)
        sim.step(160)
        p0, q0 = sim.tool_pose()
        path = msp.store.new("up", points=[make_point(p0, q0, "teach"), make_point(p0 + [0.0, 0.0, 0.04], q0,
                                                                                    "teach")])
        for name, value in (("msp.path_id", path.id), ("cart.mode", 2), ("msp.mode", MspMode.PLAY)):
            wm.set_user(name, value, key)
        done = int(wm.get("msp.finished"))
        sim.run_until(lambda: int(wm.get("msp.finished")) > done, 320 * 8)
        assert int(wm.get("msp.result")) == MspResult.OK
        sim.step(480)  # the servo's tracking lag
        p, q = sim.tool_pose()
        d = p - p0
        assert d[2] == pytest.approx(0.04, abs=0.005)
        assert np.hypot(d[0], d[1]) < 0.005
        assert math.degrees(q_angle(q, q0)) < 1.0


@pytest.mark.parametrize("controller_deg", [45, 0])
def test_impedance_gravity_compensation_takes_the_index(controller_deg):
    """Impedance on (the F/T zeroed at the start pose), then the tool turned 28 deg about the
    world z axis: with the controller's index the arm's, the tool's gravity is compensated and
    the processed wrench stays inside the 2 N deadband (0); told 0 instead of +45 deg, the
    gravity the compensation expects is tilted and a phantom force of several N pushes the
    compliant offset."""
    with _sim(45, controller_deg, cart__mode=1) as sim:
        wm = sim.rt.wm
        sim.step(160)
        wm.set_user("force.enable", True, wm.access_key)
        sim.step(200)
        assert int(wm.get("force.state")) == 2  # IMPEDANCE
        q0 = sim.tool_pose()[1]
        sim.world.set_cae([0.0, 0.0, 0.0, 10.0, 0.0, 0.0], (True, False, False))  # full yaw: 0.25 rad/s
        sim.step(640)
        sim.world.set_cae([0.0] * 6, (False, False, False))
        sim.step(640)
        assert math.degrees(q_angle(q0, sim.tool_pose()[1])) > 20.0
        force = float(np.linalg.norm(wm.get("force.wrench_n")[:3]))
        offset = float(np.linalg.norm(wm.get("force.offset")[:3]))
        if controller_deg == 45:
            assert force == 0.0 and offset < 1e-3
        else:
            assert force > 2.5 and offset > 4e-3
