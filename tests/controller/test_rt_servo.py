"""Servo Control: Tustin lead/lag, the step-response prediction, and a joint position step
flown on the simulated arm compared with the prediction (simulated time)."""

import numpy as np
import pytest

from controller.params import JOINT_NAMES, joint, unwrap_angle
from drivers.rtd.registers import VMIVME4940
from controller.servo import LeadLag, predict_step
from sim.system import SystemSimulator


def test_tustin_coefficients_match_the_formulas():
    T, K, tz, tp = 1 / 160, 20.0, 0.05, 0.1
    c = LeadLag([K], [tz], [tp], T)
    assert c.a[0] == pytest.approx((2 * tp - T) / (2 * tp + T))
    assert c.b0[0] == pytest.approx(K * (2 * tz + T) / (2 * tp + T))
    assert c.b1[0] == pytest.approx(K * (T - 2 * tz) / (2 * tp + T))
    # DC gain K: a constant error settles at K e
    c.reset(0.0)
    for _ in range(4000):
        u = c.step(np.array([0.01]))
    assert u[0] == pytest.approx(K * 0.01, rel=1e-6)


def test_pure_gain_and_bad_designs():
    c = LeadLag([8.0, 8.0], [0.0, 0.0], [0.0, 0.0], 1 / 160)
    c.reset(0.0)
    assert np.allclose(c.step(np.array([0.1, -0.2])), [0.8, -1.6])
    with pytest.raises(ValueError, match="proper"):
        LeadLag([8.0], [0.1], [0.0], 1 / 160)
    with pytest.raises(ValueError, match="K must be > 0"):
        LeadLag([0.0], [0.0], [0.0], 1 / 160)


def test_unwrap_to_the_joint_range():
    ep = joint("elbow_pitch")
    assert unwrap_angle(np.radians(270.0), ep.centre_rad) == pytest.approx(np.radians(-90.0))
    assert unwrap_angle(np.radians(5.0), ep.centre_rad) == pytest.approx(np.radians(5.0))


def test_prediction_of_the_default_gain_has_no_overshoot():
    p = predict_step(joint("shoulder_yaw"), 0.02)
    assert p.overshoot_rad < 1e-6 and 0.2 < p.settle_s < 1.0


def fly_step(sim, name, step_rad, seconds=2.0):
    i = JOINT_NAMES.index(name)
    q0 = sim.joint_angles_rad()[i]
    goal = np.array(sim.rt.wm.get("daq.joint_angle_rad"))
    goal[i] += step_rad
    sim.rt.set_joint_goal(goal)
    sim.run_until(lambda: np.isclose(sim.rt.wm.get("servo.q_cmd_rad")[i], goal[i]), 20)
    out = []
    for _ in range(int(seconds / sim.period_s)):
        sim.step(1)
        out.append(sim.joint_angles_rad()[i] - q0)
    return np.array(out)


@pytest.mark.parametrize("kp,tau_z,tau_p,step", [
    (8.0, 0.0, 0.0, 0.02),     # the nominal design (pfma-model 8.4): no overshoot predicted
    (16.0, 0.0, 0.06, 0.01),   # a lag-filtered high gain: about 33 % overshoot predicted
    (20.0, 0.05, 0.1, 0.01),   # lead/lag
])
def test_joint_position_step_overshoots_no_more_than_the_design_predicts(kp, tau_z, tau_p, step):
    name = "shoulder_yaw"  # a vertical axis: no gravity, the biggest inertia
    with SystemSimulator() as sim:
        key = sim.rt.wm.access_key
        sim.rt.wm.set_user("servo.kp_per_s", [kp] * 6, key)
        sim.rt.wm.set_user("servo.tau_z_s", [tau_z] * 6, key)
        sim.rt.wm.set_user("servo.tau_p_s", [tau_p] * 6, key)
        sim.step(10)
        sim.power_up(400)
        sim.step(60)
        q = fly_step(sim, name, step)
    pred = predict_step(joint(name), step, kp=kp, tau_z=tau_z, tau_p=tau_p,
                        servo_period_s=2 * sim.period_s, delay_s=2 * sim.period_s)
    overshoot = max(0.0, float(np.max(q - step)))
    # resolver quantisation, both ends of the loop: 3/4 of one 14-bit LSB (the figure this test
    # has always used, once written as 3 x 2 pi / 65536)
    tol = 0.75 * VMIVME4940.constants["lsb_rad"]
    assert overshoot <= pred.overshoot_rad + tol, (overshoot, pred.overshoot_rad)
    if pred.overshoot_rad > 10 * tol:  # the prediction is not just an upper bound by accident
        assert overshoot >= 0.6 * pred.overshoot_rad
    # it got there: within the Coulomb-friction dead band of this joint (8 N*m / (lambda J K))
    dead_band = 8.0 / (40.0 * joint(name).inertia_kg_m2 * kp)
    assert abs(q[-1] - step) <= dead_band + tol
