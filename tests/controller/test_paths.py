"""Path files, edits, planning, and the Multi-Segment Path Planner recording and playing back
(with the small harness; the whole-system test is in test_path_playback_sim.py)."""

import json
import math
import os

import numpy as np
import pytest

from controller.paths import (
    DEFAULT_LIMITS, FORMAT_VERSION, MspMode, MspResult, Path, PathError, PathStore, delete_points, insert_point,
    make_point, move_point, plan_duration_s, plan_path, set_limits, set_speed, simplify,
)
from controller.quat import q_angle, q_from_axis_angle, q_slerp
from controller.trajectory import Limits

from ._motion_support import MiniRt

Q = (1.0, 0.0, 0.0, 0.0)


def _pts(xs, kind="capture"):
    return [make_point((x, 0.0, 0.0), Q, kind, t_s=i * 0.1) for i, x in enumerate(xs)]


# --- files -------------------------------------------------------------------------------


def test_store_round_trip_revisions_and_ids(tmp_path):
    st = PathStore(tmp_path / "paths")
    a = st.new("pick", _pts([0.0, 0.1, 0.2]), note="first")
    b = st.new("place", _pts([0.3]))
    assert (a.id, a.revision, b.id) == (1, 1, 2)
    back = st.load("pick")
    assert back == a and back.points[1].pos_m == (0.1, 0.0, 0.0)
    assert st.by_id(2).name == "place"
    assert [(i.name, i.id, i.points) for i in st.list()] == [("pick", 1, 3), ("place", 2, 1)]
    doc = json.loads((tmp_path / "paths" / "pick.json").read_text())
    # every point has an orientation and none is a gripper event: written as version 1, which older programs read
    assert doc["format"] == "pfma-path" and doc["version"] == 1 < FORMAT_VERSION and doc["revision"] == 1
    # edits saved bump the revision; no temporary files are left behind
    c = st.save(set_limits(back, v_lin_m_s=0.02))
    assert c.revision == 2 and st.load("pick").limits.v_lin_m_s == 0.02
    assert sorted(os.listdir(tmp_path / "paths")) == ["pick.json", "place.json"]
    # a stale copy (revision 1) is refused, naming the file
    with pytest.raises(PathError, match=r"pick.json: revision 2 on disk, this copy is revision 1"):
        st.save(back)
    with pytest.raises(PathError, match="already exists"):
        st.new("pick")
    r = st.rename("place", "place2")
    assert r.id == 2 and st.names() == ["pick", "place2"]
    st.delete("pick")
    with pytest.raises(PathError, match=r"no path 'pick' in .* \(paths: place2\)"):
        st.load("pick")
    assert st.next_id() == 3


def test_bad_files_are_refused_with_the_file_and_point_named(tmp_path):
    st = PathStore(tmp_path)
    st.new("ok", _pts([0.0, 0.1]))
    f = tmp_path / "ok.json"
    doc = json.loads(f.read_text())
    (tmp_path / "trunc.json").write_text(f.read_text()[:50])
    with pytest.raises(PathError, match=r"trunc.json: not valid JSON \(truncated or corrupt\?\)"):
        st.load("trunc")
    doc2 = dict(doc, name="newer", version=FORMAT_VERSION + 1)
    (tmp_path / "newer.json").write_text(json.dumps(doc2))
    with pytest.raises(PathError, match="newer than this program"):
        st.load("newer")
    doc3 = dict(doc, name="badq")
    doc3["points"] = [doc["points"][0], dict(doc["points"][1], quat=[1.0, 1.0, 0, 0])]
    (tmp_path / "badq.json").write_text(json.dumps(doc3))
    with pytest.raises(PathError, match=r"badq.json: point 1: quaternion .* not unit length"):
        st.load("badq")
    # list() keeps going; problems() says why
    assert [i.name for i in st.list()] == ["ok"]
    assert len(st.problems()) == 3
    dup = dict(doc, name="dup")
    (tmp_path / "dup.json").write_text(json.dumps(dup))
    with pytest.raises(PathError, match="share id 1"):
        st.by_id(1)
    with pytest.raises(PathError, match="not valid"):
        st.load("../etc")


def test_pure_edits(tmp_path):
    p = Path("e", 1, tuple(_pts([0.0, 0.1, 0.2, 0.3])))
    d = delete_points(p, [1, -1])
    assert [x.pos_m[0] for x in d.points] == [0.0, 0.2]
    i = insert_point(p, 1, (0.05, 0.01, 0.0))
    assert [x.pos_m[0] for x in i.points] == [0.0, 0.05, 0.1, 0.2, 0.3] and i.points[1].kind == "edit"
    assert i.points[1].quat is None  # no orientation given: it keeps the tool's
    m = move_point(p, 2, offset_m=(0.0, 0.0, 0.01))
    assert m.points[2].pos_m == (0.2, 0.0, 0.01)
    qz = q_from_axis_angle([0, 0, 1], 0.5)
    m2 = move_point(p, 0, quat=qz)
    assert q_angle(m2.points[0].quat, qz) < 1e-12
    s = set_speed(p, [3], v_lin_m_s=0.01)
    assert s.points[3].v_lin_m_s == 0.01 and s.points[2].v_lin_m_s is None
    assert set_speed(s, clear=True).points[3].v_lin_m_s is None
    assert p.points[3].v_lin_m_s is None  # the original is unchanged
    with pytest.raises(PathError, match="point 7 does not exist"):
        delete_points(p, [7])
    with pytest.raises(PathError, match="v_lin_m_s -1"):
        set_speed(p, [0], v_lin_m_s=-1)
    with pytest.raises(PathError, match="unknown limit"):
        set_limits(p, speed=1.0)


# --- planning ----------------------------------------------------------------------------


def test_simplify_keeps_teach_points_and_the_shape_within_tolerance():
    line = _pts(np.linspace(0, 0.3, 31))
    assert simplify(line) == [0, 30]
    line[10] = make_point(line[10].pos_m, Q, "teach")
    assert simplify(line) == [0, 10, 30]
    # a quarter circle of radius 0.2 m with a turning tool, captured every ~5 mm
    th = np.linspace(0, math.pi / 2, 64)
    circ = [make_point((1.2 + 0.2 * math.cos(a), 0.2 * math.sin(a), -0.3), q_from_axis_angle([0, 0, 1], a / 3))
            for a in th]
    keys = simplify(circ, 0.001, math.radians(1.0))
    assert 5 < len(keys) < 30
    for k0, k1 in zip(keys, keys[1:]):  # every captured point within tolerance of its chord
        a, b = np.array(circ[k0].pos_m), np.array(circ[k1].pos_m)
        for m in range(k0, k1 + 1):
            p = np.array(circ[m].pos_m)
            u = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
            assert np.linalg.norm(p - (a + u * (b - a))) <= 0.001 + 1e-12
            assert q_angle(circ[m].quat, q_slerp(circ[k0].quat, circ[k1].quat, u)) <= math.radians(1.0) + 1e-9


def test_plan_limits_overrides_scale_and_caps():
    pts = _pts([0.0, 0.1, 0.2])
    pts[1] = make_point(pts[1].pos_m, Q, "teach", v_lin_m_s=0.01)
    p = Path("s", 1, tuple(pts), Limits(0.05, 0.1, 0.1, 0.2))
    plan = plan_path(p)
    assert [s.index for s in plan] == [0, 1, 2]
    assert plan[1].limits.v_lin_m_s == 0.01 and plan[2].limits.v_lin_m_s == 0.05
    half = plan_path(p, speed_scale=0.5)
    assert half[2].limits.v_lin_m_s == 0.025 and half[2].limits.a_lin_m_s2 == 0.1
    fast = plan_path(p, speed_scale=10.0)
    assert fast[2].limits.v_lin_m_s == 0.15  # the Trajectory Planner's cap (pfma-model 8.2)
    assert plan_duration_s(p) == pytest.approx((0.01 / 0.1 + 0.1 / 0.01) + (0.05 / 0.1 + 0.1 / 0.05))
    with pytest.raises(PathError, match="no points"):
        plan_path(Path("z", 1))
    with pytest.raises(PathError, match="speed scale"):
        plan_path(p, speed_scale=0.0)


# --- the layer: record and play back (harness with a perfect Cartesian follower) ------------------


@pytest.fixture
def mini(tmp_path):
    m = MiniRt(PathStore(tmp_path))
    yield m
    m.close()


def _wave(t):
    """Scripted teleoperated tool motion: a 4 s arc in x-y with a turning tool, then rest."""
    u = min(max(t - 0.5, 0.0) / 4.0, 1.0)
    s = 0.5 - 0.5 * math.cos(math.pi * u)
    p = (1.5 - 0.15 * math.sin(math.pi * s), 0.2 * s, -0.3 + 0.05 * s * s)
    return p, q_from_axis_angle([0.0, 0.3, 1.0], 0.6 * s)


def _record(m, path_id=0, teach_at=(), t_end=5.5):
    m.script = _wave
    m.set("msp.path_id", path_id)
    m.set("msp.mode", MspMode.RECORD)
    for t in teach_at:
        m.run_until(lambda: m.now >= t, 5000)
        m.set("msp.teach", int(m.get("msp.teach")) + 1)
    m.run_until(lambda: m.now >= t_end, 5000)
    n = int(m.get("msp.finished"))
    m.set("msp.mode", MspMode.IDLE)
    m.run_until(lambda: int(m.get("msp.finished")) > n, 200)
    m.script = None
    return int(m.get("msp.result"))


def test_record_teach_points_and_continuous_capture_into_a_file(mini):
    m = mini
    m.msp.store.new("wave", note="to be recorded")
    assert _record(m, path_id=1, teach_at=(1.5, 3.0)) == MspResult.OK
    p = m.msp.store.load("wave")
    assert p.revision == 2 and p.note == "to be recorded"
    kinds = [x.kind for x in p.points]
    assert kinds.count("teach") == 2 and kinds[0] == "capture"
    # continuous capture: a point once the tool moved 5 mm or turned 2 degrees since the last
    # one, checked at 20 Hz: at most one 50 ms step of the motion further
    ts = np.arange(0.0, 6.0, 0.001)
    pw = np.array([_wave(t)[0] for t in ts])
    v_max = float((np.linalg.norm(np.diff(pw, axis=0), axis=1) / 0.001).max())
    pairs = [(a, b) for a, b in zip(p.points, p.points[1:]) if b.kind == "capture"]
    dist = [np.linalg.norm(np.subtract(b.pos_m, a.pos_m)) for a, b in pairs]
    turn = [q_angle(a.quat, b.quat) for a, b in pairs]
    assert all(d >= 0.005 - 1e-12 or w >= math.radians(2) - 1e-12 for d, w in zip(dist[:-1], turn[:-1]))
    assert max(dist) <= 0.005 + v_max * 0.05 + 1e-9
    assert len(p.points) > 40
    assert np.allclose(p.points[-1].pos_m, _wave(9.0)[0])  # the end pose is part of the path
    assert int(m.get("msp.points")) == len(p.points)


def test_record_without_a_path_id_makes_a_new_file(mini):
    m = mini
    m.msp.store.new("other")
    assert _record(m, path_id=0) == MspResult.OK
    assert m.msp.store.by_id(2).name == "path-2"


def _play(m, path_id, max_s=60.0):
    n = int(m.get("msp.finished"))
    m.set("msp.path_id", path_id)
    m.set("cart.mode" if False else "msp.mode", MspMode.PLAY)
    m.run_until(lambda: int(m.get("msp.finished")) > n, int(max_s / m.frames.period_s))
    m.set("msp.mode", MspMode.IDLE)
    m.step(16)
    return int(m.get("msp.result"))


def _active(samples):
    """The samples while traj.active, and the one after (the final pose is posted with
    traj.active false when the last segment releases the trajectory)."""
    i = [k for k, s in enumerate(samples) if s[3]]
    return samples[i[0]:i[-1] + 2]


def path_error(samples, path):
    """(max distance of a recorded point to the sampled trajectory polyline, max angle to
    the sampled orientation nearest it)."""
    P = np.array([s[1] for s in samples])
    Qs = [s[2] for s in samples]
    worst_d = worst_a = 0.0
    for pt in path.points:
        x = np.array(pt.pos_m)
        a, b = P[:-1], P[1:]
        d = b - a
        L2 = np.einsum("ij,ij->i", d, d)
        u = np.clip(np.einsum("ij,ij->i", x - a, d) / np.where(L2 > 0, L2, 1), 0, 1)
        dist = np.linalg.norm(a + u[:, None] * d - x, axis=1)
        k = int(np.argmin(dist))
        worst_d = max(worst_d, float(dist[k]))
        worst_a = max(worst_a, min(q_angle(pt.quat, Qs[k]), q_angle(pt.quat, Qs[k + 1])))
    return worst_d, worst_a


def test_recorded_path_played_back_at_the_trajectory_level(mini):
    m = mini
    assert _record(m, teach_at=(2.0,)) == MspResult.OK
    path = m.msp.store.by_id(1)
    m.step(80)
    # move away, so the playback starts with an approach segment from here
    m.cmd_p = m.cmd_p + [0.0, 0.0, 0.1]
    m.step(16)
    n0 = len(m.samples)
    assert _play(m, 1) == MspResult.OK
    play = _active(m.samples[n0:])
    assert np.allclose(play[0][1], np.add(_wave(9.0)[0], [0, 0, 0.1]), atol=1e-9)  # from where it was: no jump
    assert np.allclose(play[-1][1], path.points[-1].pos_m, atol=1e-9)
    d, a = path_error(play, path)
    # key-point tolerance 1 mm / 1 degree (PLAN_TOL_*) plus the 40 Hz sampling
    assert d <= 0.0011 and a <= math.radians(1.05)
    t = np.array([s[0] for s in play])
    p = np.array([s[1] for s in play])
    assert np.allclose(np.diff(t), 0.025)
    v = np.linalg.norm(np.diff(p, axis=0), axis=1) / 0.025
    acc = np.linalg.norm(np.diff(p, 2, axis=0), axis=1) / 0.025 ** 2
    lim = DEFAULT_LIMITS
    assert v.max() <= lim.v_lin_m_s * (1 + 1e-9) and acc.max() <= lim.a_lin_m_s2 * (1 + 1e-6)
    w = np.array([q_angle(play[i + 1][2], play[i][2]) for i in range(len(play) - 1)]) / 0.025
    assert w.max() <= lim.v_rot_rad_s * (1 + 1e-6)
    assert int(m.get("msp.segments")) == len(plan_path(path))


def test_playback_stopped_by_the_user_decelerates(mini):
    m = mini
    m.msp.store.new("long", [make_point(m.cmd_p + [0.4, 0, 0], Q, "teach")])
    n0 = len(m.samples)
    m.set("msp.path_id", 1)
    m.set("msp.mode", MspMode.PLAY)
    m.run_until(lambda: m.now >= 4.0, 5000)
    m.set("msp.mode", MspMode.IDLE)
    m.run_until(lambda: int(m.get("msp.state")) == MspMode.IDLE, 100)
    m.step(400)
    assert int(m.get("msp.result")) == MspResult.CANCELLED
    assert int(m.get("traj.done_code")) == 1 and not bool(m.get("traj.active"))
    p = np.array([s[1] for s in _active(m.samples[n0:])])
    acc = np.linalg.norm(np.diff(p, 2, axis=0), axis=1) / 0.025 ** 2
    assert acc.max() <= DEFAULT_LIMITS.a_lin_m_s2 * (1 + 1e-6)
    v = np.linalg.norm(np.diff(p, axis=0), axis=1) / 0.025
    assert v[-1] <= DEFAULT_LIMITS.a_lin_m_s2 * 0.025 + 1e-12  # came to rest at the limit
    assert np.allclose(m.get("traj.pos_m"), p[-1])
    # stopped short of the target: 0.05 m/s needs 12.5 mm at 0.1 m/s^2
    assert 0.1 < p[-1][0] - 1.5 < 0.3


def test_unknown_path_and_no_pose_are_reported(mini, tmp_path):
    m = mini
    assert _play(m, 42) == MspResult.NO_PATH
    assert any("no path with id 42" in x.text for x in m.messages.recent())
    m.wm.post_task_outputs("joint", {"joint.tool_quat": [0.0, 0, 0, 0]})
    m.script = lambda t: ([0.0, 0, 0], [0.0, 0, 0, 0])
    n = int(m.get("msp.finished"))
    m.set("msp.mode", MspMode.RECORD)
    m.run_until(lambda: int(m.get("msp.finished")) > n, 100)
    assert int(m.get("msp.result")) == MspResult.NO_POSE
