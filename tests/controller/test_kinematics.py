"""controller.kinematics and controller.quat: the PFMA's fk, jacobian, closed-form ik, ik_step.

Figures checked here (pfma-model.md 8.1 "Checked numerically"), the cross-check against
the simulator's private forward kinematics (fakes.kinematics, used only in tests), the
round trip ik(fk(q)) = q over a dense random sample of the soft-limit box away from the
singular sets, and the no-jump behaviour of ik_step on pose paths through each singular
set (every joint step within its rate limit times the 80 Hz period).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller import kinematics as K
from controller.params import JOINT_NAMES
from controller.quat import (
    q_angle, q_conj, q_from_axis_angle, q_from_matrix, q_from_rotvec, q_mul, q_normalize, q_slerp,
    q_to_matrix, q_to_rotvec,
)
from fakes.kinematics import Kinematics as SimKinematics

D = math.pi / 180.0
DT = 1.0 / 80.0  # the Joint Planner period
ROLLS = (-90 * D, -45 * D, 0.0, 45 * D, 90 * D)  # shoulder-roll index positions (8.1)


def ca(sy: float, sp: float, ep: float, wp: float, wy: float, wr: float) -> np.ndarray:
    """Joint angles given in DH order and degrees, returned in command-area order, rad."""
    return (np.array([sy, sp, ep, wp, wy, wr], dtype=float) * D)[K.CA_FROM_DH]


def random_q(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform(K.SOFT_LO_RAD, K.SOFT_HI_RAD, size=(n, 6))


# --- quaternions -----------------------------------------------------------------------------

def test_quat_matrix_round_trip_and_product():
    rng = np.random.default_rng(1)
    for _ in range(200):
        a, b = q_normalize(rng.normal(size=4)), q_normalize(rng.normal(size=4))
        ra, rb = q_to_matrix(a), q_to_matrix(b)
        assert np.allclose(ra @ ra.T, np.eye(3), atol=1e-12) and np.linalg.det(ra) == pytest.approx(1.0)
        assert q_angle(q_from_matrix(ra), a) < 1e-9
        assert np.allclose(q_to_matrix(q_mul(a, b)), ra @ rb, atol=1e-12)
        assert np.allclose(q_mul(a, q_conj(a)), [1, 0, 0, 0], atol=1e-12)
    # 180 degree rotations (Shepperd branch choice)
    for axis in np.eye(3):
        q = q_from_axis_angle(axis, math.pi)
        assert q_angle(q_from_matrix(q_to_matrix(q)), q) < 1e-9


def test_quat_rotvec_and_slerp():
    q = q_from_axis_angle([0, 0, 2], 0.3)
    assert np.allclose(q_to_rotvec(q), [0, 0, 0.3])
    assert np.allclose(q_to_rotvec(-q), [0, 0, 0.3])  # short way round
    assert np.allclose(q_from_rotvec([0.1, -0.2, 0.3]), q_from_axis_angle([0.1, -0.2, 0.3], math.sqrt(0.14)))
    a, b = q_from_axis_angle([1, 0, 0], 0.2), q_from_axis_angle([1, 0, 0], 1.0)
    assert q_angle(q_slerp(a, b, 0.0), a) < 1e-12 and q_angle(q_slerp(a, b, 1.0), b) < 1e-9
    assert q_angle(q_slerp(a, -b, 0.5), q_from_axis_angle([1, 0, 0], 0.6)) < 1e-9
    with pytest.raises(ValueError):
        q_normalize([0, 0, 0, 0])


# --- forward kinematics -------------------------------------------------------------------------

def test_fk_reference_figures_of_the_model():
    """pfma-model.md 8.1 'Checked numerically'."""
    p, q = K.fk(np.zeros(6))
    assert np.allclose(p, [2.10, 0, 0], atol=1e-12)
    assert np.allclose(q_to_matrix(q)[:, 2], [1, 0, 0], atol=1e-12)  # approach z6 = +x0
    assert np.allclose(q_to_matrix(q)[:, 0], [0, 1, 0], atol=1e-12)  # tool x6 = +y0
    p, q = K.fk(ca(0, 30, -90, 60, 0, 0))  # q_ready
    assert np.allclose(p, [1.529, 0, -0.329], atol=5e-4)
    assert abs(q_to_matrix(q)[2, 2]) < 1e-12  # horizontal approach
    p, q = K.fk(ca(0, 60, -150, 0, 0, 0))  # q_stow
    assert np.allclose(p, [0.45, 0, -0.421], atol=5e-4)
    assert np.allclose(q_to_matrix(q)[:, 2], [0, 0, -1], atol=1e-12)  # approach down
    assert np.linalg.cond(K.jacobian(ca(0, 30, -60, 30, 0, 0))) == pytest.approx(7.4, abs=0.05)


def test_joint_order_is_the_command_area_order():
    assert JOINT_NAMES[0] == "shoulder_pitch" and JOINT_NAMES[1] == "shoulder_yaw"
    q = np.zeros(6)
    q[JOINT_NAMES.index("shoulder_yaw")] = 90 * D  # yaw left: tool goes to +y
    assert np.allclose(K.fk(q)[0], [0, 2.1, 0], atol=1e-12)
    q = np.zeros(6)
    q[JOINT_NAMES.index("shoulder_pitch")] = 90 * D  # pitch up: tool goes to +z
    assert np.allclose(K.fk(q)[0], [0, 0, 2.1], atol=1e-12)


@pytest.mark.parametrize("roll", ROLLS)
def test_fk_matches_the_simulated_arm(roll):
    """The controller's fk agrees with the simulator's private fk (true tool pose)."""
    sim = SimKinematics(shoulder_roll_rad=roll)
    rng = np.random.default_rng(7)
    worst = 0.0
    for q in random_q(rng, 300):
        t_sim = sim.tool_pose(q[K.DH_FROM_CA])  # the simulator runs in DH order
        p, quat = K.fk(q, shoulder_roll_rad=roll)
        worst = max(worst, float(np.max(np.abs(t_sim[:3, 3] - p))), q_angle(q_from_matrix(t_sim), quat))
        assert np.allclose(K.fk_frames(q, roll)[3][:3, 3], sim.frames(q[K.DH_FROM_CA])[3][:3, 3])
    assert worst < 1e-12


def test_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    h = 1e-6
    for q in random_q(rng, 50):
        for roll in (0.0, 45 * D):
            jm = K.jacobian(q, roll)
            p0, o0 = K.fk(q, roll)
            fd = np.empty((6, 6))
            for i in range(6):
                dq = np.zeros(6)
                dq[i] = h
                p1, o1 = K.fk(q + dq, roll)
                fd[:3, i] = (p1 - p0) / h
                fd[3:, i] = q_to_rotvec(q_mul(o1, q_conj(o0))) / h  # world-frame angular rate
            assert np.allclose(jm, fd, atol=2e-5), np.abs(jm - fd).max()


# --- closed-form inverse ------------------------------------------------------------------------

N_ROUND_TRIP = 4000


@pytest.mark.parametrize("roll", (0.0, 45 * D))
def test_inverse_of_forward_returns_q_across_the_workspace(roll):
    """Dense uniform sample of the soft-limit box, excluding configurations within 5 deg
    (wrist yaw of +-90, elbow of 0) or 0.05 m (wrist centre to shoulder-yaw axis) of a
    singular set (kinematics.SINGULAR_MARGIN_*). Max joint error found: ~1e-13 rad."""
    rng = np.random.default_rng(11)
    errs, used = [], 0
    for q in random_q(rng, N_ROUND_TRIP):
        if K.singular_sets(q):
            continue
        used += 1
        p, quat = K.fk(q, roll)
        q_back = K.ik(p, quat, q, shoulder_roll_rad=roll)
        errs.append(float(np.max(np.abs(q_back - q))))
    print(f"\nik(fk(q)) over {used} configurations (roll {roll / D:.0f} deg): max joint error {max(errs):.2e} rad")
    assert used > 0.7 * N_ROUND_TRIP
    assert max(errs) < 1e-9


def test_branch_choice_follows_q_ref():
    """Every solution inside the limits is found, and ik returns the one nearest q_ref."""
    # shoulder yaw 60 (the back branch -120 fits), shoulder pitch 90, elbow -5 (the other
    # elbow +5 fits), wrist pitch and yaw 80 (the flip -100 / 100 fits): all 8 branches
    q = ca(60, 90, -5, 80, 80, 10)
    p, quat = K.fk(q)
    sols = K.ik_all(p, quat, q)
    assert len(sols) == 8
    for s in sols:
        assert K.within_limits(s)
        ps, qs = K.fk(s)
        assert np.allclose(ps, p, atol=1e-12) and q_angle(qs, quat) < 1e-9
    for s in sols:  # each is chosen when the reference sits next to it
        assert np.allclose(K.ik(p, quat, s + 0.01), s, atol=1e-9)
    flipped = [s for s in sols if abs(s[J_WP] - q[J_WP]) > 3.0]
    assert flipped, "wrist-flip branch expected"
    assert np.allclose(K.ik(p, quat, q), q, atol=1e-9)


J_WP = JOINT_NAMES.index("wrist_pitch")
J_WY = JOINT_NAMES.index("wrist_yaw")
J_WR = JOINT_NAMES.index("wrist_roll")
J_SY = JOINT_NAMES.index("shoulder_yaw")
J_EP = JOINT_NAMES.index("elbow_pitch")


def test_ik_exactly_at_singular_sets_takes_the_free_angle_from_q_ref():
    # wrist yaw at -90 deg: only wrist pitch + wrist roll is defined; at +90 deg, pitch - roll
    for wy, sign in ((-90, -1), (90, +1)):
        q = ca(10, 30, -80, 20, wy, 30)
        p, quat = K.fk(q)
        ref = q.copy()
        ref[J_WP] += 10 * D
        s = K.ik(p, quat, ref)
        assert s[J_WP] == pytest.approx(ref[J_WP]) and s[J_WR] == pytest.approx(q[J_WR] + sign * 10 * D)
        ps, qs = K.fk(s)
        assert np.allclose(ps, p, atol=1e-12) and q_angle(qs, quat) < 1e-9
    # wrist centre on the shoulder-yaw axis: shoulder yaw keeps its reference value
    q = ca(25, 100, -20, 10, 20, 0)  # 0.9 cos(100) + 0.9 cos(80) = 0
    assert abs(K.wrist_centre(q)[0]) < 1e-12 and abs(K.wrist_centre(q)[1]) < 1e-12
    p, quat = K.fk(q)
    s = K.ik(p, quat, q)
    assert s[J_SY] == pytest.approx(q[J_SY]) and np.allclose(s, q, atol=1e-9)
    # full stretch: a single elbow solution
    q = ca(0, 20, 0, 10, 0, 0)
    p, quat = K.fk(q)
    assert np.allclose(K.ik(p, quat, q), q, atol=1e-6)


def test_unreachable_poses_raise_kinematics_error():
    quat = q_from_matrix(np.array([[0, 0, 1], [1, 0, 0], [0, 1, 0]], dtype=float))  # approach +x
    with pytest.raises(K.KinematicsError, match="out of reach"):
        K.ik([2.5, 0, 0], quat, np.zeros(6))
    with pytest.raises(K.KinematicsError, match="outside the joint limits.*elbow_pitch -180"):
        K.ik([0.3, 0, 0], quat, np.zeros(6))  # wrist centre on the shoulder: elbow folded back
    for qd, joint in [((0, 30, -80, 0, 0, 179), "wrist_roll"), ((0, -40, -80, 0, 0, 0), "shoulder_pitch"),
                      ((170, 30, -80, 0, 0, 0), "shoulder_yaw"), ((0, 30, -80, 0, 130, 0), "wrist_yaw")]:
        p, quat = K.fk(ca(*qd))
        with pytest.raises(K.KinematicsError, match=f"outside the joint limits.*{joint}"):
            K.ik(p, quat, ca(*qd))
        assert K.ik_all(p, quat) == []
    from pfma.errors import PfmaError
    assert issubclass(K.KinematicsError, PfmaError)


def test_within_limits_and_violations():
    assert K.within_limits(np.zeros(6))
    q = np.zeros(6)
    q[J_EP] = 6 * D
    assert not K.within_limits(q)
    assert K.limit_violations(q) == ["elbow_pitch +6.0 deg outside -145..+5"]
    assert K.within_limits(K.SOFT_HI_RAD) and K.within_limits(K.SOFT_LO_RAD)


def test_singular_sets_are_named():
    assert K.singular_sets(ca(0, 30, -80, 0, 88, 0)) == ("wrist",)
    assert K.singular_sets(ca(0, 30, -2, 0, 0, 0)) == ("stretch",)
    assert K.singular_sets(ca(0, 100, -20, 0, 0, 0)) == ("axis",)
    assert K.singular_sets(ca(0, 30, -80, 0, 0, 0)) == ()


# --- ik_step: rate-limited damped least squares ---------------------------------------------------

BUDGET = K.RATE_LIMIT_RAD_S * DT


def follow(qa: np.ndarray, qb: np.ndarray, duration_s: float, settle_s: float = 2.0):
    """Drive ik_step along the straight pose path fk(qa) -> fk(qb) (lerp + slerp) at 80 Hz.

    Returns (max step / budget, max position lag m, max orientation lag rad, final q,
    max joint step the closed-form ik nearest the previous solution would have taken).
    """
    pa, oa = K.fk(qa)
    pb, ob = K.fk(qb)
    n = int(round(duration_s / DT))
    q, ref = qa.copy(), qa.copy()
    worst_step = lag_p = lag_r = cf_jump = 0.0
    for k in range(n + int(settle_s / DT)):
        s = min(1.0, (k + 1) / n)
        p, o = pa + (pb - pa) * s, q_slerp(oa, ob, s)
        nxt = K.ik_step(q, p, o, DT)
        worst_step = max(worst_step, float(np.max(np.abs(nxt - q) / BUDGET)))
        assert K.within_limits(nxt)
        q = nxt
        pn, on = K.fk(q)
        lag_p, lag_r = max(lag_p, float(np.linalg.norm(pn - p))), max(lag_r, q_angle(on, o))
        c = K.ik(p, o, ref)
        cf_jump, ref = max(cf_jump, float(np.max(np.abs(c - ref) / BUDGET))), c
    return worst_step, lag_p, lag_r, q, cf_jump


def assert_settled(q: np.ndarray, qb: np.ndarray, pos_m: float, rot_rad: float) -> None:
    p, o = K.fk(q)
    pb, ob = K.fk(qb)
    assert np.linalg.norm(p - pb) < pos_m and q_angle(o, ob) < rot_rad


def test_ik_step_converges_and_never_exceeds_the_rate_limits():
    rng = np.random.default_rng(5)
    for _ in range(5):
        qa = rng.uniform(K.SOFT_LO_RAD * 0.6, K.SOFT_HI_RAD * 0.6)
        qb = np.clip(qa + rng.normal(0, 0.3, 6), K.SOFT_LO_RAD, K.SOFT_HI_RAD)
        if K.singular_sets(qa) or K.singular_sets(qb):
            continue
        pb, ob = K.fk(qb)
        q = qa.copy()
        for _ in range(int(6 / DT)):
            nxt = K.ik_step(q, pb, ob, DT)
            assert np.all(np.abs(nxt - q) <= BUDGET + 1e-12)
            q = nxt
        assert_settled(q, qb, 1e-9, 1e-9)


def test_path_through_the_wrist_singularity_has_no_jump():
    """Wrist yaw 80 -> 100 deg while wrist pitch and roll swing: the straight pose path
    passes next to wrist yaw = 90 deg. The closed-form ik would flip the wrist (a step
    of ~ 180 deg); ik_step stays within the rate limits, lags by a few cm / ~20 deg
    while the wrist turns at its rate limit, and reaches the pose exactly."""
    qa, qb = ca(0, 30, -80, -40, 80, 30), ca(0, 30, -80, 40, 100, -30)
    step, lag_p, lag_r, q, cf = follow(qa, qb, 4.0)
    assert step <= 1.0 + 1e-9
    assert cf > 10.0  # the closed form alone would have commanded a jump
    assert lag_p < 0.06 and lag_r < 30 * D
    assert_settled(q, qb, 1e-6, 1e-6)
    # straight through the singular set (only the wrist yaw moves): smooth, small lag
    step, lag_p, lag_r, q, _ = follow(ca(0, 30, -80, -40, 85, 30), ca(0, 30, -80, -40, 95, 30), 2.0)
    assert step <= 1.0 + 1e-9 and lag_p < 2e-3 and lag_r < 0.5 * D
    assert_settled(q, ca(0, 30, -80, -40, 95, 30), 1e-6, 1e-6)


def test_path_to_full_stretch_has_no_jump():
    qa, qb = ca(0, 10, -10, 0, 0, 0), ca(0, 10, 0, 0, 0, 0)
    step, lag_p, lag_r, q, _ = follow(qa, qb, 2.0)
    assert step <= 1.0 + 1e-9 and lag_p < 2e-3 and lag_r < 0.1 * D
    assert_settled(q, qb, 1e-4, 1e-4)  # damped at the singular point itself: 21 um left after 2 s


def test_path_past_the_shoulder_yaw_axis_has_no_jump():
    """The wrist centre passes 1.5 cm from the shoulder-yaw axis: the closed form swings
    the shoulder yaw through ~180 deg, ik_step turns it at its rate limit."""
    qa, qb = ca(-20, 100, -21, 10, 0, 0), ca(20, 100, -19, 10, 0, 0)
    step, lag_p, lag_r, q, cf = follow(qa, qb, 3.0)
    assert step <= 1.0 + 1e-9
    assert cf > 10.0
    assert lag_p < 0.02 and lag_r < 2 * D
    assert_settled(q, qb, 5e-3, 1e-2)  # 1.5 cm from the axis, inside the singular margin
    step, lag_p, lag_r, q, _ = follow(ca(-20, 100, -20, 10, 0, 0), ca(20, 100, -20, 10, 0, 0), 3.0)
    assert step <= 1.0 + 1e-9 and lag_p < 1e-6  # exactly on the axis: only the yaw turns


def test_unreachable_target_moves_toward_it_and_stops_at_full_stretch():
    q = ca(0, 10, -20, 0, 0, 0)
    p, o = K.fk(q)
    target = p * 1.3  # 2.7 m: beyond reach
    for _ in range(int(8 / DT)):
        nxt = K.ik_step(q, target, o, DT)
        assert np.all(np.abs(nxt - q) <= BUDGET + 1e-12) and K.within_limits(nxt)
        q = nxt
    assert np.linalg.norm(K.fk(q)[0]) > 2.09  # stretched out toward the target
    assert abs(q[J_EP]) < 3 * D


def test_ik_step_respects_the_soft_limits():
    """A pose that needs wrist yaw 120 deg: the arm goes to the 105 deg soft limit and stops."""
    qa, qt = ca(0, 30, -80, 0, 90, 0), ca(0, 30, -80, 0, 120, 0)
    p, o = K.fk(qt)
    q = qa.copy()
    limited = False
    for _ in range(int(4 / DT)):
        r = K.ik_step_ex(q, p, o, DT)
        assert K.within_limits(r.q_rad)
        limited |= r.limited
        q = r.q_rad
    assert limited and q[J_WY] == pytest.approx(105 * D, abs=1e-9)
    # a joint that starts outside the limits is not pulled in by a jump
    q = ca(0, -27, -80, 0, 0, 0)
    r = K.ik_step_ex(q, *K.fk(q), DT)
    assert np.allclose(r.q_rad, q)
    with pytest.raises(K.KinematicsError):
        K.ik_step(q, *K.fk(q), 0.0)
