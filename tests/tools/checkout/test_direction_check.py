"""`pfma checkout`'s joints group is the direction check the service asks for after a
change of sign (ioservice/direction.py): on a healthy arm it confirms every joint and the
record is written; with a flipped rate-command sign the service stops the wrong-way move
and the checkout fails naming the joint."""

from __future__ import annotations

import json

from ioservice import direction
from pfma.rack import DEFAULT_RACK, load_rack, parse_rack
from tools.checkout import FAIL, Checkout, SimTarget


def test_the_checkouts_joint_moves_confirm_every_joint(tmp_path, cfg):
    path = tmp_path / "d.json"
    t = SimTarget(load_rack(), direction_state=path)
    try:
        assert set(t.svc.direction.pending) == set(t.rack.joints)
        rep = Checkout(t, cfg, say=lambda _line: None, only=["joints"]).run()
        assert rep.passed, [r for r in rep.results if r.status == FAIL]
        assert t.svc.direction.pending == {}
        assert json.loads(path.read_text())["signs"] == direction.signature(t.svc.rack)
    finally:
        t.close()


def test_a_flipped_sign_fails_the_checkout_at_that_joint_with_the_services_reason(tmp_path, cfg):
    path = tmp_path / "d.json"
    rack = load_rack()
    path.write_text(json.dumps({"format": direction.FORMAT, "format_version": 1, "rack": rack.name,
                                "signs": direction.signature(rack)}))
    text = DEFAULT_RACK.read_text().replace("scale = 0.1, limit = 1.0, joint = \"wrist_yaw\"",
                                            "scale = -0.1, limit = 1.0, joint = \"wrist_yaw\"", 1)
    text += '\n[checks]\nallow_nonnominal = ["wrist_yaw_command.scale"]\n'
    t = SimTarget(parse_rack(text, "flipped.toml"), direction_state=path)
    try:
        assert list(t.svc.direction.pending) == ["wrist_yaw"]
        rep = Checkout(t, cfg, say=lambda _line: None, only=["joints"]).run()
        assert not rep.passed
        fails = rep.failures()
        assert fails[0].channel.startswith("wrist_yaw"), fails[0]
        said = [m.text for m in t.reader.messages()]
        # the checkout's "+" leg is 0.15 x 10 V x the (now negative) scale: the joint moves +
        assert any(s.startswith("direction check: wrist_yaw moved +0.01") and "-0.15 rad/s command: the loop is "
                   "inverted" in s for s in said), said[-5:]
        assert "wrist_yaw" in t.svc.direction.pending
    finally:
        t.close()
