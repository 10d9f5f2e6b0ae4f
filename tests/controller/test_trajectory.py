"""Trajectory Planner: the profile generator, segments, stops, and the layer in simulated time."""

import math

import numpy as np
import pytest

from controller.quat import q_angle, q_from_axis_angle, q_mul, q_slerp
from controller.trajectory import (
    DEFAULT_CAP, DoneCode, Limits, SegmentRun, plan_segment, plan_trapezoid,
)
from controller.paths import PathStore

from ._motion_support import MiniRt


def _sampled(prof, dt=1e-3):
    t = np.arange(0.0, prof.duration_s + 5 * dt, dt)
    return t, np.array([prof.sample(x) for x in t])


@pytest.mark.parametrize("d,v,a", [(1.0, 0.5, 1.0), (0.01, 0.5, 1.0), (0.3, 0.05, 0.1), (2.0, 0.15, 0.15)])
def test_trapezoid_reaches_the_distance_within_its_limits(d, v, a):
    prof = plan_trapezoid(d, v, a)
    t, x = _sampled(prof)
    assert x[-1, 0] == pytest.approx(d)
    assert x[0].tolist() == [0.0, 0.0, 0.0] and x[-1, 1] == 0.0
    assert np.all(np.diff(x[:, 0]) >= -1e-15)  # never backwards
    assert x[:, 1].max() <= v + 1e-12
    vel_fd = np.diff(x[:, 0]) / np.diff(t)
    acc_fd = np.diff(vel_fd) / np.diff(t)[1:]
    assert np.abs(acc_fd).max() <= a * (1 + 1e-6)
    # time-optimal: the trapezoid (or triangle) formula
    t_min = v / a + d / v if d >= v * v / a else 2.0 * math.sqrt(d / a)
    assert prof.duration_s == pytest.approx(t_min)


def test_trapezoid_refuses_bad_limits_and_handles_zero_distance():
    with pytest.raises(ValueError, match="v_max"):
        plan_trapezoid(1.0, 0.0, 1.0)
    with pytest.raises(ValueError, match="distance"):
        plan_trapezoid(-1.0, 1.0, 1.0)
    z = plan_trapezoid(0.0, 1.0, 1.0)
    assert z.duration_s == 0.0 and z.sample(0.5) == (0.0, 0.0, 0.0)


def _rates(seg, dt=1e-3):
    """Finite-difference linear/angular speed and acceleration along a segment's profile."""
    t = np.arange(0.0, seg.duration_s + 5 * dt, dt)
    poses = [seg.pose_at_s(seg.profile.sample(x)[0]) for x in t]
    p = np.array([a for a, _ in poses])
    v = np.linalg.norm(np.diff(p, axis=0), axis=1) / dt
    ang = np.array([q_angle(poses[i + 1][1], poses[i][1]) for i in range(len(poses) - 1)]) / dt
    acc = np.linalg.norm(np.diff(np.diff(p, axis=0), axis=0), axis=1) / dt ** 2
    return v, ang, acc


@pytest.mark.parametrize("dp,angle_deg", [((0.2, 0.0, 0.0), 0.0), ((0.0, 0.0, 0.0), 60.0),
                                          ((0.05, -0.02, 0.03), 90.0), ((0.4, 0.1, 0.0), 5.0)])
def test_segment_moves_position_and_orientation_together_within_both_limits(dp, angle_deg):
    p0 = np.array([1.5, 0.0, -0.3])
    q0 = q_from_axis_angle([0, 1, 0], 0.3)
    q1 = q_mul(q_from_axis_angle([1, 1, 0], math.radians(angle_deg)), q0)
    lim = Limits(0.1, 0.2, 0.3, 0.5)
    seg = plan_segment(p0, q0, p0 + dp, q1, lim)
    p, q = seg.pose_at_s(0.0)
    assert np.allclose(p, p0) and q_angle(q, q0) < 1e-9
    p, q = seg.pose_at_s(1.0)
    assert np.allclose(p, p0 + dp) and q_angle(q, q1) < 1e-9
    for s in (0.25, 0.5, 0.8):  # one parameter: the geodesic (slerp) with the same timing
        p, q = seg.pose_at_s(s)
        assert np.allclose(p, p0 + s * np.asarray(dp))
        assert q_angle(q, q_slerp(q0, q1, s)) < 1e-9
    v, w, acc = _rates(seg)
    assert v.max() <= lim.v_lin_m_s * (1 + 1e-6) and w.max() <= lim.v_rot_rad_s * (1 + 1e-6)
    assert acc.max() <= lim.a_lin_m_s2 * (1 + 1e-3)
    # the binding limit is reached (the plan is not needlessly slow)
    assert max(v.max() / lim.v_lin_m_s, w.max() / lim.v_rot_rad_s,
               seg.profile.a * max(seg.length_m / lim.a_lin_m_s2, seg.angle_rad / lim.a_rot_rad_s2)) \
        == pytest.approx(1.0, rel=0.02)


def test_segment_takes_the_short_way_round_and_refuses_bad_input():
    q0 = np.array([1.0, 0, 0, 0])
    q1 = -q_from_axis_angle([0, 0, 1], 0.2)  # same rotation as +q1, other sign
    seg = plan_segment([0, 0, 0], q0, [0, 0, 0], q1, DEFAULT_CAP)
    assert seg.angle_rad == pytest.approx(0.2)
    with pytest.raises(ValueError, match="finite"):
        plan_segment([0, 0, math.nan], q0, [0, 0, 0], q1, DEFAULT_CAP)
    with pytest.raises(ValueError, match="no direction"):
        plan_segment([0, 0, 0], [0, 0, 0, 0], [0, 0, 0], q1, DEFAULT_CAP)
    assert Limits(0.0, -1, math.inf, 0.1).clipped(DEFAULT_CAP) == Limits(
        DEFAULT_CAP.v_lin_m_s, DEFAULT_CAP.a_lin_m_s2, DEFAULT_CAP.v_rot_rad_s, 0.1)


def test_stop_decelerates_at_the_limit_and_ends_short_of_the_target():
    seg = plan_segment([0, 0, 0], [1, 0, 0, 0], [0.5, 0, 0], [1, 0, 0, 0], Limits(0.1, 0.2, 0.2, 0.2))
    run = SegmentRun(seg, t0_s=10.0, seq=1)
    run.request_stop(12.0)  # cruising at 0.1 m/s (0.2 s/unit-s)
    ts = np.arange(10.0, 14.0, 1e-3)
    out = np.array([run.sample(t)[:3] for t in ts])
    s = out[:, 0]
    assert np.all(np.diff(s) >= -1e-15)
    acc = np.diff(s, 2) / 1e-6 * seg.length_m
    assert np.abs(acc).max() <= 0.2 * (1 + 1e-3)
    assert run.sample(14.0)[3] and run.stopped
    # stopped 0.1^2 / (2 * 0.2) = 25 mm after the stop point, well before the end
    s_stop = seg.profile.sample(2.0)[0]
    assert s[-1] * seg.length_m == pytest.approx(s_stop * seg.length_m + 0.025, abs=1e-6)
    assert s[-1] < 1.0


# --- the layer (with a perfect Cartesian follower; tests/controller/_motion_support.py) ---------


@pytest.fixture
def mini(tmp_path):
    m = MiniRt(PathStore(tmp_path))
    yield m
    m.close()


def _segment(m, seq, p, q=(1.0, 0, 0, 0), lim=(0.1, 0.2, 0.2, 0.4), last=False, stop=False):
    m.wm.post_task_outputs("msp", {"msp.seg_seq": seq, "msp.seg_pos_m": p, "msp.seg_quat": q,
                                   "msp.seg_limits": lim, "msp.seg_last": last, "msp.seg_stop": stop})


def test_layer_runs_one_segment_from_the_cartesian_command_and_reports_it_done(mini):
    m = mini
    start = m.cmd_p.copy()
    target = start + [0.1, -0.05, 0.02]
    _segment(m, 1, target, last=True)
    m.run_until(lambda: int(m.get("traj.done_seq")) == 1, 2000)
    assert int(m.get("traj.done_code")) == DoneCode.REACHED
    assert np.allclose(m.get("traj.pos_m"), target)
    m.step(16)
    assert not bool(m.get("traj.active"))  # the last segment releases the trajectory
    act = [s for s in m.samples if s[3]]
    assert np.allclose(act[0][1], start, atol=1e-9)  # starts where the command was: no jump
    # traj.* samples at 40 Hz: speed and acceleration within the limits
    t = np.array([s[0] for s in act])
    p = np.array([s[1] for s in act])
    dt = np.diff(t)
    assert np.allclose(dt, 0.025)
    v = np.linalg.norm(np.diff(p, axis=0), axis=1) / dt
    a = np.linalg.norm(np.diff(p, 2, axis=0), axis=1) / 0.025 ** 2
    assert v.max() <= 0.1 * (1 + 1e-9)
    assert a.max() <= 0.2 * (1 + 1e-6)
    assert v.max() > 0.09  # it did reach (nearly) full speed


def test_layer_holds_between_segments_and_starts_the_next_from_the_held_pose(mini):
    m = mini
    a = m.cmd_p + [0.05, 0, 0]
    b = a + [0, 0.05, 0]
    _segment(m, 1, a)
    m.run_until(lambda: int(m.get("traj.done_seq")) == 1, 2000)
    m.step(40)
    assert bool(m.get("traj.active")) and np.allclose(m.get("traj.pos_m"), a)  # holding
    n = len(m.samples)
    _segment(m, 2, b, q=q_from_axis_angle([0, 0, 1], 0.3), last=True)
    m.run_until(lambda: int(m.get("traj.done_seq")) == 2, 2000)
    p = np.array([s[1] for s in m.samples[n:]])
    assert np.linalg.norm(np.diff(p, axis=0), axis=1).max() <= 0.1 * 0.025 + 1e-12
    assert q_angle(m.get("traj.quat"), q_from_axis_angle([0, 0, 1], 0.3)) < 1e-9


def test_layer_stop_request_decelerates_and_releases(mini):
    m = mini
    target = m.cmd_p + [0.5, 0, 0]
    _segment(m, 1, target, lim=(0.1, 0.2, 0.2, 0.2))
    m.step(int(2.5 / m.frames.period_s))
    m.wm.post_task_outputs("msp", {"msp.seg_stop": True})
    m.run_until(lambda: int(m.get("traj.done_seq")) == 1, 2000)
    assert int(m.get("traj.done_code")) == DoneCode.STOPPED
    m.step(8)
    assert not bool(m.get("traj.active"))
    p = np.array([s[1] for s in m.samples if s[3]])
    a = np.linalg.norm(np.diff(p, 2, axis=0), axis=1) / 0.025 ** 2
    assert a.max() <= 0.2 * (1 + 1e-6)
    assert np.linalg.norm(p[-1] - target) > 0.1


def test_layer_refuses_a_segment_without_a_start_pose(tmp_path):
    m = MiniRt(PathStore(tmp_path))
    try:
        m.wm.post_task_outputs("cartesian", {"cart.cmd_valid": False})
        m.wm.post_task_outputs("joint", {"joint.tool_quat": [0.0, 0, 0, 0]})
        m.script = lambda t: ([0.0, 0, 0], [0.0, 0, 0, 0])
        _segment(m, 5, [1.0, 0, 0])
        m.run_until(lambda: int(m.get("traj.done_seq")) == 5, 200)
        assert int(m.get("traj.done_code")) == DoneCode.REFUSED
        assert not bool(m.get("traj.active"))
        assert any("refused: no start pose" in x.text for x in m.messages.recent())
    finally:
        m.close()


def test_layer_caps_segment_limits(mini):
    m = mini
    m.wm.set_user("traj.v_lin_max_m_s", 0.02, m.key)
    m.step(1)
    _segment(m, 1, m.cmd_p + [0.1, 0, 0], lim=(1.0, 0.2, 1.0, 1.0), last=True)
    m.run_until(lambda: int(m.get("traj.done_seq")) == 1, 4000)
    p = np.array([s[1] for s in m.samples if s[3]])
    v = np.linalg.norm(np.diff(p, axis=0), axis=1) / 0.025
    assert v.max() <= 0.02 * (1 + 1e-9)
