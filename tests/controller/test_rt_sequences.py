"""Power-up, shut-down and request/response on the whole simulated system (simulated time)."""

import numpy as np
import pytest

from controller.decision import Status
from controller.layers import Request, Response
from sim.system import SystemSimulator
from controller.worldmodel import WorldModelError

S = Status
ORDER = ("updown", "msp", "trajectory", "cartesian", "joint", "servo", "daq")


def _frames(rt, to):
    return [rt.first_change(k, to) for k in ORDER]


def test_cold_start_power_up_in_a_few_hundred_ms_in_the_reports_order(sim):
    rt = sim.rt
    assert rt.all_status(S.SHUT_DOWN)
    seq = rt.request(Request.POWER_UP)
    frames = sim.run_until(lambda: rt.all_status(S.START_UP_COMPLETE), 400)
    elapsed_s = frames * sim.period_s
    assert elapsed_s < 0.4, f"power-up took {elapsed_s * 1e3:.0f} ms"
    init = _frames(rt, S.INITIALIZATION_IN_PROGRESS)
    ic = _frames(rt, S.INITIALIZATION_COMPLETE)
    su = _frames(rt, S.START_UP)
    suc = _frames(rt, S.START_UP_COMPLETE)
    # initialise down the tree layer by layer ...
    assert init == sorted(init) and len(set(init)) == 7
    # ... a layer commands its subordinate only after its own initialisation (WAITING FOR SUBORDINATE)
    wait = _frames(rt, S.WAITING_FOR_SUBORDINATE_TO_INIT)[:-1]
    assert all(w < i for w, i in zip(wait, init[1:]))
    # INITIALIZATION COMPLETE back up, bottom first, after the bottom layer's initialisation
    assert ic[::-1] == sorted(ic) and ic[-1] > init[-1]
    # START UP down, once System Up/Down is INITIALIZATION COMPLETE
    assert su == sorted(su) and su[0] > ic[0]
    # START UP COMPLETE up, bottom first
    assert suc[::-1] == sorted(suc) and suc[-1] > su[-1]
    sim.step(2)
    assert rt.response() == (seq, Response.COMPLETE)
    assert rt.wm.powered_up
    assert bool(rt.wm.get("daq.outputs_enabled")) and bool(rt.wm.get("daq.brakes_released"))
    # the trace shows the same thing to a reader
    text = "\n".join(rt.format_frame(r) for r in rt.trace if any(l.changed for l in r.layers))
    assert "*INIT>INIT.." in text and "*START>UP" in text


def test_power_up_trace_is_deterministic():
    def run():
        with SystemSimulator() as s:
            s.step(10)
            s.power_up(400)
            s.step(30)
            s.rt.request(Request.POWER_DOWN)
            s.step(60)
            return [(r.frame, round(r.t_s, 12), r.layers, r.fault_bits, r.tasks) for r in s.rt.trace], \
                s.joint_angles_rad()
    a, qa = run()
    b, qb = run()
    assert a == b and np.array_equal(qa, qb)


def test_shut_down_passes_down_in_parallel_and_leaves_the_dac_at_0_v(powered):
    rt = powered.rt
    seq = rt.request(Request.POWER_DOWN)
    powered.run_until(lambda: rt.all_status(S.SHUT_DOWN), 400)
    sdip = _frames(rt, S.SHUT_DOWN_IN_PROGRESS)
    # one frame per layer on the way down: no layer waits for the one below before passing it on
    assert np.all(np.diff(sdip) == 1)
    sd = _frames(rt, S.SHUT_DOWN)
    assert sd[::-1] == sorted(sd)  # SHUT DOWN completes bottom first
    powered.step(3)
    assert rt.response() == (seq, Response.COMPLETE)
    assert not rt.wm.powered_up
    assert np.all(powered.dac_volts() == 0.0)
    assert int(rt.wm.get("daq.service_state")) == 1  # SAFE
    assert int(rt.wm.get("servo.brake_phase")) == 5


def test_no_shut_down_before_initialization_complete(sim):
    rt = sim.rt
    rt.request(Request.POWER_UP)
    sim.run_until(lambda: rt.status("updown") == S.WAITING_FOR_SUBORDINATE_TO_INIT, 50)
    seq = rt.request(Request.POWER_DOWN)
    sim.step(2)
    assert rt.response() == (seq, Response.REFUSED)
    assert any("no SHUT DOWN before INITIALIZATION COMPLETE" in m.text for m in rt.messages.recent())
    # the power-up carries on to the end
    sim.run_until(lambda: rt.all_status(S.START_UP_COMPLETE), 400)


def test_power_up_again_after_power_down(powered):
    rt = powered.rt
    rt.request(Request.POWER_DOWN)
    powered.run_until(lambda: rt.all_status(S.SHUT_DOWN), 400)
    powered.step(5)
    powered.power_up(400)
    assert rt.all_status(S.START_UP_COMPLETE)


def test_refused_requests_are_answered(powered):
    rt = powered.rt
    seq = rt.request(Request.POWER_UP)  # already up
    powered.step(2)
    assert rt.response() == (seq, Response.REFUSED)
    seq = rt.request(Request.ERROR_RESET)  # not in ERROR
    powered.step(2)
    assert rt.response() == (seq, Response.REFUSED)


def test_control_law_parameters_are_protected_while_powered_up(sim):
    rt = sim.rt
    key = rt.wm.access_key
    with pytest.raises(WorldModelError, match="access key"):
        rt.wm.set_user("servo.kp_per_s", [6.0] * 6, "wrong")
    rt.wm.set_user("servo.kp_per_s", [6.0] * 6, key)  # powered down: accepted with the key
    sim.power_up(400)
    with pytest.raises(WorldModelError, match="protected"):
        rt.wm.set_user("servo.kp_per_s", [20.0] * 6, key)
    assert list(rt.servo.comp.k) == [6.0] * 6  # latched at initialisation
    assert any("K=6 6 6 6 6 6" in m.text for m in rt.messages.recent())


def test_scheduling_table_runs_tasks_at_their_rates(powered):
    rt = powered.rt
    before = dict(rt.by_key["msp"].runs), dict(rt.by_key["cartesian"].runs)
    ran = []
    rt.on_frame.append(lambda rec: ran.append(rec))
    powered.step(32)  # two major frames
    assert rt.by_key["msp"].runs["msp_planner"] - before[0]["msp_planner"] == 2  # 20 Hz
    assert rt.by_key["cartesian"].runs["cartesian_fast"] - before[1]["cartesian_fast"] == 8  # 80 Hz
    servo = [r.frame for r in ran if "servo_control" in r.tasks]
    assert len(servo) == 16 and all(f % 2 == 0 for f in servo)  # 160 Hz, resolver frames
    assert all("updown_requests" in r.tasks for r in ran)
    assert all(r.frame == f for r, f in zip(ran, range(ran[0].frame, ran[0].frame + 32)))


def test_halted_runtime_is_single_stepped_by_the_simulator(powered):
    """Halting stops every frame (IRSS's halt stops the frame interrupts); one step is one
    service frame plus one controller frame."""
    rt = powered.rt
    n0, f0 = rt.frames_run, rt.frame
    powered.step(1)
    assert rt.frames_run == n0 + 1 and rt.frame == f0 + 1
    assert powered.service_frames == rt.frames_run
