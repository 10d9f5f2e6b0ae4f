"""World model (controller/worldmodel/): IRSS rules 3 and 4, the queued posts and the
communications segment, keyed user writes, shared memory read from other processes.

Children are spawned processes; the parent waits on events/pipes with time-outs, never
on sleeps. The torn-read fuzz is a correctness test (zero torn frames), not a timing test.
"""

import json
import os
import re

import numpy as np
import pytest

from controller.worldmodel import (
    AREAS, DEFAULT_ACCESS_KEY, REQUEST_SLOTS, VarSpec, WorldModel, WorldModelError,
    WorldModelValueError, list_segments,
)
from tests.controller import _wm_support as sup


@pytest.fixture
def wm_name():
    name = sup.unique_name()
    yield name
    WorldModel.remove_segment(name)


@pytest.fixture(params=["private", "shm"])
def wm(request, wm_name):
    m = WorldModel.create(sup.sample_specs(), name=None if request.param == "private" else wm_name)
    yield m
    m.close()


@pytest.fixture(scope="module")
def mp():
    import multiprocessing
    return multiprocessing.get_context("spawn")


# --- specs and initial validity ----------------------------------------------------------


def test_every_variable_holds_its_valid_initial_value_after_create(wm):
    assert wm.frame == 0 and not wm.powered_up
    assert {s.area for s in wm.specs} == set(AREAS)  # the sample uses all seven areas
    for s in sup.sample_specs():
        v = wm.get(s.name)
        assert np.asarray(v).dtype == np.dtype(s.dtype), s.name
        assert np.asarray(v).shape == s.shape, s.name
        np.testing.assert_array_equal(v, np.asarray(s.initial, dtype=s.dtype))
    assert wm.get("servo.q_rad")[5] == 0.5
    np.testing.assert_array_equal(wm.get("tool.T_base"), np.eye(4, dtype="f4"))
    assert isinstance(wm.get("updown.status"), np.int16)


def test_specs_are_grouped_by_area_and_normalised():
    s = VarSpec("x", "task_io", "float64", [3], "t", np.zeros(3))
    assert s.dtype == "f8" and s.shape == (3,) and s.initial == (0.0, 0.0, 0.0)
    assert s.type_text == "f8[3]" and s.nbytes == 24
    assert VarSpec.from_json(s.to_json()) == s
    m = WorldModel.create(sup.sample_specs())
    areas = [AREAS.index(x.area) for x in m.specs]
    assert areas == sorted(areas)


@pytest.mark.parametrize("kwargs, text", [
    (dict(area="somewhere"), "area 'somewhere'"),
    (dict(dtype="U8"), "not a plain number"),
    (dict(dtype="f9"), "not a numpy dtype"),
    (dict(shape=(0,), initial=[]), "positive"),
    (dict(writer=""), "exactly one writer"),
    (dict(initial=[1.0, 2.0]), "rule 4"),
    (dict(initial=float("nan")), "not finite"),
    (dict(name="bad name"), "bad name"),
])
def test_invalid_specs_are_refused_with_the_variable_named(kwargs, text):
    base = dict(name="v", area="task_io", dtype="f8", shape=(), writer="t", initial=0.0)
    base.update(kwargs)
    with pytest.raises(WorldModelError, match=text) as err:
        VarSpec(**base)
    assert repr(base["name"]) in str(err.value)


def test_duplicate_names_are_refused():
    a = VarSpec("v", "task_io", "f8", (), "t1", 0.0)
    b = VarSpec("v", "task_status", "f8", (), "t2", 0.0)
    with pytest.raises(WorldModelError, match="defined twice.*'t1'.*'t2'"):
        WorldModel.create([a, b])


# --- one writer, value checks -------------------------------------------------------------


def test_only_the_one_writer_may_post_and_the_error_names_the_owner(wm):
    with pytest.raises(WorldModelError, match="written only by 'servo'.*'trajectory'"):
        wm.post_task_outputs("trajectory", {"servo.q_rad": [1.0] * 6})
    # all-or-nothing: one bad entry, nothing queued
    with pytest.raises(WorldModelError, match="written only by 'servo'"):
        wm.post_task_outputs("trajectory", {"servo.q_cmd_rad": [1.0] * 6, "servo.q_rad": [1.0] * 6})
    assert wm.pending == 0
    assert wm.communications_segment() == 0
    np.testing.assert_array_equal(wm.get("servo.q_cmd_rad"), np.zeros(6))
    assert wm.variables_of("servo") == ("servo.q_rad", "servo.integrator", "servo.frames",
                                        "servo.error_code")
    assert wm.variables_of("user") == ("servo.kp_1_s", "hc.enable")


@pytest.mark.parametrize("name, value, text", [
    ("servo.q_rad", [1.0] * 5, r"shape \(5,\) given, shape \(6,\) expected"),
    ("servo.q_rad", 1.0, "a scalar given"),
    ("servo.q_rad", [0, 0, 0, float("inf"), 0, 0], "not finite"),
    ("servo.q_rad", ["a"] * 6, "not a number"),
    ("servo.frames", -1, "outside uint32 range"),
    ("servo.error_code", 2.5, "float given for an integer"),
    ("servo.error_code", True, "boolean given"),
    ("tool.T_base", np.full((4, 4), 1e39), "not finite as float32"),
])
def test_bad_values_are_refused_and_the_model_is_unchanged(wm, name, value, text):
    writer = wm.spec(name).writer
    with pytest.raises(WorldModelValueError, match=text) as err:
        wm.post_task_outputs(writer, {name: value})
    assert isinstance(err.value, ValueError) and name in str(err.value)
    wm.communications_segment()
    np.testing.assert_array_equal(wm.get(name), np.asarray(wm.spec(name).initial, wm.spec(name).dtype))


def test_unknown_variables_are_named_with_close_matches(wm):
    with pytest.raises(WorldModelError, match="no variable 'servo.q_ra'.*did you mean servo.q_rad"):
        wm.get("servo.q_ra")
    with pytest.raises(WorldModelError, match="no variable 'nope'"):
        wm.get_task_inputs(["servo.q_rad", "nope"])


# --- queued posts and the communications segment -------------------------------------------


def test_posts_are_invisible_until_the_communications_segment(wm):
    other = WorldModel.attach(wm.name) if wm.name else None
    try:
        wm.post_task_outputs("servo", {"servo.q_rad": [1.0] * 6, "servo.frames": 7})
        wm.post_state_variable("updown", "updown.status", 3)
        assert wm.pending == 3
        np.testing.assert_array_equal(wm.get("servo.q_rad"), [0.0, 0.1, 0.2, 0.3, 0.4, 0.5])
        assert wm.get_state_variable("updown.status") == 0
        if other:
            assert other.get("servo.frames") == 0 and other.frame == 0
        # fresh data replaces old: the later post of the same variable wins
        wm.post_task_outputs("servo", {"servo.q_rad": [2.0] * 6})
        assert wm.communications_segment() == 3
        assert wm.pending == 0 and wm.frame == 1
        got = wm.get_task_inputs(["servo.q_rad", "servo.frames", "updown.status"])
        np.testing.assert_array_equal(got["servo.q_rad"], [2.0] * 6)
        assert got["servo.frames"] == 7 and got["updown.status"] == 3
        if other:
            assert other.get_state_variable("updown.status") == 3 and other.frame == 1
        assert wm.communications_segment() == 0 and wm.frame == 2  # an empty segment still counts
        assert wm.stats()["posts_applied"] == 3
    finally:
        if other:
            other.close()


def test_returned_values_are_copies(wm):
    a = wm.get("servo.q_rad")
    a[:] = 99.0
    assert wm.get("servo.q_rad")[0] == 0.0
    v = np.ones(6)
    wm.post_task_outputs("servo", {"servo.q_rad": v})
    v[:] = 5.0  # changing the caller's array after posting changes nothing
    wm.communications_segment()
    np.testing.assert_array_equal(wm.get("servo.q_rad"), np.ones(6))


def test_a_post_made_while_a_segment_flushes_goes_to_the_next_one(wm):
    """IRSS COMM-INTERRUPT / IN-COMM-FRAME: simulate a task posting in the middle of a flush."""
    seen = {}
    original = wm._pending_requests

    def interrupting_task():
        seen["in_comm_frame"] = wm.in_comm_frame
        wm.post_task_outputs("servo", {"servo.frames": 42})
        with pytest.raises(WorldModelError, match="locked out"):
            wm.get("servo.frames")  # the model is locked out during the segment
        return original()

    wm._pending_requests = interrupting_task
    wm.post_task_outputs("servo", {"servo.error_code": 5})
    assert wm.communications_segment() == 1
    wm._pending_requests = original
    assert seen["in_comm_frame"] is True and not wm.in_comm_frame
    assert wm.get("servo.error_code") == 5
    assert wm.get("servo.frames") == 0  # not in this segment ...
    assert wm.pending == 1 and wm.stats()["deferred_posts"] == 1
    assert wm.communications_segment() == 1
    assert wm.get("servo.frames") == 42  # ... but in the next, never lost


def test_state_variable_tools_take_only_integer_scalars(wm):
    wm.post_state_variable("user_interface", "updown.command", 2)
    wm.communications_segment()
    assert wm.get_state_variable("updown.command") == 2
    assert type(wm.get_state_variable("updown.command")) is int
    with pytest.raises(WorldModelError, match="not an integer state variable"):
        wm.get_state_variable("servo.q_rad")
    with pytest.raises(WorldModelError, match="not an integer state variable"):
        wm.post_state_variable("servo", "servo.q_rad", 1)
    with pytest.raises(WorldModelValueError, match="outside int16"):
        wm.post_state_variable("user_interface", "updown.command", 40000)


def test_clock_stamps_each_segment(wm_name):
    from pfma.clock import SimClock
    clk = SimClock(100.0)
    m = WorldModel.create(sup.sample_specs(), name=wm_name, clock=clk)
    try:
        clk.advance(0.003)
        m.communications_segment()
        assert m.info().frame_t_s == pytest.approx(100.003)
    finally:
        m.close()


# --- who may set what (VarSpec.user) -------------------------------------------------------


def test_user_declaration_defaults_from_the_writer_and_the_area():
    def spec(area, writer, **kw):
        return VarSpec("v", area, "f8", (), writer, 0.0, **kw)

    for area in AREAS:  # whatever a task or a table posts: never, in every area
        assert spec(area, "servo").user == "never", area
    assert spec("command_input", "user").user == "always"        # a user request
    assert spec("task_io", "user").user == "always"              # a task input the user supplies
    assert spec("control_flags", "user").user == "powered_down"  # a parameter: locked while up
    assert spec("control_flags", "user", user="always").user == "always"  # declared safe live
    assert spec("command_input", "user", user="never").user == "never"
    for area in ("task_status", "status_output", "response_output", "error_reports"):
        assert spec(area, "user").user == "never", area
    # protected is the old name of powered_down, and stays equal to it
    p = spec("control_flags", "user", protected=True)
    assert p.user == "powered_down" and p.protected
    assert spec("control_flags", "user", user="powered_down").protected
    assert not spec("control_flags", "user", user="always").protected


@pytest.mark.parametrize("kw, text", [
    ({"area": "task_io", "writer": "joint", "user": "always"}, "written by 'joint'"),
    ({"area": "command_input", "writer": "servo", "user": "always"}, "second writer"),
    ({"area": "control_flags", "writer": "servo", "protected": True}, "written by 'servo'"),
    ({"area": "status_output", "writer": "user", "user": "always"}, "status_output written by 'user'"),
    ({"area": "error_reports", "writer": "user", "user": "powered_down"}, "error_reports"),
    ({"area": "control_flags", "writer": "user", "user": "sometimes"}, "not one of never, powered_down, always"),
    ({"area": "control_flags", "writer": "user", "user": "always", "protected": True},
     "protected=True means user='powered_down'"),
])
def test_a_user_writable_task_output_status_or_command_cannot_be_declared(kw, text):
    with pytest.raises(WorldModelError, match=re.escape(text)):
        VarSpec("v", dtype="f8", initial=0.0, **kw)


def test_user_declaration_is_stored_in_the_segment_table_and_old_tables_still_read():
    specs = sup.sample_specs()
    for s in specs:
        assert s.to_json()["user"] == s.user and VarSpec.from_json(s.to_json()) == s
    m = WorldModel.create(specs)
    try:
        table = json.loads(m._lay.spec_json)
        assert {v["name"]: v["user"] for v in table["variables"]} == {s.name: s.user for s in specs}
    finally:
        m.close()
    # a table written before "user" existed: the same rule; protected on a task's variable
    # (allowed then) reads as never instead of failing
    old = {"name": "servo.kp", "area": "control_flags", "dtype": "f8", "shape": [], "writer": "servo",
           "initial": 10.0, "units": "1/s", "protected": True, "doc": ""}
    assert VarSpec.from_json(old).user == "never" and not VarSpec.from_json(old).protected
    assert VarSpec.from_json(dict(old, writer="user")).user == "powered_down"
    assert VarSpec.from_json(dict(old, writer="user", protected=False)).user == "powered_down"
    assert VarSpec.from_json(dict(old, area="command_input", writer="user", protected=False)).user == "always"


def test_users_may_not_set_what_a_task_posts_with_or_without_the_key(wm):
    cases = {"servo.q_cmd_rad": "an output of task trajectory", "servo.integrator": "a status of task servo",
             "updown.status": "a status posted by updown", "servo.frames": "a response posted by servo",
             "servo.error_code": "an error report posted by servo"}
    for powered in (False, True):
        wm.powered_up = powered
        for name, role in cases.items():
            value = wm.spec(name).initial
            for key in (DEFAULT_ACCESS_KEY, "wrong", None):
                with pytest.raises(WorldModelError) as e:
                    wm.set_user(name, value, key)
                assert str(e.value) == f"{name} is {role}; users may not set it"
    assert wm.user_requests_pending() == 0


def test_a_forged_ring_entry_for_a_task_output_is_rejected_by_the_owner(wm_name):
    m = WorldModel.create(sup.sample_specs(), name=wm_name)
    try:
        rid = sup.forge_request(wm_name, "servo.q_cmd_rad", [6.0] * 6, DEFAULT_ACCESS_KEY)
        ok = sup.forge_request(wm_name, "hc.enable", True, DEFAULT_ACCESS_KEY)  # the forger's layout is right
        assert m.user_requests_pending() == 2
        assert m.communications_segment() == 1
        np.testing.assert_array_equal(m.get("servo.q_cmd_rad"), np.zeros(6))
        r = m.request(rid)
        assert (r.state, r.variable, r.user) == ("rejected", "servo.q_cmd_rad", "forger")
        assert r.result == "servo.q_cmd_rad is an output of task trajectory; users may not set it"
        assert m.request(ok).state == "applied" and m.get("hc.enable")
        assert m.stats()["user_rejected"] == 1 and m.info().user_rejected == 1
        assert m.info().user_applied == 1
    finally:
        m.close()


# --- user writes: access key, protected variables ------------------------------------------


def test_user_writes_need_the_key_and_apply_at_the_next_segment(wm):
    with pytest.raises(WorldModelError, match="wrong or missing access key"):
        wm.set_user("servo.kp_1_s", [5.0] * 6, "guess")
    with pytest.raises(WorldModelError, match="wrong or missing access key"):
        wm.set_user("servo.kp_1_s", [5.0] * 6, None)
    rid = wm.set_user("servo.kp_1_s", [5.0] * 6, DEFAULT_ACCESS_KEY, user="tester")
    assert wm.get("servo.kp_1_s")[0] == 10.0  # not before the communications segment
    assert wm.request(rid).state == "pending" and wm.user_requests_pending() == 1
    assert wm.communications_segment() == 1
    np.testing.assert_array_equal(wm.get("servo.kp_1_s"), [5.0] * 6)
    r = wm.request(rid)
    assert (r.state, r.variable, r.user, r.applied_frame) == ("applied", "servo.kp_1_s", "tester", 1)
    with pytest.raises(WorldModelValueError, match="not finite"):
        wm.set_user("servo.kp_1_s", [float("nan")] * 6, DEFAULT_ACCESS_KEY)
    with pytest.raises(WorldModelError, match="no variable"):
        wm.set_user("servo.kp", 1.0, DEFAULT_ACCESS_KEY)


def test_protected_variables_are_refused_while_powered_up(wm):
    wm.powered_up = True
    with pytest.raises(WorldModelError, match="protected.*powered up"):
        wm.set_user("servo.kp_1_s", [5.0] * 6, DEFAULT_ACCESS_KEY)
    # an unprotected variable still takes a keyed user write while powered up
    wm.set_user("hc.enable", True, DEFAULT_ACCESS_KEY)
    wm.communications_segment()
    assert wm.get("hc.enable")
    wm.powered_up = False
    wm.set_user("servo.kp_1_s", [5.0] * 6, DEFAULT_ACCESS_KEY)
    wm.communications_segment()
    assert wm.get("servo.kp_1_s")[0] == 5.0


def test_the_owner_rechecks_a_request_when_it_applies_it(wm):
    """Queued before power-up, applied after: refused, with the reason in the ring."""
    rid = wm.set_user("servo.kp_1_s", [5.0] * 6, DEFAULT_ACCESS_KEY)
    wm.powered_up = True
    assert wm.communications_segment() == 0
    r = wm.request(rid)
    assert r.state == "rejected" and "may be set only while powered down" in r.result
    assert wm.get("servo.kp_1_s")[0] == 10.0
    assert wm.stats()["user_rejected"] == 1 and wm.info().user_rejected == 1
    # a key change between request and segment also rejects it
    wm.powered_up = False
    rid = wm.set_user("servo.kp_1_s", [5.0] * 6, DEFAULT_ACCESS_KEY)
    wm.access_key = "new-key"
    wm.communications_segment()
    assert wm.request(rid).state == "rejected" and "wrong access key" in wm.request(rid).result


def test_access_key_is_configurable(wm_name, monkeypatch):
    m = WorldModel.create(sup.sample_specs(), access_key="s3cret")
    assert m.access_key == "s3cret" and m.check_key("s3cret") and not m.check_key(DEFAULT_ACCESS_KEY)
    monkeypatch.setenv("PFMA_WM_KEY", "from-env")
    m2 = WorldModel.create(sup.sample_specs(), name=wm_name)
    try:
        assert m2.check_key("from-env") and not m2.check_key(DEFAULT_ACCESS_KEY)
        with WorldModel.attach(wm_name) as ro:
            assert ro.check_key("from-env")
            with pytest.raises(WorldModelError, match="read-only"):
                ro.access_key  # noqa: B018 - only a salted hash is in the segment
        raw = bytes(m2._root)
        assert b"from-env" not in raw
    finally:
        m2.close()
    with pytest.raises(WorldModelError, match="non-empty"):
        m.access_key = ""


def test_a_full_request_ring_is_refused_clearly(wm):
    for _ in range(REQUEST_SLOTS):
        wm.set_user("hc.enable", True, DEFAULT_ACCESS_KEY)
    with pytest.raises(WorldModelError, match="queue full"):
        wm.set_user("hc.enable", True, DEFAULT_ACCESS_KEY)
    assert wm.communications_segment() == REQUEST_SLOTS
    wm.set_user("hc.enable", False, DEFAULT_ACCESS_KEY)  # slots free again
    wm.communications_segment()
    assert not wm.get("hc.enable")
    assert [r.req_id for r in wm.requests()] == list(range(2, REQUEST_SLOTS + 2))


def test_kept_user_writes_are_each_taken_in_order_with_their_request_id(wm):
    """A variable whose writes are messages (System Up/Down's requests): two writes applied
    in one segment are two, not the last one's value alone."""
    wm.keep_user_writes("updown.command")
    assert wm.take_user_writes() == ()  # nothing kept yet: nothing built
    rids = [wm.set_user("updown.command", v, DEFAULT_ACCESS_KEY) for v in (1, 3, 2)]
    other = wm.set_user("hc.enable", True, DEFAULT_ACCESS_KEY)  # not kept: a state as before
    assert wm.take_user_writes() == ()  # not before the communications segment
    wm.communications_segment()
    taken = wm.take_user_writes()
    assert [(rid, name, int(v)) for rid, name, v in taken] == [(rids[0], "updown.command", 1),
                                                               (rids[1], "updown.command", 3),
                                                               (rids[2], "updown.command", 2)]
    assert int(wm.get("updown.command")) == 2 and wm.request(other).state == "applied"
    assert wm.take_user_writes() == ()  # taken once


def test_kept_user_writes_the_owner_does_not_take_are_rejected_not_lost(wm):
    from controller.worldmodel.model import KEPT_WRITES
    wm.keep_user_writes("updown.command")
    for _ in range(KEPT_WRITES // REQUEST_SLOTS):
        for _ in range(REQUEST_SLOTS):
            wm.set_user("updown.command", 1, DEFAULT_ACCESS_KEY)
        wm.communications_segment()
    rid = wm.set_user("updown.command", 4, DEFAULT_ACCESS_KEY)
    wm.communications_segment()
    r = wm.request(rid)
    assert r.state == "rejected" and f"has not taken its {KEPT_WRITES} earlier writes" in r.result
    assert len(wm.take_user_writes()) == KEPT_WRITES and int(wm.get("updown.command")) == 1


def test_only_the_owner_keeps_user_writes(wm_name):
    m = WorldModel.create(sup.sample_specs(), name=wm_name)
    try:
        with WorldModel.attach(wm_name) as ro:
            with pytest.raises(WorldModelError, match="keep_user_writes"):
                ro.keep_user_writes("updown.command")
        with pytest.raises(WorldModelError, match="no variable"):
            m.keep_user_writes("updown.commandx")
    finally:
        m.close()


# --- shared memory: ownership, attach, other processes --------------------------------------


def test_attached_model_is_read_only_and_names_the_owner(wm_name):
    m = WorldModel.create(sup.sample_specs(), name=wm_name, owner="ctl-test")
    try:
        with WorldModel.attach(wm_name) as ro:
            for action in (lambda: ro.post_task_outputs("servo", {"servo.frames": 1}),
                           ro.communications_segment,
                           lambda: setattr(ro, "powered_up", True)):
                with pytest.raises(WorldModelError, match=f"owner 'ctl-test' \\(pid {os.getpid()}\\)"):
                    action()
            with pytest.raises((TypeError, ValueError)):
                ro._body[0:1] = b"x"  # the data view itself is read-only
            m.powered_up = True
            assert ro.powered_up and ro.info().owner == "ctl-test" and ro.info().owner_alive
            assert wm_name in list_segments()
    finally:
        m.close()


def test_one_owner_per_segment_and_a_dead_owners_segment_is_replaced(wm_name):
    m = WorldModel.create(sup.sample_specs(), name=wm_name, owner="first")
    with pytest.raises(WorldModelError, match=f"owned by 'first' \\(pid {os.getpid()}, running\\)"):
        WorldModel.create(sup.sample_specs(), name=wm_name)
    m.close()  # the segment stays, without an owner
    with WorldModel.attach(wm_name) as ro:
        assert ro.info().owner_pid == 0
        with pytest.raises(WorldModelError, match="not running"):
            ro.set_user("hc.enable", True, DEFAULT_ACCESS_KEY)
    m2 = WorldModel.create(sup.sample_specs()[:2], name=wm_name, owner="second")
    try:
        assert m2.names() == ("servo.q_cmd_rad", "servo.q_rad")
    finally:
        m2.close()
    assert m2.unlink() and not WorldModel.remove_segment(wm_name)
    with pytest.raises(WorldModelError, match="is the controller running"):
        WorldModel.attach(wm_name)


@pytest.mark.realtime
def test_another_process_decodes_names_and_values_from_the_stored_table(wm_name, mp):
    m = WorldModel.create(sup.sample_specs(), name=wm_name, owner="ctl-x")
    child = None
    try:
        m.post_task_outputs("servo", {"servo.q_rad": [0.5] * 6, "servo.error_code": -3})
        m.post_task_outputs("kinematics", {"tool.T_base": 2 * np.eye(4)})
        m.communications_segment()
        m.powered_up = True
        parent, child_end = mp.Pipe()
        child = mp.Process(target=sup.inspect_model, args=(wm_name, child_end))
        child.start()
        assert parent.poll(30.0), "inspecting process did not answer"
        got = parent.recv()
        assert got["names"] == m.names()
        assert [VarSpec.from_json(d) for d in got["specs"]] == list(m.specs)
        assert got["values"]["servo.q_rad"] == [0.5] * 6
        assert got["values"]["servo.error_code"] == -3
        assert got["values"]["tool.T_base"][1][1] == 2.0
        assert got["values"]["hc.enable"] is False
        assert (got["frame"], got["powered_up"], got["owner"], got["owner_pid"]) == (1, True, "ctl-x", os.getpid())
        # the other process asks for a user write; this process (the owner) applies it
        parent.send(("servo.kp_1_s", [1.0] * 6, DEFAULT_ACCESS_KEY))
        assert parent.poll(30.0)
        status, detail = parent.recv()
        assert status == "error" and "protected" in detail
        m.powered_up = False
        child.join(30.0)
        child2_parent, child2_end = mp.Pipe()
        child = mp.Process(target=sup.inspect_model, args=(wm_name, child2_end))
        child.start()
        assert child2_parent.poll(30.0)
        child2_parent.recv()
        child2_parent.send(("servo.kp_1_s", [1.0] * 6, DEFAULT_ACCESS_KEY))
        assert child2_parent.poll(30.0)
        status, rid = child2_parent.recv()
        assert status == "ok"
        assert m.communications_segment() == 1
        assert m.get("servo.kp_1_s")[0] == 1.0 and m.request(rid).state == "applied"
        assert m.request(rid).user  # who asked is recorded
    finally:
        if child is not None:
            child.join(30.0)
            if child.is_alive():
                child.kill()
        m.close()


N_READS = 20_000


@pytest.mark.realtime
def test_no_torn_frames_against_a_flat_out_writer_in_another_process(wm_name, mp):
    started, stop, result = mp.Event(), mp.Event(), mp.Queue()
    child = mp.Process(target=sup.flat_out_owner, args=(wm_name, started, stop, 20.0, result))
    child.start()
    try:
        assert started.wait(30.0), "writer process did not start"
        reader = WorldModel.attach(wm_name)
        torn = 0
        frames = set()
        last = 0
        try:
            for k in range(N_READS):
                if k % 2:
                    got = reader.get_task_inputs(["big", "small", "count"])
                    lo = min(got["big"].min(), got["small"].min(), got["count"])
                    hi = max(got["big"].max(), got["small"].max(), got["count"])
                else:  # one variable, read by itself (read_part_into)
                    big = reader.get("big")
                    lo, hi = big.min(), big.max()
                if lo != hi:
                    torn += 1
                assert lo >= last, "frames went backwards"
                last = int(lo)
                frames.add(last)
            retries = reader.read_retries
        finally:
            reader.close()
        stop.set()
        written = result.get(timeout=30.0)
        child.join(30.0)
        print(f"world-model fuzz: {N_READS} reads, {len(frames)} frames seen, {written} written, "
              f"{retries} retries, {torn} torn")
        assert torn == 0
        assert len(frames) >= 10 and written > 200  # the writer really ran during the reads
        if (os.cpu_count() or 1) > 1:
            assert retries > 0  # the reader did meet segments in progress
    finally:
        stop.set()
        child.join(30.0)
        if child.is_alive():
            child.kill()


def test_a_slot_abandoned_mid_write_is_reused(wm):
    """A submitter that died between 'writing' and 'pending' does not block the ring."""
    from controller.worldmodel import WRITING
    st = wm._slot_state(0)
    st[0] = WRITING  # as left by a tool killed in the middle of its write
    st.release()
    assert wm.communications_segment() == 0  # the owner ignores it
    rid = wm.set_user("hc.enable", True, DEFAULT_ACCESS_KEY)
    assert rid == 1 and wm.communications_segment() == 1 and wm.get("hc.enable")
