"""Gripper events in path files (controller/paths: kind "gripper", format version 2) and in the
playback plan; ``pfma path new|edit --gripper``. No controller: files and pure functions."""

from __future__ import annotations

import json

import pytest

from controller.paths import (
    FORMAT_VERSION, Path, PathError, PathStore, insert_gripper, make_point, plan_path, simplify,
)
from tools.cli import main

Q = (1.0, 0.0, 0.0, 0.0)


def _pts(xs):
    return [make_point((x, 0.0, 0.0), Q, "capture", t_s=round(i * 0.1, 6)) for i, x in enumerate(xs)]


def test_gripper_events_round_trip_as_version_2_and_keep_their_place(tmp_path):
    st = PathStore(tmp_path)
    p = st.new("pick", _pts([0.0, 0.01, 0.02, 0.03]))
    p = insert_gripper(p, 2, "close", 60.0)
    p = insert_gripper(p, len(p.points), "open")
    saved = st.save(p)
    doc = json.loads(st.file("pick").read_text())
    assert doc["version"] == FORMAT_VERSION == 2
    ev = [d for d in doc["points"] if d["kind"] == "gripper"]
    assert ev[0]["gripper"] == "close" and ev[0]["force_n"] == 60.0 and "force_n" not in ev[1]
    back = st.load("pick")
    assert back == saved
    assert [(q.kind, q.gripper, q.force_n) for q in back.points] == [
        ("capture", None, None), ("capture", None, None), ("gripper", "close", 60.0), ("capture", None, None),
        ("capture", None, None), ("gripper", "open", None)]
    # an event takes the pose of the point before it
    assert back.points[2].pos_m == back.points[1].pos_m and back.points[5].pos_m == back.points[4].pos_m
    assert "gripper close 60 N" in back.describe() and "gripper open" in back.describe()


@pytest.mark.parametrize("point, says", [
    ({"kind": "gripper"}, "a gripper event needs gripper = one of open, close, stop, not None"),
    ({"kind": "gripper", "gripper": "grab"}, "not 'grab'"),
    ({"kind": "gripper", "gripper": "force", "force_n": 50}, "not 'force'"),
    ({"kind": "gripper", "gripper": "close", "force_n": 900}, "grip force 900 N is outside 10..200 N"),
    ({"kind": "gripper", "gripper": "close", "force_n": "hard"}, "grip force 'hard' is not a number"),
    ({"kind": "teach", "gripper": "close"}, "gripper/force_n belong to a point of kind 'gripper', not 'teach'"),
])
def test_a_bad_gripper_event_in_a_file_is_refused_naming_the_point(tmp_path, point, says):
    doc = dict(Path("bad", 1, tuple(_pts([0.0]))).to_json(), version=2)
    doc["points"].append({"pos_m": [0, 0, 0], "quat": list(Q), **point})
    with pytest.raises(PathError, match="point 1: .*" + says.replace("(", r"\(").replace(")", r"\)")):
        Path.from_json(doc, "bad.json")


def test_an_older_reader_refuses_a_file_with_gripper_events_by_its_version():
    p = insert_gripper(Path("g", 1, tuple(_pts([0.0]))), 1, "close")
    assert p.to_json()["version"] == 2 and Path("n", 1, tuple(_pts([0.0]))).to_json()["version"] == 1
    with pytest.raises(PathError, match="format version 3 is newer than this program's 2"):
        Path.from_json(dict(p.to_json(), version=3), "future.json")


def test_a_version_1_file_with_a_gripper_event_is_refused_naming_the_point():
    doc = insert_gripper(Path("g", 1, tuple(_pts([0.0]))), 1, "close").to_json()
    with pytest.raises(PathError, match="point 1: a gripper event needs format version 2"):
        Path.from_json(dict(doc, version=1), "old.json")


def test_gripper_events_and_points_without_an_orientation_round_trip_together(tmp_path):
    # one version-bump rule (Path.needs_v2): either one makes a file version 2, both too
    st = PathStore(tmp_path)
    keep = make_point((0.02, 0.0, 0.0), None, "teach")
    p = insert_gripper(Path("mix", 0, tuple(_pts([0.0, 0.01])) + (keep,)), 3, "close", 50.0)
    assert p.points[3].quat is None  # the event takes the pose of the point before it, orientation kept too
    saved = st.save(st.new("mix", p.points))
    doc = json.loads(st.file("mix").read_text())
    assert doc["version"] == 2 and doc["points"][2]["quat"] is None and doc["points"][3]["gripper"] == "close"
    assert st.load("mix") == saved
    q = (0.0, 0.0, 0.0, 1.0)
    plan = plan_path(saved, start_quat=q)
    # resolved: the null orientations take point 1's (all points before have one); the event stays a key point
    assert [(s.index, s.gripper) for s in plan][-1] == (3, "close")
    assert all(tuple(s.quat) == Q for s in plan)
    only_null = Path("n", 1, tuple(_pts([0.0])) + (keep,))
    assert only_null.needs_v2 and not only_null.has_gripper and only_null.to_json()["version"] == 2


def test_the_plan_keeps_every_gripper_event_as_a_key_point_with_its_action():
    pts = _pts([0.0, 0.001, 0.002, 0.003, 0.004])  # a straight line: the captures in between go
    p = insert_gripper(Path("line", 1, tuple(pts)), 3, "close", 80.0)
    keys = simplify(p.points)
    assert keys == [0, 3, 5]
    plan = plan_path(p)
    assert [(s.index, s.gripper, s.force_n) for s in plan] == [(0, None, None), (3, "close", 80.0), (5, None, None)]
    assert plan[1].pos_m.tolist() == list(p.points[2].pos_m)  # it ends where the arm was


def test_insert_gripper_needs_a_point_and_a_known_action():
    with pytest.raises(PathError, match="needs a point to take its pose from"):
        insert_gripper(Path("e", 1), 0, "open")
    with pytest.raises(PathError, match="not 'wave'"):
        insert_gripper(Path("e", 1, tuple(_pts([0.0]))), 1, "wave")
    with pytest.raises(PathError, match="point 7 does not exist"):
        insert_gripper(Path("e", 1, tuple(_pts([0.0]))), 7, "open")


def _pfma(capsys, *argv):
    try:
        rc = main(list(argv))
    except SystemExit as e:
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def test_path_new_and_edit_put_gripper_events_where_they_are_given(tmp_path, capsys):
    d = str(tmp_path)
    rc, out, err = _pfma(capsys, "path", "--dir", d, "new", "pick", "--gripper", "open", "--point", "1.5,0,-0.3",
                         "--point", "1.5,0,-0.35", "--gripper", "close:60", "--gripper", "stop", "--point", "1.5,0,-0.3")
    assert (rc, err) == (0, "") and "6 points" in out
    p = PathStore(d).load("pick")
    assert [(q.kind, q.gripper, q.force_n) for q in p.points] == [
        ("gripper", "open", None), ("teach", None, None), ("teach", None, None), ("gripper", "close", 60.0),
        ("gripper", "stop", None), ("teach", None, None)]
    assert p.points[0].pos_m == p.points[1].pos_m and p.points[3].pos_m == p.points[2].pos_m
    rc, out, err = _pfma(capsys, "path", "--dir", d, "edit", "pick", "--gripper", "2", "close:30")
    assert rc == 0 and "7 points" in out
    p = PathStore(d).load("pick")
    assert (p.points[2].gripper, p.points[2].force_n, p.points[2].pos_m) == ("close", 30.0, p.points[1].pos_m)


@pytest.mark.parametrize("argv, says", [
    (("new", "x", "--point", "1,0,0", "--gripper", "grab"), "--gripper: 'grab': the action is one of open, close, stop"),
    (("new", "x", "--point", "1,0,0", "--gripper", "close:lots"), "the grip force 'lots' is not a number"),
    (("new", "x", "--point", "1,0,0", "--gripper", "close:900"), "grip force 900 N is outside 10..200 N"),
    (("new", "x", "--gripper", "open"), "--gripper: a gripper event needs a --point to take its pose from"),
])
def test_bad_gripper_events_on_the_command_line_are_one_line_and_exit_1(tmp_path, capsys, argv, says):
    rc, out, err = _pfma(capsys, "path", "--dir", str(tmp_path), *argv)
    assert rc == 1 and out == "" and "Traceback" not in err
    assert says in err and len(err.strip().splitlines()) == 1, err
    assert not PathStore(tmp_path).exists("x")
