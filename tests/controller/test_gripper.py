"""The gripper through the whole stack in simulated time (controller/gripper.py, docs/controller.md
"The gripper"): requests to Servo Control, Data Acquisition writing DAC channels 6 (gripper
command) and 13 (its current limit), the simulated jaw stalling on an object at the force the
current limit sets, the limits, halt and power-down, and paths with gripper events replayed in
order with the motion."""

from __future__ import annotations

import numpy as np
import pytest

from controller.layers import Request, Response
from controller.paths import MspMode, MspResult, PathStore, insert_gripper, make_point
from fakes.arm_params import SimErrors
from pfma.arm import GRIPPER
from pfma.gripper import GripperRequest as G, GripperState as S

GR = 6  # the jaw's axis in the simulated arm
CH_GRIP, CH_LIMIT = 6, 13  # DAC channels: gripper command (V), its current limit (0.5 A/V)


def _jaw(sim) -> float:
    return float(sim.world.sim.arm.q[GR])


def _set_jaw(sim, opening_m: float) -> None:
    sim.world.sim.arm.q[GR] = opening_m  # the world's jaw, placed by hand (the arm is not moving)


def _state(sim) -> S:
    return S(int(sim.rt.wm.get("gripper.state")))


def grip(sim, kind: int, force_n: float = 0.0, max_s: float = 9.0) -> tuple[int, str]:
    """Send a gripper request and run frames until its final answer: (Response code, text)."""
    seq = sim.rt.gripper_request(kind, force_n)
    for _ in range(int(max_s / sim.period_s)):
        sim.step(1)
        v = sim.rt.wm.get_task_inputs(("gripper.response_seq", "gripper.response", "gripper.response_text"))
        if int(v["gripper.response_seq"]) == seq and int(v["gripper.response"]) != Response.IN_PROGRESS:
            return int(v["gripper.response"]), bytes(v["gripper.response_text"]).rstrip(b"\0").decode()
    raise AssertionError(f"gripper request {seq} not answered in {max_s} s")


def test_open_runs_the_jaw_to_its_stop_and_a_close_stalls_on_the_object_and_holds_the_set_force(powered):
    sim = powered
    assert _state(sim) == S.STOPPED  # powered: the drive runs, nothing moves
    _set_jaw(sim, 0.085)
    code, text = grip(sim, G.OPEN)
    assert code == Response.COMPLETE and text.startswith("OPEN: at the open stop"), text
    assert _jaw(sim) == pytest.approx(GRIPPER.travel_m, abs=2e-4) and _state(sim) == S.OPEN
    assert bool(sim.rt.wm.get("gripper.jaw_known")) and float(sim.rt.wm.get("gripper.jaw_m")) == GRIPPER.travel_m
    sim.world.sim.arm.place_jaw_object(0.08)
    code, text = grip(sim, G.CLOSE, 60.0)
    assert code == Response.COMPLETE and "GRIPPING" in text and "holding at 60 N; jaw ~80 mm" in text, text
    sim.step(320)  # it holds: a second later the jaw is still on the object, pressing with 60 N
    arm = sim.world.sim.arm
    assert _state(sim) == S.GRIPPING and _jaw(sim) == pytest.approx(0.08, abs=2e-4)
    assert arm.jaw_force_n == pytest.approx(60.0, abs=GRIPPER.coulomb_n + 0.5)
    volts = sim.dac_volts()
    assert volts[CH_GRIP] == pytest.approx(-10.0)  # full-scale closing: the amplifier sits at its limit
    assert volts[CH_LIMIT] == pytest.approx(60.0 / GRIPPER.force_per_amp / 0.5, abs=0.01)  # 1.5 A at 0.5 A/V
    assert float(sim.rt.wm.get("gripper.motor_force_n")) == pytest.approx(60.0, abs=0.5)
    # a new grip force acts on the hold at once
    code, text = grip(sim, G.FORCE, 120.0)
    assert (code, text) == (Response.COMPLETE, "FORCE: grip force 120 N, current limit 3 A")
    sim.step(160)
    assert arm.jaw_force_n == pytest.approx(120.0, abs=GRIPPER.coulomb_n + 0.5)
    # the joints' current limits are untouched by the gripper's
    limits = np.asarray(sim.rt.wm.get("servo.current_limit_cmd_a"))
    assert limits[:6].tolist() == [5.0, 5.0, 5.0, 2.5, 2.5, 2.5] and limits[6] == 3.0


def test_a_close_with_nothing_in_the_jaw_ends_closed_and_stop_halts_a_move(powered):
    sim = powered
    _set_jaw(sim, 0.095)
    assert grip(sim, G.OPEN)[0] == Response.COMPLETE  # references the jaw estimate
    seq = sim.rt.gripper_request(G.CLOSE)
    sim.step(320)  # one second: 20 mm closed
    assert _state(sim) == S.CLOSING and _jaw(sim) == pytest.approx(0.08, abs=2e-3)
    code, text = grip(sim, G.STOP)
    assert code == Response.COMPLETE and text.startswith("STOP: stopped (CLOSING ended), jaw ~"), text
    answered = sim.rt.servo.gripper.answers
    assert (seq, Response.FAILED) in [(s, c) for _, s, c, _ in answered]  # the close: superseded by the stop
    sim.step(64)  # 0.2 s: the command reaches the DAC, the jaw (100 kg reflected) comes to rest
    q = _jaw(sim)
    sim.step(160)
    assert _jaw(sim) == pytest.approx(q, abs=2e-5) and sim.dac_volts()[CH_GRIP] == 0.0
    code, text = grip(sim, G.CLOSE)
    assert code == Response.COMPLETE and text.startswith("CLOSED after"), text
    assert "nothing between the jaws" in text and _jaw(sim) == pytest.approx(0.0, abs=2e-4)
    assert _state(sim) == S.CLOSED and float(sim.rt.wm.get("gripper.jaw_m")) == 0.0


@pytest.mark.parametrize("force, says", [
    (500.0, "CLOSE: grip force 500 N is outside 10..200 N (current limit 0.25..5 A at 40 N/A)"),
    (5.0, "CLOSE: grip force 5 N is outside 10..200 N"),
])
def test_a_force_beyond_the_limits_is_refused_with_a_message_and_nothing_moves(powered, force, says):
    sim = powered
    before = _jaw(sim)
    code, text = grip(sim, G.CLOSE, force)
    assert (code, text.split(" (")[0]) == (Response.REFUSED, says.split(" (")[0]) and says in text
    sim.step(100)
    assert _state(sim) == S.STOPPED and _jaw(sim) == before and sim.dac_volts()[CH_GRIP] == 0.0
    assert any("gripper request" in m.text and "REFUSED" in m.text for m in sim.rt.messages.recent(5))


def test_the_current_limit_parameter_caps_the_grip_force_and_moves_need_power(sim):
    code, text = grip(sim, G.CLOSE)
    assert code == Response.REFUSED and "Servo Control is SHUT DOWN: the gripper drive is off (power up first)" in text
    limits = list(sim.rt.wm.get("servo.current_limit_a"))
    limits[6] = 1.0  # the most the gripper may draw: 40 N
    sim.rt.wm.set_user("servo.current_limit_a", limits, sim.rt.wm.access_key)
    sim.power_up()
    sim.step(20)
    code, text = grip(sim, G.FORCE, 60.0)
    assert code == Response.REFUSED and "grip force 60 N is outside 10..40 N" in text
    assert grip(sim, G.FORCE, 30.0)[0] == Response.COMPLETE


def test_a_drive_that_does_not_answer_stalls_the_move_which_fails(powered):
    sim = powered
    off = tuple(i == GR for i in range(7))
    sim.world.sim.set_errors(SimErrors(amp_off=off))  # the gripper's PWM stage switched off
    code, text = grip(sim, G.OPEN)
    assert code == Response.FAILED and "the drive does not answer" in text, text
    sim.step(4)  # the next frames' commands
    assert _state(sim) == S.STALLED and sim.dac_volts()[CH_GRIP] == 0.0


def test_halted_a_gripper_request_is_refused_and_a_power_down_fails_a_close(powered):
    sim = powered
    assert sim.request(Request.HALT)[0] == Response.COMPLETE
    code, text = grip(sim, G.CLOSE, max_s=0.1)
    assert code == Response.REFUSED and "the controller is HALTED" in text
    assert sim.dac_volts()[CH_GRIP] == 0.0 and sim.dac_volts()[CH_LIMIT] == 0.0
    assert sim.request(Request.RESUME, 1)[0] == Response.COMPLETE
    sim.step(20)
    seq = sim.rt.gripper_request(G.OPEN)
    sim.step(64)
    assert _state(sim) == S.OPENING and sim.dac_volts()[CH_GRIP] == pytest.approx(0.02 * GRIPPER.k_w_v_per_m_s, abs=0.01)
    sim.rt.request(Request.POWER_DOWN)
    sim.run_until(lambda: int(sim.rt.wm.get("gripper.response_seq")) == seq
                  and int(sim.rt.wm.get("gripper.response")) == Response.FAILED, 64)
    assert "switched off" in bytes(sim.rt.wm.get("gripper.response_text")).decode()
    sim.step(400)
    assert _state(sim) == S.OFF and sim.dac_volts()[CH_GRIP] == 0.0 and sim.dac_volts()[CH_LIMIT] == 0.0


# --- paths: gripper events recorded and replayed in order with the motion -----------------------

def _tool_pose(sim):
    v = sim.rt.wm.get_task_inputs(("joint.tool_pos_m", "joint.tool_quat"))
    return np.array(v["joint.tool_pos_m"], dtype=float), np.array(v["joint.tool_quat"], dtype=float)


def _play(sim, store, name: str, max_s: float) -> list[tuple[float, int, int, float]]:
    """Play path ``name``; each change of (segment, gripper state) with the time and the tool's x."""
    wm, key = sim.rt.wm, sim.rt.wm.access_key
    wm.set_user("msp.path_id", store.load(name).id, key)
    wm.set_user("cart.mode", 2, key)
    wm.set_user("msp.mode", MspMode.PLAY, key)
    log, last = [], None
    for k in range(int(max_s / sim.period_s)):
        sim.step(1)
        v = wm.get_task_inputs(("msp.segment", "gripper.state", "msp.state"))
        cur = (int(v["msp.segment"]), int(v["gripper.state"]))
        if cur != last:
            log.append((sim.clock.now(), *cur, float(_tool_pose(sim)[0][0])))
            last = cur
        if k > 20 and int(v["msp.state"]) == MspMode.IDLE:
            break
    return log


def test_a_path_with_gripper_events_replays_them_in_order_with_the_motion(powered, tmp_path):
    sim = powered
    store = PathStore(tmp_path)
    sim.rt.by_key["msp"].store = store
    _set_jaw(sim, GRIPPER.travel_m)
    sim.world.sim.arm.place_jaw_object(0.085)
    p, q = _tool_pose(sim)
    a, b = p + (0.0, 0.0, 0.015), p + (0.015, 0.0, 0.015)  # up 15 mm, then 15 mm forward
    path = store.new("pick", [make_point(a, q, "teach"), make_point(b, q, "teach")])
    path = insert_gripper(path, 1, "close", 50.0)  # close once at a, before going on to b
    path = insert_gripper(path, 3, "open")  # open once at b
    store.save(path)
    log = _play(sim, store, "pick", 20.0)
    states = [s for _, _, s, _ in log]
    segs = [g for _, g, _, _ in log]
    assert int(sim.rt.wm.get("msp.result")) == MspResult.OK
    # segments 1 (approach to a), 2 (the close's, at a), 3 (to b), 4 (the open's, at b)
    assert max(segs) == 4
    close_at = next(i for i, (_, g, s, _) in enumerate(log) if s == S.CLOSING)
    open_at = next(i for i, (_, g, s, _) in enumerate(log) if s == S.OPENING)
    assert close_at < open_at and S.GRIPPING in states[close_at:open_at]
    assert log[close_at][1] == 2 and log[open_at][1] == 4  # each after its own segment, not before
    # the arm stood at a while the jaw closed, and left it only once the grip held
    t_grip = next(t for t, g, s, _ in log if s == S.GRIPPING)
    t_seg3 = next(t for t, g, s, _ in log if g == 3)
    assert t_seg3 >= t_grip
    assert log[close_at][3] == pytest.approx(a[0], abs=0.01) and abs(log[open_at][3] - b[0]) < 0.01
    assert _state(sim) == S.OPEN and sim.world.sim.arm.jaw_force_n == 0.0


def test_a_gripper_event_that_fails_ends_the_playback_gripper_failed(powered, tmp_path):
    sim = powered
    store = PathStore(tmp_path)
    sim.rt.by_key["msp"].store = store
    p, q = _tool_pose(sim)
    store.save(insert_gripper(store.new("bad", [make_point(p, q, "teach")]), 1, "open"))
    sim.world.sim.set_errors(SimErrors(amp_off=tuple(i == GR for i in range(7))))
    _play(sim, store, "bad", 5.0)
    assert int(sim.rt.wm.get("msp.result")) == MspResult.GRIPPER
    assert any("GRIPPER FAILED" in m.text for m in sim.rt.messages.recent(10))


def test_a_recording_stores_the_gripper_requests_in_order_with_the_motion(powered, tmp_path):
    sim = powered
    store = PathStore(tmp_path)
    msp = sim.rt.by_key["msp"]
    msp.store, msp.background_save = store, False
    wm, key = sim.rt.wm, sim.rt.wm.access_key
    _set_jaw(sim, 0.09)
    sim.world.sim.arm.place_jaw_object(0.085)
    wm.set_user("msp.path_id", store.new("rec").id, key)
    wm.set_user("msp.mode", MspMode.RECORD, key)
    sim.step(20)
    goal = sim.joint_angles_rad()
    goal[1] += 0.03
    sim.rt.set_joint_goal(goal)
    sim.step(320)
    assert grip(sim, G.CLOSE, 70.0)[0] == Response.COMPLETE
    goal[1] -= 0.03
    sim.rt.set_joint_goal(goal)
    sim.step(320)
    assert grip(sim, G.STOP)[0] == Response.COMPLETE
    wm.set_user("msp.mode", MspMode.IDLE, key)
    sim.step(40)
    pts = store.load("rec").points
    kinds = [p.kind for p in pts]
    events = [(i, p.gripper, p.force_n) for i, p in enumerate(pts) if p.kind == "gripper"]
    assert [(g, f) for _, g, f in events] == [("close", 70.0), ("stop", 70.0)]
    first, second = events[0][0], events[1][0]
    # motion captured before the close, between the two events, and the events where the tool was
    assert "capture" in kinds[:first] and "capture" in kinds[first + 1:second]
    assert np.allclose(pts[second].pos_m, _tool_pose(sim)[0], atol=0.002)
