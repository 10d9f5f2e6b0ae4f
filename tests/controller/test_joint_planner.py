"""Joint Planner on the simulated rack (simulated time): Cartesian mode, joint goals, flags.

How the tests command a Cartesian pose: the ``cart.*`` variables belong to the Cartesian
Engine (writer ``cartesian``), so they are not user-writable. The fixture ``stub``
swaps the Cartesian Engine for a test-only layer with the same key, the same variables
(the real layer's ``specs()``) and the same periodic task names, whose 80 Hz task posts
the pose the test sets (``stub.set(...)``) as the writer ``cartesian``. It does this by
wrapping ``controller.runtime.build_layers`` with pytest's monkeypatch, so the rest of
the stack (service, Data Acquisition, Servo, the simulated arm) is the real one and the
real Cartesian Engine is untouched. One test at the end runs the real Cartesian Engine.

Accuracy figures checked here (the simulated arm, measured by its true state, not the
resolvers): a commanded pose 0.15 m and 15 deg away is reached within 2 mm and 0.1 deg
(measured ~0.15 mm and 0.01 deg: resolver quantisation, 96 urad, times the 2 m reach).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import controller.runtime as runtime
from controller import kinematics as K
from controller.decision import Status
from controller.layers import JointPlannerLayer, Layer
from controller.messages import Level
from controller.quat import q_angle, q_from_axis_angle, q_from_matrix, q_mul, q_slerp
from sim.system import SystemSimulator
from fakes.arm import ArmModel
from fakes.kinematics import Kinematics as SimKinematics

D = math.pi / 180.0
SIM_KIN = SimKinematics()


class CartesianStub(Layer):
    """Test-only stand-in for the Cartesian Engine: posts a pose the test chooses."""

    key = "cartesian"
    title = "Cartesian Engine (test stub)"
    short = "CART"

    def __init__(self, real: Layer) -> None:
        super().__init__()
        self._specs = real.specs()
        names = {s.name for s in self._specs}
        assert set(JointPlannerLayer.CART_VARS) <= names, "the Cartesian Engine must declare cart.*"
        for t in real.periodic:
            self.periodic[t] = (lambda rt: None)
        self.periodic["cartesian_fast"] = self.fast
        self.valid = False
        self.pose_fn = None  #: callable(t_s) -> (p, quat), t since set()
        self.t0 = 0.0
        self.seq = 0
        self.now = 0.0

    def specs(self):
        return list(self._specs)

    def set(self, pose_fn, valid: bool = True) -> None:
        """Command ``pose_fn(t_s)`` from now on (a constant pose: ``lambda t: (p, q)``)."""
        self.pose_fn, self.valid, self.t0 = pose_fn, valid, self.now

    def fast(self, rt) -> None:
        self.now = rt.now
        if self.pose_fn is None:
            return
        p, q = self.pose_fn(rt.now - self.t0)
        self.seq += 1
        rt.wm.post_task_outputs(self.key, {"cart.pos_cmd_m": p, "cart.quat_cmd": q,
                                           "cart.cmd_valid": self.valid, "cart.cmd_seq": self.seq})


#: a lag servo design (K = 40 1/s, tau_z = 0.5 s, tau_p = 2.5 s: the default's gain of 8 at
#: high frequency, 5x it at DC) that shrinks the static error of the proportional loop
LAG_SERVO = (40.0, 0.5, 2.5)


@pytest.fixture
def make(monkeypatch):
    """Factory: ``make(q0=None, servo=None)`` -> (powered-up SystemSimulator, CartesianStub).

    :param q0: initial arm joint angles, command-area order (default: the 8.1 ready pose)
    :param servo: (K, tau_z, tau_p) for every joint (default: the nominal K = 8 1/s)
    """
    real_build = runtime.build_layers
    made: list[CartesianStub] = []
    sims: list[SystemSimulator] = []

    def build(client, require_ft=True):
        layers = real_build(client, require_ft)
        i = next(k for k, l in enumerate(layers) if l.key == "cartesian")
        layers[i] = CartesianStub(layers[i])
        made.append(layers[i])
        for up, down in zip(layers, layers[1:]):
            up.subordinate, down.superior = down, up
        return layers

    monkeypatch.setattr(runtime, "build_layers", build)

    def factory(q0=None, servo=None):
        kw = {}
        if q0 is not None:
            kw["arm"] = ArmModel(q0=list(np.asarray(q0, dtype=float)[K.DH_FROM_CA]) + [0.05])
        sim = SystemSimulator(**kw)
        sims.append(sim)
        if servo is not None:
            key = sim.rt.wm.access_key
            for name, value in zip(("servo.kp_per_s", "servo.tau_z_s", "servo.tau_p_s"), servo):
                sim.rt.wm.set_user(name, [value] * 6, key)
        sim.step(10)
        sim.power_up(400)
        sim.step(20)
        assert sim.rt.all_status(Status.START_UP_COMPLETE)
        return sim, made[-1]

    try:
        yield factory
    finally:
        for sim in sims:
            sim.close()


@pytest.fixture
def stub(make):
    return make()


def true_tool(sim) -> tuple[np.ndarray, np.ndarray]:
    """The simulated arm's true tool pose (its own kinematics, DH joint order)."""
    t = SIM_KIN.tool_pose(sim.world.sim.true_state().q[:6])
    return t[:3, 3].copy(), q_from_matrix(t)


DT = 1.0 / 80.0  # the Joint Planner period


def ca(sy: float, sp: float, ep: float, wp: float, wy: float, wr: float) -> np.ndarray:
    """Joint angles given in DH order and degrees, returned in command-area order, rad."""
    return (np.array([sy, sp, ep, wp, wy, wr], dtype=float) * D)[K.CA_FROM_DH]


def seconds(sim, s: float) -> int:
    return int(round(s / sim.period_s))


def run_recording_q_cmd(sim, n_frames: int) -> np.ndarray:
    """Step ``n_frames`` and return servo.q_cmd_rad after each frame."""
    out = np.empty((n_frames, 6))
    for k in range(n_frames):
        sim.step(1)
        out[k] = sim.rt.wm.get("servo.q_cmd_rad")
    return out


def assert_no_jump(q_cmd: np.ndarray, sim) -> None:
    """No joint command changes by more than its rate limit per 80 Hz run."""
    dt = sim.rt.task_period_s("joint_planner")
    steps = np.abs(np.diff(q_cmd, axis=0))
    assert np.all(steps <= K.RATE_LIMIT_RAD_S * dt + 1e-12), (steps / (K.RATE_LIMIT_RAD_S * dt)).max()


# --- tests ---------------------------------------------------------------------------------------

def test_measured_tool_pose_is_posted_and_matches_the_arm(stub):
    sim, _ = stub
    p = np.asarray(sim.rt.wm.get("joint.tool_pos_m"))
    q = np.asarray(sim.rt.wm.get("joint.tool_quat"))
    pt, qt = true_tool(sim)
    assert np.linalg.norm(p - pt) < 1e-3 and q_angle(q, qt) < 1e-3  # resolver quantisation
    assert sim.rt.wm.get("joint.mode") == JointPlannerLayer.MODE_JOINT
    assert sim.rt.wm.get("joint.shoulder_roll_rad") == 0.0


@pytest.mark.parametrize("servo,tol_m,tol_rad", [
    (None, 15e-3, 3.0 * D),        # nominal servo: measured 10.2 mm, 2.30 deg (static error)
    (LAG_SERVO, 2e-3, 0.5 * D),    # lag servo: measured 0.9 mm, 0.31 deg
])
def test_commanded_pose_is_reached_without_jumps(make, servo, tol_m, tol_rad):
    """The planner's command lands on the pose exactly (fk(servo.q_cmd_rad) to 1e-9); the
    simulated tool is off by the servo's static error: the nominal proportional joint loop
    (K = 8 1/s over the analog rate loop) needs a position error to make the holding
    torque, e.g. the wrist roll's 1 N*m Coulomb friction takes 39 mrad (2.3 deg) and the
    10 % uncompensated gravity a few mrad at the shoulder and elbow."""
    sim, cart = make(servo=servo)
    p0, q0 = true_tool(sim)
    target_p = p0 + np.array([0.10, -0.08, 0.08])
    target_q = q_mul(q_from_axis_angle([0.3, 1.0, -0.2], 15 * D), q0)
    cart.set(lambda t: (target_p, target_q))
    q_cmd = run_recording_q_cmd(sim, seconds(sim, 3.0))
    assert_no_jump(q_cmd, sim)
    assert sim.rt.wm.get("joint.mode") == JointPlannerLayer.MODE_CARTESIAN
    assert sim.rt.wm.get("joint.cart_err_m") < 1e-9 and sim.rt.wm.get("joint.cart_err_rad") < 1e-9
    pc, qc = K.fk(q_cmd[-1])
    assert np.linalg.norm(pc - target_p) < 1e-9 and q_angle(qc, target_q) < 1e-9
    p, q = true_tool(sim)
    pos_err, rot_err = float(np.linalg.norm(p - target_p)), q_angle(q, target_q)
    print(f"\nservo {servo or 'nominal'}: simulated tool vs commanded pose {pos_err * 1e3:.3f} mm, "
          f"{rot_err / D:.3f} deg")
    assert pos_err < tol_m and rot_err < tol_rad
    # the measured tool pose the planner posts agrees with the arm's true pose
    assert np.linalg.norm(np.asarray(sim.rt.wm.get("joint.tool_pos_m")) - p) < 1e-3
    assert not sim.rt.wm.get("joint.singular") and not sim.rt.wm.get("joint.limited")
    assert sim.rt.all_status(Status.START_UP_COMPLETE)


def test_a_moving_pose_through_the_wrist_singularity_is_followed_without_jumps(make):
    """A straight pose path (lerp + slerp over 3 s) from wrist yaw 80 deg to 100 deg with
    the wrist pitch and roll swinging: the closed-form branch flips half way (a ~180 deg
    step), the planner only turns the wrist at its rate limits and the arm ends on the pose."""
    qa = ca(0, 30, -80, -40, 80, 30)
    qb = ca(0, 30, -80, 40, 100, -30)
    sim, cart = make(q0=qa, servo=LAG_SERVO)
    pa, oa = K.fk(qa)
    pb, ob = K.fk(qb)

    def path(t):
        s = min(1.0, t / 3.0)
        return pa + (pb - pa) * s, q_slerp(oa, ob, s)

    cart.set(path)
    singular_seen = False
    q_cmd = np.empty((seconds(sim, 4.5), 6))
    for k in range(q_cmd.shape[0]):
        sim.step(1)
        q_cmd[k] = sim.rt.wm.get("servo.q_cmd_rad")
        singular_seen |= bool(sim.rt.wm.get("joint.singular"))
    assert_no_jump(q_cmd, sim)
    assert singular_seen
    assert any("singular" in m.text for m in sim.rt.messages.recent(1000, source="joint"))
    pc, oc = K.fk(q_cmd[-1])
    assert np.linalg.norm(pc - pb) < 1e-6 and q_angle(oc, ob) < 1e-6
    # the lag servo (2.5 s pole, saturating on the branch flip; anti-windup keeps its state at
    # the applied rate) is still settling 1.5 s after the path; 3 s after it the tool is on the pose
    sim.step(seconds(sim, 1.5))
    p, q = true_tool(sim)
    assert np.linalg.norm(p - pb) < 2e-3 and q_angle(q, ob) < 1.0 * D
    assert sim.rt.all_status(Status.START_UP_COMPLETE)


def test_blocked_at_a_soft_limit_on_the_wrong_wrist_branch_recovers_in_joint_space(make):
    """Where damped least squares can end: a path from wrist yaw -80 to -100 deg (wrist
    pitch 20 -> 60, roll 20 -> -20) carries the wrist round the singular set onto the
    flipped branch, where wrist pitch stops on its -105 deg soft limit 12 mm / 2.4 deg
    short (kinematics-level reproduction below). Started there with the pose commanded,
    the planner waits STUCK_S, then moves on a rate-limited joint-space line to the
    closed-form solution inside the limits and ends on the pose."""
    qa, qb = ca(0, 30, -90, 20, -80, 20), ca(0, 30, -90, 60, -100, -20)
    pa, oa = K.fk(qa)
    pb, ob = K.fk(qb)
    q = qa.copy()  # the kinematics alone: follow the path, end blocked on the limit
    for k in range(int(5 / DT)):
        s = min(1.0, (k + 1) * DT / 3.0)
        q = K.ik_step(q, pa + (pb - pa) * s, q_slerp(oa, ob, s), DT)
    assert q[K.JOINT_NAMES.index("wrist_pitch")] == pytest.approx(-105 * D)
    assert np.linalg.norm(K.fk(q)[0] - pb) > 5e-3
    sim, cart = make(q0=q)
    cart.set(lambda t: (pb, ob))
    q_cmd = run_recording_q_cmd(sim, seconds(sim, 6.0))
    assert_no_jump(q_cmd, sim)
    assert any("joint-space move" in m.text for m in sim.rt.messages.recent(1000, source="joint"))
    pc, oc = K.fk(q_cmd[-1])
    assert np.linalg.norm(pc - pb) < 1e-6 and q_angle(oc, ob) < 1e-6
    assert sim.rt.wm.get("joint.cart_err_m") < 1e-6


def test_unreachable_pose_stretches_toward_it_without_a_fault(stub):
    sim, cart = stub
    p0, q0 = true_tool(sim)
    far = p0 / np.linalg.norm(p0) * 2.6  # beyond the 2.1 m reach
    cart.set(lambda t: (far, q0))
    q_cmd = run_recording_q_cmd(sim, seconds(sim, 4.0))
    assert_no_jump(q_cmd, sim)
    assert sim.rt.all_status(Status.START_UP_COMPLETE)
    assert sim.rt.wm.get("joint.cart_err_m") > 0.4  # it cannot get there, and says so
    assert K.within_limits(sim.rt.wm.get("servo.q_cmd_rad"))
    assert np.linalg.norm(true_tool(sim)[0]) > 2.0


def test_soft_limits_hold_in_cartesian_mode(make):
    """A pose that needs the wrist yaw beyond +105 deg: the command stops at the soft limit."""
    jy = K.JOINT_NAMES.index("wrist_yaw")
    q = np.array([30, 0, -90, 0, 60, 0], dtype=float) * D
    q[jy] = 70 * D
    sim, cart = make(q0=q)
    q[jy] = 120 * D
    p, o = K.fk(q)
    cart.set(lambda t: (p, o))
    q_cmd = run_recording_q_cmd(sim, seconds(sim, 1.5))
    assert_no_jump(q_cmd, sim)
    assert np.all(q_cmd[:, jy] <= 105 * D + 1e-12) and q_cmd[-1, jy] == pytest.approx(105 * D, abs=1e-6)
    assert sim.rt.wm.get("joint.limited")
    assert any("soft limit" in m.text for m in sim.rt.messages.recent(1000, source="joint", min_level=Level.WARNING))


def test_joint_goal_wins_until_the_cartesian_pose_moves_and_invalid_commands_hold(stub):
    sim, cart = stub
    p0, q0 = true_tool(sim)
    cart.set(lambda t: (p0, q0))  # a Cartesian Engine holding the pose
    sim.step(seconds(sim, 0.2))
    assert sim.rt.wm.get("joint.mode") == JointPlannerLayer.MODE_CARTESIAN
    goal = np.asarray(sim.rt.wm.get("servo.q_cmd_rad"), dtype=float) + 0.05
    sim.rt.set_joint_goal(goal)
    sim.step(seconds(sim, 0.2))
    assert sim.rt.wm.get("joint.mode") == JointPlannerLayer.MODE_JOINT
    assert np.allclose(sim.rt.wm.get("servo.q_cmd_rad"), goal)
    # the Cartesian command moves: Cartesian mode resumes from the goal, no jump
    p1 = p0 + np.array([0.0, 0.0, 0.05])
    cart.set(lambda t: (p1, q0))
    q_cmd = run_recording_q_cmd(sim, seconds(sim, 1.5))
    assert np.abs(q_cmd[0] - goal).max() <= (K.RATE_LIMIT_RAD_S / 80).max()
    assert_no_jump(q_cmd, sim)
    assert sim.rt.wm.get("joint.mode") == JointPlannerLayer.MODE_CARTESIAN
    assert np.linalg.norm(K.fk(q_cmd[-1])[0] - p1) < 1e-6
    # not a pose: hold, an ERROR message, no fault
    held = np.asarray(sim.rt.wm.get("servo.q_cmd_rad")).copy()
    cart.set(lambda t: (p1, np.zeros(4)))
    sim.step(seconds(sim, 0.3))
    assert np.array_equal(sim.rt.wm.get("servo.q_cmd_rad"), held)
    assert sim.rt.all_status(Status.START_UP_COMPLETE)
    assert any("is not a pose" in m.text for m in sim.rt.messages.recent(1000, source="joint", min_level=Level.ERROR))
    # cart.cmd_valid false: joint-goal mode, holding the last command
    cart.set(lambda t: (p0, q0), valid=False)
    sim.step(seconds(sim, 0.3))
    assert sim.rt.wm.get("joint.mode") == JointPlannerLayer.MODE_JOINT
    assert np.array_equal(sim.rt.wm.get("servo.q_cmd_rad"), held)


def test_power_up_with_the_real_cartesian_engine_commands_no_motion():
    """The real stack: the Cartesian Engine holds the start-up pose, the Joint Planner
    follows it in Cartesian mode and commands (to 1e-6 rad) the start-up angles."""
    with SystemSimulator() as sim:
        sim.step(10)
        sim.power_up(400)
        q_start = np.asarray(sim.rt.wm.get("servo.q_cmd_rad")).copy()
        p0, _ = true_tool(sim)
        sim.step(seconds(sim, 1.0))
        assert sim.rt.all_status(Status.START_UP_COMPLETE)
        assert sim.rt.wm.get("joint.mode") == JointPlannerLayer.MODE_CARTESIAN
        assert np.abs(np.asarray(sim.rt.wm.get("servo.q_cmd_rad")) - q_start).max() < 1e-6
        assert sim.rt.wm.get("joint.cart_err_m") < 1e-6
        # the arm only settles into the servo's static error (gravity, friction): millimetres
        assert np.linalg.norm(true_tool(sim)[0] - p0) < 5e-3
        assert not sim.rt.messages.recent(1000, min_level=Level.ERROR)
