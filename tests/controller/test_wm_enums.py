"""Enumerated world-model variables (issue 29 item 5): a state, status, mode or error code
declares its values (``VarSpec.enum``), every post and user write outside them is refused,
and the tools show it by name with the number beside it."""

from __future__ import annotations

import json
import struct
import uuid

import numpy as np
import pytest

from controller.daq_layer import FAULT_NAMES, DataAcquisitionLayer
from controller.decision import Command, Status
from controller.layers import ERR_PROCESS_STOPPING, ERR_SECTION_LOST, ERR_TASK_RAISED, Layer, TASK_NAMES
from controller.servo import ERR_LIMIT, ERR_MISSED, ERR_PARAMS, SUPERVISION_CODES, ServoLayer
from controller.worldmodel import VarSpec, WorldModel, WorldModelError, WorldModelValueError, coerce
from sim.faults import FaultSet
from sim.system import SystemSimulator
from tools.cli import main

MODES = {0: "HOLD", 1: "TELEOP", 2: "TRAJECTORY"}
CODES = {0: "none", 10: "soft limit", 12: "missed frames", 90: "a task raised"}  # with gaps


def _specs() -> list[VarSpec]:
    return [
        VarSpec("cart.mode", "command_input", "i2", (), "user", 0, doc="mode", enum=MODES),
        VarSpec("x.status", "status_output", "i2", (), "x", int(Status.SHUT_DOWN), enum=Status),
        VarSpec("x.error", "error_reports", "i4", (), "x", 0, enum=CODES),
        VarSpec("x.bits", "error_reports", "i4", (), "x", 0, flags={1: "resolver", 4: "F/T link"}),
        VarSpec("x.count", "task_status", "i4", (), "x", 0),
    ]


@pytest.fixture
def wm():
    m = WorldModel.create(_specs(), name=None, owner="test")
    yield m
    m.close()


def test_an_enumeration_is_declared_as_a_dict_an_intenum_members_or_pairs_and_stored_sorted():
    a = VarSpec("a", "status_output", "i2", (), "w", 0, enum={2: "TWO", 0: "ZERO"})
    assert a.enum == ((0, "ZERO"), (2, "TWO")) and a.enum_names == {0: "ZERO", 2: "TWO"}
    b = VarSpec("b", "status_output", "i2", (), "w", 0, enum=Command)
    assert b.enum_names[4] == "ERROR RESET"  # an IntEnum's "_" read as " "
    c = VarSpec("c", "status_output", "i2", (), "w", 0, enum=[Status.SHUT_DOWN, Status.ERROR])
    assert c.enum == ((0, "SHUT DOWN"), (7, "ERROR"))
    assert VarSpec.from_json(json.loads(json.dumps(c.to_json()))) == c  # kept in the segment's table
    old = {k: v for k, v in c.to_json().items() if k != "enum"}  # a table written before enum existed
    assert VarSpec.from_json(old).enum == ()


@pytest.mark.parametrize("kw,why", [
    (dict(dtype="f8", enum={0: "A"}), "needs an integer scalar"),
    (dict(dtype="i2", shape=(2,), initial=[0, 0], enum={0: "A"}), "needs an integer scalar"),
    (dict(enum={0: "A", 1: "A"}), "a name is given to two values"),
    (dict(enum=[(0, "A"), (0, "B")]), "value 0 named twice"),
    (dict(enum={0: ""}), "needs an integer value and a name"),
    (dict(enum={0: "A", 1 << 20: "BIG"}), "outside int16"),
    (dict(enum={0: "A"}, flags={1: "B"}), "not both"),
    (dict(initial=5, enum={0: "A", 1: "B"}), "initial value is not valid"),
])
def test_a_bad_enumeration_is_refused_when_the_variable_is_declared(kw, why):
    args = dict(name="v", area="status_output", dtype="i2", shape=(), writer="w", initial=0) | kw
    with pytest.raises(WorldModelError, match=why):
        VarSpec(**args)


def test_coerce_refuses_a_value_outside_the_enumeration_naming_the_values(wm):
    s = wm.spec("cart.mode")
    assert int(coerce(s, 2)) == 2
    with pytest.raises(WorldModelValueError, match=r"7 is not one of its values \(0 HOLD, 1 TELEOP, 2 TRAJECTORY\)"):
        coerce(s, 7)
    assert s.value_text(1) == "TELEOP (1)" and s.value_text(7) == "7 (unknown)"
    assert wm.spec("x.bits").value_text(5) == "resolver|F/T link (5)" and wm.spec("x.bits").value_text(0) == "none (0)"
    assert wm.spec("x.count").value_text(3) is None  # not enumerated: the caller shows the number


@pytest.mark.parametrize("name,good,bad", [("x.status", [0, 7, 9], [-1, 10, 300]),  # contiguous
                                           ("x.error", [0, 10, 12, 90], [1, 11, 89, 91])])  # with gaps
def test_every_post_outside_the_enumeration_is_refused_before_it_is_queued(wm, name, good, bad):
    for v in good:
        wm.post_state_variable("x", name, v)  # the fast path (struct, no numpy)
        wm.post_task_outputs("x", {name: np.int16(v)})  # the general path
    wm.communications_segment()
    assert int(wm.get(name)) == good[-1]
    for v in bad:
        with pytest.raises(WorldModelValueError, match="is not one of its values"):
            wm.post_state_variable("x", name, v)
        with pytest.raises(WorldModelValueError, match="is not one of its values"):
            wm.post_task_outputs("x", {name: v, "x.count": 1})  # all or nothing
        assert wm.pending == 0
    assert int(wm.get(name)) == good[-1]


def test_a_user_write_outside_the_enumeration_is_refused_now_and_when_applied(wm):
    key = wm.access_key
    with pytest.raises(WorldModelValueError, match="7 is not one of its values"):
        wm.set_user("cart.mode", 7, key)
    assert wm.requests() == []  # nothing queued
    rid = wm.set_user("cart.mode", 1, key)
    # a request written into the shared ring by another program, past the check: the owner
    # re-checks it when it applies the ring and rejects it, saying why
    forged = wm._submit(wm._index["cart.mode"], struct.pack("<h", 7), wm._key_hash(key), "forger")
    wm.communications_segment()
    assert wm.request(rid).state == "applied" and int(wm.get("cart.mode")) == 1
    r = wm.request(forged)
    assert r.state == "rejected" and "7 is not one of its values" in r.result


def test_every_error_code_a_layer_posts_is_in_its_enumeration():
    for cls in (Layer, ServoLayer, DataAcquisitionLayer):
        assert {0, ERR_TASK_RAISED, ERR_SECTION_LOST, ERR_PROCESS_STOPPING} <= set(cls.error_names), cls
    assert {ERR_LIMIT, ERR_PARAMS, ERR_MISSED, *SUPERVISION_CODES.values()} <= set(ServoLayer.error_names)
    assert set(FAULT_NAMES) <= set(DataAcquisitionLayer.error_names)  # daq.error: the lowest check bit
    assert TASK_NAMES[0] == "IDLE" and TASK_NAMES[42] == "SAFE DONE"


#: the controller's enumerated variables (the values are the layers' own tables)
ENUMERATED = {"updown.status": "ERROR", "servo.command": "ERROR RESET", "servo.error": "controller missed frames",
              "daq.error": "resolver", "joint.task": "INIT RUNNING",
              "ui.response": "CANCELLED", "cart.mode": "TELEOP", "cart.hc_source": "CRL", "cart.hc_frame": "TOOL",
              "force.frame": "TOOL", "force.state": "IMPEDANCE", "joint.mode": "CARTESIAN", "msp.mode": "PLAY",
              "msp.state": "RECORD", "msp.result": "NO PATH", "msp.record_source": "COMMAND",
              "traj.done_code": "STOPPED", "servo.trip_joint": "elbow_pitch",
              "servo.trip_cause": "tach reversed", "servo.brake_phase": "RELEASED", "daq.service_state": "ARMED",
              "gripper.state": "GRIPPING", "gripper.request": "CLOSE", "gripper.response": "REFUSED",
              "gripper.msp_done_code": "FAILED", "gripper.event": "OPEN", "msp.gripper_request": "STOP"}


@pytest.fixture
def named_sim():
    name = "pfma-test-enum-" + uuid.uuid4().hex[:6]
    sim = SystemSimulator(wm_name=name)
    try:
        sim.step(10)
        yield sim, name
    finally:
        sim.close()
        WorldModel.remove_segment(name)


def test_the_controllers_states_modes_and_codes_are_enumerated(named_sim):
    sim, _ = named_sim
    wm = sim.rt.wm
    for name, value_name in ENUMERATED.items():
        assert value_name in wm.spec(name).enum_names.values(), name
    assert wm.spec("daq.fault_bits").flag_names == FAULT_NAMES
    # every integer state variable of a layer (command, status, mailbox, error) is enumerated
    for s in wm.specs:
        if s.name.rsplit(".", 1)[-1] in ("command", "status", "task", "error") and s.is_state:
            assert s.enum, s.name


def pfma(capsys, *argv):
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def test_wm_list_and_get_show_names_with_the_numbers_and_json_keeps_the_numbers(named_sim, capsys):
    sim, name = named_sim
    sim.power_up(max_frames=400)
    FaultSet(sim.world).inject("resolver-los:shoulder_pitch_angle")
    sim.run_until(lambda: sim.rt.status("updown") == Status.ERROR, 200)
    rc, out, _ = pfma(capsys, "wm", "list", "--wm", name)
    lines = out.splitlines()
    assert rc == 0 and "powered up: yes (but " in lines[0] and " layers in ERROR)" in lines[0]
    value = {ln.split()[0]: ln for ln in lines}
    assert "ERROR (7)" in value["updown.status"] and "resolver (1)" in value["daq.error"]
    assert "resolver (1)" in value["daq.fault_bits"] and "HOLD (0)" in value["cart.mode"]
    rc, out, _ = pfma(capsys, "wm", "get", "msp.mode", "daq.fault_bits", "--wm", name)
    assert "  value      IDLE (0)" in out and "  values     0 IDLE, 1 RECORD, 2 PLAY (any other is refused)" in out
    assert "  bits       1 resolver, 2 tach ADC" in out
    rc, out, _ = pfma(capsys, "wm", "get", "updown.status", "daq.fault_bits", "--wm", name, "--json")
    v = json.loads(out)["variables"]
    assert v["updown.status"]["value"] == 7 and v["updown.status"]["value_name"] == "ERROR"
    assert v["updown.status"]["enum"]["5"] == "START UP COMPLETE"
    assert v["daq.fault_bits"]["value"] & 1 and "resolver" in v["daq.fault_bits"]["value_name"]


def test_wm_set_refuses_a_value_outside_the_enumeration_in_one_line_and_takes_a_name(named_sim, capsys):
    sim, name = named_sim
    key = sim.rt.wm.access_key
    rc, out, err = pfma(capsys, "wm", "set", "msp.mode", "7", "--key", key, "--wm", name, "--wait", "0")
    assert rc == 1 and out == "" and len(err.splitlines()) == 1 and "Traceback" not in err
    assert "7 is not one of its values (0 IDLE, 1 RECORD, 2 PLAY)" in err
    rc, out, err = pfma(capsys, "wm", "set", "msp.mode", "WALK", "--key", key, "--wm", name, "--wait", "0")
    assert rc == 1 and "'WALK' is not one of its values (0 IDLE, 1 RECORD, 2 PLAY)" in err
    assert sim.rt.wm.requests() == []  # nothing queued
    rc, out, err = pfma(capsys, "wm", "set", "cart.hc_source", "crl", "--key", key, "--wm", name, "--wait", "0")
    assert rc == 0 and "queued" in out
    sim.step(2)
    assert int(sim.rt.wm.get("cart.hc_source")) == 1
