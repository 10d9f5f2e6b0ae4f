"""World-model writes respect ownership (IRSS 2.2.8): on the whole simulated system, users
may set requests and (while powered down) control-law parameters, never what a task or a
decision table posts: task outputs, layer commands, statuses, reports. Not with the key,
not through ``pfma wm set``, not by writing the request ring in shared memory directly.

Simulated time only: the simulator steps frames, nothing sleeps.
"""

import numpy as np
import pytest

from controller.decision import Status
from sim.system import SystemSimulator
from controller.worldmodel import WorldModel, WorldModelError
from tools.cli import main
from tests.controller import _wm_support as sup

#: variable -> what the refusal says it is (the writer named as its owner)
POSTED_BY_TASKS = {
    "servo.q_cmd_rad": "an output of task joint",
    "servo.rate_cmd_rad_s": "an output of task servo",
    "daq.joint_angle_rad": "an output of task daq",
    "daq.command": "a layer command posted by servo",
    "servo.command": "a layer command posted by joint",
    "updown.command": "a layer command posted by updown_requests",
    "updown.status": "a status posted by updown",
    "daq.service_state": "a status posted by daq",
    "servo.brake_phase": "a status of task servo",
    "ui.response": "a response posted by updown_requests",
    "daq.fault_bits": "an error report posted by daq",
}


@pytest.fixture
def shm_sim():
    name = sup.unique_name()
    s = SystemSimulator(wm_name=name)
    s.step(10)
    yield s
    s.close()
    WorldModel.remove_segment(name)


def _refused(wm, name: str, key) -> str:
    with pytest.raises(WorldModelError) as e:
        wm.set_user(name, wm.spec(name).initial, key)
    return str(e.value)


def test_every_real_output_command_and_status_is_never_user_settable(shm_sim):
    wm = shm_sim.rt.wm
    for s in wm.specs:
        if s.writer != "user":  # everything a task or a decision table posts
            assert s.user == "never", s.name
    for name, role in POSTED_BY_TASKS.items():
        for key in (wm.access_key, "wrong", None):
            assert _refused(wm, name, key) == f"{name} is {role}; users may not set it"
    assert wm.user_requests_pending() == 0


def test_what_the_code_base_sets_as_a_user_is_declared_user_settable(shm_sim):
    """runtime.request()/set_joint_goal(), `pfma controller` motion/path flags, the tests."""
    wm = shm_sim.rt.wm
    always = ("ui.request", "joint.goal_rad", "joint.goal_seq", "cart.mode",
              "cart.hc_source", "cart.hc_frame", "cart.vernier", "force.enable", "delay.round_trip_s",
              "delay.jitter", "msp.mode", "msp.path_id", "msp.teach", "msp.speed_scale")
    down = ("servo.kp_per_s", "servo.tau_z_s", "servo.tau_p_s", "traj.v_lin_max_m_s")
    assert {n: wm.spec(n).user for n in always} == dict.fromkeys(always, "always")
    assert {n: wm.spec(n).user for n in down} == dict.fromkeys(down, "powered_down")


def test_powered_up_outputs_refused_parameters_refused_requests_accepted(shm_sim):
    sim = shm_sim
    wm, key = sim.rt.wm, sim.rt.wm.access_key
    # powered down: a control-law parameter is accepted (and latched at initialisation)
    wm.set_user("servo.kp_per_s", [6.0] * 6, key)
    sim.step(1)
    np.testing.assert_array_equal(wm.get("servo.kp_per_s"), [6.0] * 6)
    sim.power_up(400)
    sim.step(20)
    assert sim.rt.all_status(Status.START_UP_COMPLETE)
    # the report's case: the joint planner's output, 6 rad on joint 0, while the arm is live
    assert _refused(wm, "servo.q_cmd_rad", key) == \
        "servo.q_cmd_rad is an output of task joint; users may not set it"
    assert _refused(wm, "servo.kp_per_s", key) == \
        "servo.kp_per_s is protected: it may be set only while powered down (the system is powered up)"
    assert _refused(wm, "updown.status", key).startswith("updown.status is a status posted by updown")
    assert wm.user_requests_pending() == 0
    # a request still goes through while powered up
    wm.set_user("cart.vernier", True, key)
    sim.step(1)
    assert wm.get("cart.vernier")


def test_a_forged_ring_entry_is_rejected_by_the_owner_and_counted(shm_sim):
    """The ring is shared memory: another process can skip set_user and write it. The owner
    re-checks at its communications segment; the output is never applied, not even for a frame."""
    sim = shm_sim
    wm = sim.rt.wm
    sim.power_up(400)
    sim.step(20)
    before = wm.info().user_rejected
    forged = {sup.forge_request(wm.name, "servo.q_cmd_rad", [6.0, 0, 0, 0, 0, 0], wm.access_key): "joint",
              sup.forge_request(wm.name, "daq.command", 3, wm.access_key): "servo",
              sup.forge_request(wm.name, "updown.status", 0, wm.access_key): "updown"}
    param = sup.forge_request(wm.name, "servo.kp_per_s", [20.0] * 6, wm.access_key)
    for _ in range(8):
        sim.step(1)
        assert wm.get("servo.q_cmd_rad")[0] != 6.0
        assert sim.rt.status("updown") == Status.START_UP_COMPLETE
    for rid, owner in forged.items():
        r = wm.request(rid)
        assert r.state == "rejected" and r.user == "forger", r
        assert r.result == f"{r.variable} is {POSTED_BY_TASKS[r.variable]}; users may not set it"
        assert owner in r.result
    r = wm.request(param)
    assert r.state == "rejected" and "only while powered down" in r.result
    assert wm.info().user_rejected == before + 4 and wm.stats()["user_rejected"] >= 4
    assert sim.rt.all_status(Status.START_UP_COMPLETE)


def test_pfma_wm_set_of_a_task_output_exits_non_zero_with_one_line(shm_sim, capsys, monkeypatch):
    monkeypatch.delenv("PFMA_WM_KEY", raising=False)
    wm = shm_sim.rt.wm
    for key in (["--key", wm.access_key], []):
        rc = main(["wm", "set", "servo.q_cmd_rad", "[6, 0, 0, 0, 0, 0]", "--wait", "0",
                   "--name", wm.name, *key])
        out, err = capsys.readouterr()
        assert rc == 1 and out == ""
        assert err == "pfma wm: servo.q_cmd_rad is an output of task joint; users may not set it\n"
    assert wm.user_requests_pending() == 0
    rc = main(["wm", "list", "--filter", "q_cmd", "--name", wm.name])
    out = capsys.readouterr().out
    row = next(ln for ln in out.splitlines() if ln.startswith("servo.q_cmd_rad "))
    assert rc == 0 and row.split()[4:6] == ["joint", "never"]
