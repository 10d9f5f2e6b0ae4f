"""Path.from_json's refusals, word for word: operators read these texts when a path file
does not load (``pfma path``), so they are pinned here, one case per check, in the order
the checks run. Texts that quote another module (numpy's reshape error, the gripper's force
range) are pinned only up to that quotation."""

import pytest

from controller.paths import Path, PathError

GOOD_POINT = {"pos_m": [0.1, 0.2, 0.3], "quat": [1, 0, 0, 0], "kind": "capture", "t_s": 0.0}
DROP = object()  # doc(key=DROP): the document without that key


def doc(**changes):
    d = {"format": "pfma-path", "version": 2, "name": "pick", "id": 1, "points": [GOOD_POINT]}
    for k, v in changes.items():
        if v is DROP:
            d.pop(k)
        else:
            d[k] = v
    return d


def point(**changes):
    return doc(points=[{**GOOD_POINT, **changes}])


CASES = [
    ([1], "f.json: not a pfma-path document"),
    (doc(format="other"), "f.json: not a pfma-path document"),
    (doc(version=DROP), "f.json: bad format version None"),
    (doc(version=0), "f.json: bad format version 0"),
    (doc(version="2"), "f.json: bad format version '2'"),
    (doc(version=3), "f.json: format version 3 is newer than this program's 2"),
    (doc(name="bad name"), "f.json: path name 'bad name' is not valid (letters, digits, '_', '.', '-'; "
                           "starts with a letter or digit; at most 64 characters)"),
    (doc(id=True), "f.json: id True must be an integer 1 .. 2^31-1"),
    (doc(id=0), "f.json: id 0 must be an integer 1 .. 2^31-1"),
    (doc(id=2**31), "f.json: id 2147483648 must be an integer 1 .. 2^31-1"),
    (doc(limits=[1]), "f.json: limits must be an object"),
    (doc(limits={"v_lin_m_s": 0}), "f.json: limits: v_lin_m_s = 0.0 must be finite and > 0"),
    (doc(limits={"a_rot_rad_s2": "x"}), "f.json: limits: need v_lin_m_s, a_lin_m_s2, v_rot_rad_s, a_rot_rad_s2 "
                                         "(could not convert string to float: 'x')"),
    (doc(points={}), "f.json: points must be a list"),
    (doc(points=[GOOD_POINT, 3]), "f.json: point 1: not an object"),
    (doc(version=1, points=[{**GOOD_POINT, "quat": None}]),
     "f.json: point 0: no quat (a point without an orientation needs format version 2)"),
    (doc(version=1, points=[{**GOOD_POINT, "kind": "gripper", "gripper": "open"}]),
     "f.json: point 0: a gripper event needs format version 2"),
    (point(pos_m=[1, 2]), "f.json: point 0: position needs 3 numbers and quat 4 ("),
    (point(pos_m=[1, 2, float("nan")]), "f.json: point 0: position/quaternion not finite"),
    (point(quat=[1, 1, 0, 0]), "f.json: point 0: quaternion [1.0, 1.0, 0.0, 0.0] is not unit length (norm 1.414214)"),
    (point(kind="walk"), "f.json: point 0: kind 'walk' is not one of teach, capture, edit, gripper"),
    (point(v_rot_rad_s=0), "f.json: point 0: v_rot_rad_s 0 must be a number > 0 (or absent)"),
    (point(kind="gripper", gripper="force"),
     "f.json: point 0: a gripper event needs gripper = one of open, close, stop, not 'force'"),
    (point(kind="gripper", gripper="close", force_n="hard"), "f.json: point 0: grip force 'hard' is not a number"),
    (point(kind="gripper", gripper="close", force_n=True), "f.json: point 0: grip force True is not a number"),
    (point(kind="gripper", gripper="close", force_n=1e6), "f.json: point 0: grip force 1e+06 N is outside "),
    (point(gripper="open"), "f.json: point 0: gripper/force_n belong to a point of kind 'gripper', not 'capture'"),
    (doc(revision=-1), "f.json: revision -1 must be an integer >= 0"),
]


@pytest.mark.parametrize("d, text", CASES)
def test_from_json_refusal_texts(d, text):
    with pytest.raises(PathError) as info:
        Path.from_json(d, "f.json")
    msg = str(info.value)
    # a text ending in "(" or " " is pinned up to another module's quotation
    assert msg.startswith(text) if text.endswith(("(", " ")) else msg == text


def test_from_json_reads_a_good_document():
    p = Path.from_json(doc(revision=3, note="n"), "f.json")
    assert (p.name, p.id, p.revision, p.note, len(p.points)) == ("pick", 1, 3, "n", 1)
    assert p.points[0].pos_m == (0.1, 0.2, 0.3) and p.points[0].quat == (1.0, 0.0, 0.0, 0.0)
