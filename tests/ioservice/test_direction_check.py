"""The direction check after a change of polarity (issue 28 item 7, ``ioservice/direction.py``):
with a state file, a joint whose scale signs differ from the record may be armed only for a
small guarded move, one joint at a time, until the resolver and tach confirm it moved the
way it was commanded; a joint that moves the other way is stopped. Simulated time
(``SimRig``), the simulated arm moving under the service's DAC outputs."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bit3.layout import ServiceState
from ioservice import direction
from pfma.rack import DEFAULT_RACK, load_rack, parse_rack
from sim.rig import SimRig


class Ctl:
    """Writes the command area before every service frame: rates per joint, current limits
    per joint (0 = braked), an arm request with a number bumped by :meth:`rearm`."""

    def __init__(self, rig) -> None:
        self.rig = rig
        self.client = rig.controller()
        self.joints = list(rig.layout.joint_names)
        self.limit_joints = [rig.rack.channel(n).joint for n in rig.layout.current_limit_names]
        self.rates = dict.fromkeys(self.joints, 0.0)
        self.limits = dict.fromkeys(self.limit_joints, 0.0)
        self.arm, self.counter = 0, 0
        rig.on_frame.append(self)

    def rearm(self) -> None:
        self.arm, self.counter = 1, self.counter + 1

    def __call__(self, info) -> None:
        self.client.write_commands(joint_rate_rad_s=[self.rates[j] for j in self.joints],
                                   current_limit_a=[self.limits[j] for j in self.limit_joints],
                                   arm_request=self.arm, rearm_counter=self.counter)


def _state(rig):
    return ServiceState(rig.reader.read_inputs().service_state)


def _texts(rig, code=None):
    return [m.text for m in rig.reader.messages() if code is None or m.code == code]


def _move(rig, ctl, j: str, fraction: float = 0.2, seconds: float = 0.5) -> None:
    """Arm for joint ``j`` alone: its brake released at half its current limit, a rate of
    ``fraction`` of its rate limit for ``seconds``, then stop and disarm."""
    rack = rig.rack
    ctl.limits = dict.fromkeys(ctl.limit_joints, 0.0)
    ctl.limits[j] = 0.5 * rack.joint_channel(j, "current_limit").limit
    ctl.rates = dict.fromkeys(ctl.joints, 0.0)
    ctl.rearm()
    rig.run(0.05)
    ctl.rates[j] = fraction * rack.joint_channel(j, "rate_command").limit
    rig.run(seconds)
    ctl.rates[j] = 0.0
    ctl.limits[j] = 0.0
    ctl.arm = 0
    rig.run(0.05)


def test_without_a_record_every_joint_is_checked_one_at_a_time_and_then_recorded(tmp_path):
    path = tmp_path / "pfma.direction.json"
    rig = SimRig(prefix="pfma-dir-", service_kw={"direction_state": path})
    try:
        [start] = _texts(rig, direction.PENDING_CODE)
        assert start.startswith(f"direction check required before normal arming ({rig.rack.joints[0]}: no "
                                f"direction check recorded;")
        assert set(rig.svc.direction.pending) == set(rig.rack.joints)
        ctl = Ctl(rig)
        # a normal arm (every brake released) is refused while joints are pending
        ctl.limits = {j: 0.5 * rig.rack.joint_channel(j, "current_limit").limit for j in ctl.limit_joints
                      if j in rig.rack.joints} | {"gripper": 0.0}
        ctl.rearm()
        rig.run(0.05)
        assert _state(rig) == ServiceState.SAFE
        assert any(t.startswith("arm refused: direction check pending: one joint at a time") for t in _texts(rig))
        # too fast for a direction-check move
        ctl.limits = dict.fromkeys(ctl.limit_joints, 0.0)
        ctl.limits["elbow_pitch"] = 5.0
        ctl.rearm()
        rig.run(0.05)
        assert _state(rig) == ServiceState.ARMED
        ctl.rates["elbow_pitch"] = 0.4  # 0.8 x its 0.5 rad/s limit
        rig.run(0.02)
        assert _state(rig) == ServiceState.SAFE
        assert "direction check pending: elbow_pitch rate 0.4 beyond 0.3 x 0.5" in _texts(rig)
        ctl.rates["elbow_pitch"] = 0.0
        ctl.arm = 0
        rig.run(0.05)
        assert not path.exists()
        for j in rig.rack.joints:
            _move(rig, ctl, j)
            assert j not in rig.svc.direction.pending, (j, _texts(rig)[-4:])
        confirmed = _texts(rig, direction.CONFIRMED_CODE)
        assert [t.split()[2] for t in confirmed] == list(rig.rack.joints)
        assert _texts(rig, direction.DONE_CODE) == [f"direction check done: every joint moved as commanded; "
                                                   f"recorded in {path}"]
        assert json.loads(path.read_text())["signs"] == direction.signature(rig.rack)
        # now a normal arm with every brake released is obeyed
        ctl.limits = {j: 0.5 * rig.rack.joint_channel(j, "current_limit").limit for j in ctl.limit_joints}
        ctl.rearm()
        rig.run(0.05)
        assert _state(rig) == ServiceState.ARMED
    finally:
        rig.close()


def _record(path, rack) -> None:
    path.write_text(json.dumps({"format": direction.FORMAT, "format_version": 1, "rack": rack.name,
                                "signs": direction.signature(rack)}))


def test_a_record_that_matches_asks_nothing(tmp_path):
    path = tmp_path / "d.json"
    _record(path, load_rack())
    rig = SimRig(prefix="pfma-dir-", service_kw={"direction_state": path})
    try:
        assert rig.svc.direction.pending == {}
        assert _texts(rig, direction.PENDING_CODE) == []
    finally:
        rig.close()


@pytest.mark.parametrize("content", ["{not json", json.dumps({"format": "other"}), json.dumps([1, 2])])
def test_a_record_that_cannot_be_read_asks_for_every_joint(tmp_path, content):
    path = tmp_path / "d.json"
    path.write_text(content)
    rig = SimRig(prefix="pfma-dir-", service_kw={"direction_state": path})
    try:
        assert set(rig.svc.direction.pending) == set(rig.rack.joints)
        assert all("cannot be read" in w for w in rig.svc.direction.pending.values())
    finally:
        rig.close()


def test_a_flipped_rate_command_sign_is_pending_and_its_wrong_way_move_is_stopped(tmp_path):
    """The issue's runaway: the rack file says the elbow's rate command scale is negative
    (accepted by an override) while the arm is wired as before. The record holds the old
    signs, so only the elbow is pending; its first guarded move goes the wrong way and is
    stopped after about 0.01 rad instead of running away."""
    path = tmp_path / "d.json"
    _record(path, load_rack())
    text = DEFAULT_RACK.read_text().replace("scale = 0.05, limit = 0.5", "scale = -0.05, limit = 0.5", 1)
    text += '\n[checks]\nallow_nonnominal = ["elbow_pitch_command.scale"]\n'
    rack = parse_rack(text, "flipped.toml")
    rig = SimRig(rack, prefix="pfma-dir-", service_kw={"direction_state": path})
    try:
        assert rig.svc.direction.pending == {
            "elbow_pitch": "scale sign changed since the last direction check: rate_command + -> -"}
        ctl = Ctl(rig)
        rig.run(0.05)
        a0 = float(rig.reader.read_inputs().value("elbow_pitch_angle"))
        _move(rig, ctl, "elbow_pitch", fraction=0.2, seconds=1.0)
        [stop] = [t for t in _texts(rig) if t.startswith("direction check: elbow_pitch moved")]
        assert "for a +0.1 rad/s command: the loop is inverted" in stop
        travel = (float(rig.reader.read_inputs().value("elbow_pitch_angle")) - a0 + np.pi) % (2 * np.pi) - np.pi
        assert -0.03 < travel < 0  # it went the wrong way, and not far: 1 s at 0.1 rad/s would be 0.1 rad
        assert _state(rig) == ServiceState.SAFE
        assert np.all(np.asarray(rig.world.bus["dac"].output_volts_all(), dtype=float) == 0.0)
        assert "elbow_pitch" in rig.svc.direction.pending
        assert json.loads(path.read_text())["signs"]["elbow_pitch"]["rate_command"] == 1  # not recorded
    finally:
        rig.close()


def test_serve_keeps_the_record_beside_the_calibration():
    from tools.cli.serve import _direction_state

    class Args:
        calibration = "/lab/pfma-cal.json"
        direction_state = None
    assert _direction_state(Args()) == "/lab/pfma-cal.json.direction.json"
    Args.direction_state = "/lab/d.json"
    assert _direction_state(Args()) == "/lab/d.json"
    Args.calibration, Args.direction_state = None, None
    assert _direction_state(Args()) is None
