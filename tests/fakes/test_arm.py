"""The simulated arm (fakes.arm): rate loop, brakes, gravity, friction, stops, F/T, determinism.

Simulated time only: each test integrates the model with fixed steps.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from fakes.arm import ArmModel
from fakes.arm_params import AXES, NOMINAL, N_AXES, SimErrors
from fakes.environment import Box, Environment, Wall
from fakes.kinematics import Kinematics

DT = 1.0 / 320.0
DEG = math.pi / 180.0
SY, SP, EP, WP, WY, WR, GR = range(7)
ZERO = np.zeros(N_AXES)
FULL = np.full(N_AXES, 10.0)


def run(arm: ArmModel, seconds: float, cmd=ZERO, ilim=FULL, dt: float = DT) -> None:
    for _ in range(round(seconds / dt)):
        arm.step(dt, cmd, ilim)


def cmd_on(axis: int, volts: float) -> np.ndarray:
    c = np.zeros(N_AXES)
    c[axis] = volts
    return c


def steady_rate(arm: ArmModel, axis: int, v_cmd: float, tau_ext: float = 0.0) -> float:
    """Rate-loop equilibrium with Coulomb + viscous friction: K_a k (V - K_w w) + tau_ext = F_c sgn w + b w."""
    kk = arm.k_a[axis] * arm.torque_per_amp[axis]
    drive = kk * v_cmd + tau_ext
    return math.copysign(max(abs(drive) - arm.coulomb[axis], 0.0), drive) / (kk * arm.k_w_true[axis]
                                                                              + arm.viscous[axis])


# -- parameters and kinematics ------------------------------------------------------------

def test_parameter_table_reproduces_the_model_numbers():
    assert [round(a.k_w, 6) for a in AXES[:6]] == [25, 25, 20, 10, 10, 5]
    assert [round(a.torque_max, 6) for a in AXES[:6]] == [192, 192, 144, 24, 24, 14.4]
    assert np.allclose(NOMINAL.k_a()[:6], [3.33, 3.33, 1.67, 0.50, 0.50, 0.22], atol=0.005)
    assert NOMINAL.tau_f_s == pytest.approx(0.0159, abs=1e-4)


@pytest.mark.parametrize("q_deg, tool_m, approach", [
    ((0, 0, 0, 0, 0, 0), (2.10, 0, 0), (1, 0, 0)),
    ((0, 30, -90, 60, 0, 0), (1.529, 0, -0.329), (1, 0, 0)),
    ((0, 60, -150, 0, 0, 0), (0.45, 0, -0.421), (0, 0, -1)),
])
def test_forward_kinematics_matches_the_reference_poses(q_deg, tool_m, approach):
    T = Kinematics().tool_pose(np.radians(q_deg))
    assert np.allclose(T[:3, 3], tool_m, atol=1e-3)
    assert np.allclose(T[:3, 2], approach, atol=1e-9)


def test_uncounterbalanced_gravity_at_full_stretch_is_468_nm():
    params = dataclasses.replace(NOMINAL, counterbalance_fraction=0.0)
    arm = ArmModel(params, q0=(0, 0, 0, 0, 0, 0, 0.05))
    tau = arm.gravity_torque_nm()
    assert tau[SP] == pytest.approx(-467.7, abs=0.5)  # gravity pulls the tip down (q2 < 0)
    assert ArmModel(q0=(0, 0, 0, 0, 0, 0, 0.05)).gravity_torque_nm()[SP] == pytest.approx(-46.77, abs=0.05)


@pytest.mark.parametrize("roll_deg", [0.0, 45.0, -90.0])
def test_gravity_torque_is_minus_the_gradient_of_the_potential(roll_deg):
    payload = 3.0
    arm = ArmModel(errors=SimErrors(payload_kg=payload), shoulder_roll_rad=roll_deg * DEG)
    kin, g = arm.kin, arm.params.gravity_m_s2
    cb = np.array([0.1, 0.1, 0.1, 0.1, 0.1, 1.0])  # J1-J5 (fakes.arm_params.SHOULDER_YAW_COUNTERBALANCED)

    def potential(q, scale_links):
        F = kin.frames(q)
        u_links = [m.mass_kg * g * (F[m.frame] @ np.array([*m.com_m, 1.0]))[2] for m in arm.params.link_masses]
        return scale_links * sum(u_links) + payload * g * F[6, 2, 3]

    rng = np.random.default_rng(7)
    for _ in range(3):
        q = np.append(rng.uniform(-1.0, 1.0, 6), 0.05)
        tau = arm.gravity_torque_nm(q)
        for i in range(6):
            dq = np.zeros(N_AXES)
            dq[i] = 1e-6
            du_links = (potential(q + dq, 1.0) - potential(q - dq, 1.0)) / 2e-6
            du_pay = (potential(q + dq, 0.0) - potential(q - dq, 0.0)) / 2e-6
            expected = -(du_links - du_pay) * cb[i] - du_pay
            assert tau[i] == pytest.approx(expected, abs=1e-4), (roll_deg, i)
        assert tau[GR] == 0.0


# -- brakes ----------------------------------------------------------------------------------

@pytest.mark.parametrize("ilim_v", [0.0, -5.0, 0.2])
def test_brakes_hold_against_gravity_with_zero_current_limit(ilim_v):
    arm = ArmModel(errors=SimErrors(payload_kg=5.0))
    q0 = arm.q.copy()
    run(arm, 2.0, cmd=np.full(N_AXES, 3.0), ilim=np.full(N_AXES, ilim_v))
    assert arm.brake_engaged[:6].all() and not arm.brake_engaged[GR]
    assert np.array_equal(arm.q[:6], q0[:6])
    assert not arm.qdot[:6].any()


def test_brake_release_has_hysteresis():
    arm = ArmModel()
    for v, engaged in [(0.4, True), (0.5, True), (0.51, False), (0.4, False), (0.3, False), (0.29, True)]:
        arm.step(DT, ZERO, np.full(N_AXES, v))
        assert arm.brake_engaged[:6].all() == engaged, v


def test_brake_slips_when_the_load_exceeds_its_slip_torque():
    weak = ArmModel(dataclasses.replace(NOMINAL, brake_slip_factor=0.05))  # 9.6 + 8 N*m < 34.8 N*m
    q0 = weak.q.copy()
    run(weak, 0.5, ilim=ZERO)
    assert weak.q[SP] < q0[SP] - 1e-3  # slid down under gravity
    assert weak.q[SY] == q0[SY]


# -- rate loop --------------------------------------------------------------------------------

def test_zero_command_with_current_holds_position_within_the_rate_loop_drift():
    arm = ArmModel()
    q0 = arm.q.copy()
    run(arm, 1.0)
    assert not arm.brake_engaged.any()
    # No gravity on SY, WY, WR, GR at this pose: they do not move at all.
    for axis in (SY, WY, WR, GR):
        assert arm.q[axis] == q0[axis]
    # The proportional rate loop lets the residual 10 % gravity through: a slow drift,
    # exactly the loop's equilibrium rate.
    tau_g = arm.gravity_torque_nm()[SP]
    assert arm.qdot[SP] == pytest.approx(steady_rate(arm, SP, 0.0, tau_g), rel=0.02)
    assert abs(arm.qdot[SP]) < 0.05 * AXES[SP].omega_fs
    assert abs(arm.q[SP] - q0[SP]) < 0.03


@pytest.mark.parametrize("axis, volts", [(SY, 5.0), (SY, -8.0), (WR, 5.0), (EP, 2.5), (GR, 4.0)])
def test_constant_rate_command_reaches_the_commanded_rate(axis, volts):
    arm = ArmModel(q0=(0, 30 * DEG, -60 * DEG, 30 * DEG, 0, 0, 0.05))
    arm.step(DT, cmd_on(axis, volts), FULL)
    # tach filter lag: while accelerating the filtered tach trails K_w * qdot
    run(arm, 0.02, cmd_on(axis, volts))
    assert abs(arm.tach_volts[axis]) < abs(arm.k_w[axis] * arm.qdot[axis])
    run(arm, 0.5, cmd_on(axis, volts))
    tau_g = arm.gravity_torque_nm()[axis]
    assert arm.qdot[axis] == pytest.approx(steady_rate(arm, axis, volts, tau_g), rel=0.01)
    assert arm.tach_volts[axis] == pytest.approx(arm.k_w[axis] * arm.qdot[axis], rel=1e-3)
    if axis == SY:  # heavy joint, no gravity: within a few percent of V / K_w
        assert arm.qdot[axis] == pytest.approx(volts / arm.k_w[axis], rel=0.05)
    others = [i for i in (SY, WY, WR, GR) if i != axis]
    assert not arm.qdot[others].any()


def test_tach_scale_error_changes_the_true_rate():
    arm = ArmModel(errors=SimErrors(tach_scale_error=(0.1, 0, 0, 0, 0, 0, 0)))
    run(arm, 0.6, cmd_on(SY, 5.0))
    assert arm.qdot[SY] == pytest.approx(steady_rate(arm, SY, 5.0), rel=0.01)
    assert arm.qdot[SY] < 0.95 * 5.0 / 25.0
    assert arm.tach_volts[SY] == pytest.approx(25.0 * 1.1 * arm.qdot[SY], rel=1e-3)


@pytest.mark.parametrize("position", [0.5, 2.0])
def test_the_gain_switch_scales_the_rate_loop_and_moves_its_droop(position):
    """IRSS 3.6.1: each rate servo card's gain switch; K_a scales with it, and with it the
    viscous droop of the wrist roll (b/J = 25 1/s against lambda = 40 1/s nominal)."""
    switched = dataclasses.replace(NOMINAL, gain_switch=tuple(position if i == WR else 1.0 for i in range(N_AXES)))
    arms = {g: ArmModel(params=p) for g, p in ((1.0, NOMINAL), (position, switched))}
    rates = {}
    for g, arm in arms.items():
        run(arm, 0.8, cmd_on(WR, 5.0))
        rates[g] = arm.qdot[WR]
        assert arm.qdot[WR] == pytest.approx(steady_rate(arm, WR, 5.0), rel=0.01)
    assert arms[position].k_a[WR] == pytest.approx(position * arms[1.0].k_a[WR])
    assert arms[position].k_a[SY] == arms[1.0].k_a[SY]  # the other cards keep theirs
    # pfma-model 8.4's steady rate (lambda' J u - F_c) / (lambda' J + b), lambda' = position x 40
    a, u = AXES[WR], 5.0 / AXES[WR].k_w
    for g in (1.0, position):
        lam_j = g * 40.0 * a.inertia
        assert rates[g] == pytest.approx((lam_j * u - a.coulomb) / (lam_j + a.viscous), rel=0.01)
    with pytest.raises(ValueError, match="gain_switch"):
        dataclasses.replace(NOMINAL, gain_switch=(1.5,) * N_AXES)


def test_current_saturates_at_the_current_limit():
    arm = ArmModel()
    ilim = np.full(N_AXES, 2.0)  # I_lim = 10 A * 2 V / 10 = 2 A on SY
    peak = 0.0
    for _ in range(round(0.3 / DT)):
        arm.step(DT, cmd_on(SY, 10.0), ilim)
        peak = max(peak, abs(arm.current_a[SY]))
    assert peak == pytest.approx(2.0, abs=1e-12)
    arm.step(DT, cmd_on(SY, 10.0), ilim)
    assert arm.current_monitor_volts[SY] == pytest.approx(10.0 * arm.current_a[SY] / 10.0)
    # with the limit the motor cannot follow: acceleration bounded by (k * 2 A - F_c) / J
    amax = (arm.torque_per_amp[SY] * 2.0 - 8.0) / 40.0
    assert arm.qdot[SY] <= amax * 0.3 * 1.001 + 1e-9


@pytest.mark.parametrize("axis, q_start, volts, limit", [
    (WR, 170 * DEG, 10.0, 180 * DEG),
    (EP, 0.0, 10.0, 10 * DEG),
    (WY, -100 * DEG, -10.0, -110 * DEG),
    (GR, 0.09, 10.0, 0.10),
])
def test_the_joint_stops_at_its_hard_limit(axis, q_start, volts, limit):
    q0 = list(NOMINAL.q_initial)
    q0[axis] = q_start
    arm = ArmModel(q0=q0)
    run(arm, 1.5, cmd_on(axis, volts))
    assert abs(arm.q[axis] - limit) < 0.005
    assert abs(arm.qdot[axis]) < 1e-3


def test_friction_sticks_without_chattering_at_small_steps():
    arm = ArmModel()
    run(arm, 0.3, cmd_on(WY, 4.0), dt=1e-4)
    assert arm.qdot[WY] > 0.2
    rates = []
    for _ in range(5000):
        arm.step(1e-4, ZERO, FULL)
        rates.append(arm.qdot[WY])
    rates = np.array(rates)
    sign_changes = np.count_nonzero(np.diff(np.sign(rates[rates != 0.0])))
    assert sign_changes <= 2
    assert rates[-1000:].tolist() == [0.0] * 1000  # stuck: exactly at rest


def test_step_rejects_bad_input():
    arm = ArmModel()
    with pytest.raises(ValueError, match="dt_s"):
        arm.step(-1.0, ZERO, FULL)
    with pytest.raises(ValueError, match="7 rate commands"):
        arm.step(DT, np.zeros(6), FULL)
    with pytest.raises(ValueError, match="q0"):
        ArmModel(q0=(0, 0, 0))
    t, q = arm.t_s, arm.q.copy()
    arm.step(0.0, ZERO, FULL)
    assert arm.t_s == t and np.array_equal(arm.q, q)


def test_same_inputs_give_an_identical_trajectory():
    def trajectory():
        arm = ArmModel(environment=Environment([Wall((0, 0.05, 0), (0, -1, 0))]))
        rng = np.random.default_rng(3)
        out = []
        for k in range(400):
            cmd = rng.uniform(-3, 3, N_AXES) if k % 40 == 0 else cmd
            arm.step(DT, cmd, FULL if k > 20 else ZERO)
            out.append(np.concatenate([arm.q, arm.qdot, arm.tach_volts, arm.current_a, arm.contact_force_n]))
        return np.array(out)

    assert np.array_equal(trajectory(), trajectory())


# -- F/T and contact ------------------------------------------------------------------------

def test_ft_reads_tool_gravity_at_rest():
    arm = ArmModel()  # ready pose: approach +x0, tool x6 = +y0, so y6 = +z0
    force, torque = arm.ft_load()
    w = 1.5 * 9.81
    assert np.allclose(force, (0.0, -w, 0.0), atol=1e-9)
    assert np.allclose(torque, (0.06 * w, 0.0, 0.0), atol=1e-9)
    loaded = ArmModel(errors=SimErrors(payload_kg=2.0))
    force2, torque2 = loaded.ft_load()
    assert np.allclose(force2, (0.0, -w - 2.0 * 9.81, 0.0), atol=1e-9)
    assert torque2[0] == pytest.approx(0.06 * w + 0.10 * 2.0 * 9.81)


def test_driving_into_a_wall_gives_a_contact_force():
    wall = Wall(point_m=(0.0, 0.05, 0.0), normal=(0.0, -1.0, 0.0))  # free space at y < 0.05
    arm = ArmModel(environment=Environment([wall]))
    ilim = cmd_on(SY, 3.0)  # SY: 3 A -> 57.6 N*m at most; the other joints braked
    run(arm, 3.0, cmd_on(SY, 2.5), ilim)
    tool = arm.tool_point_m()
    assert tool[1] > 0.05  # pressed into the wall
    assert abs(arm.qdot[SY]) < 1e-3
    fc = arm.contact_force_n
    lever = math.hypot(tool[0], tool[1])
    torque_motor = arm.torque_per_amp[SY] * arm.current_a[SY]
    assert fc[1] < 0 and abs(fc[0]) < 1e-9 and abs(fc[2]) < 1e-9
    assert abs(fc[1]) * lever == pytest.approx(torque_motor, abs=8.0 + 1e-6)  # within the Coulomb band
    assert (tool[1] - 0.05) * wall.stiffness_n_m == pytest.approx(-fc[1], rel=1e-3)
    force, torque = arm.ft_load()
    rot = arm.frames()[6, :3, :3]
    f_expected = rot.T @ fc + rot.T @ np.array([0, 0, -1.5 * 9.81])
    assert np.allclose(force, f_expected, atol=1e-6)
    assert abs(force[0]) > 30.0  # the wall force is along the tool x axis (+y0 at q1 = 0)
    assert np.allclose(torque, np.cross([0, 0, 0.10], rot.T @ fc) + np.cross([0, 0, 0.06], rot.T @ [0, 0, -14.715]),
                       atol=1e-6)


def test_environment_objects_push_and_never_pull():
    wall = Wall((0, 0, 0), (0, 0, 2.0))
    assert np.array_equal(wall.force_n(np.array([0, 0, 0.01]), np.zeros(3)), np.zeros(3))
    assert np.allclose(wall.force_n(np.array([0, 0, -0.001]), np.zeros(3)), (0, 0, 20.0))
    assert np.array_equal(wall.force_n(np.array([0, 0, -0.001]), np.array([0, 0, 1.0])), np.zeros(3))
    box = Box(centre_m=(1, 0, 0), half_size_m=(0.1, 0.2, 0.3), stiffness_n_m=1000.0)
    assert np.allclose(box.force_n(np.array([1.095, 0, 0]), np.zeros(3)), (5.0, 0, 0))
    assert np.allclose(box.force_n(np.array([1.0, -0.19, 0.0]), np.zeros(3)), (0, -10.0, 0))
    assert not box.force_n(np.array([1.2, 0, 0]), np.zeros(3)).any()
    assert box.clearance_m(np.array([1.4, 0.0, 0.0])) == pytest.approx(0.3)
    assert box.clearance_m(np.array([1.0, 0.1, 0.1])) == 0.0
    assert wall.clearance_m(np.array([0, 5.0, 0.25])) == pytest.approx(0.25)
    env = Environment()
    assert not env.active
    env.add(box)
    assert env.active and np.allclose(env.contact_force_n(np.array([1.095, 0, 0]), np.zeros(3)), (5.0, 0, 0))
    with pytest.raises(ValueError):
        Wall((0, 0, 0), (0, 0, 0))
    with pytest.raises(ValueError):
        Box((0, 0, 0), (0.1, 0, 0.1))
