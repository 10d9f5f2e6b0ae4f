"""Halt, single step and resume on a running system (issue 18 item 3, docs/console.md).

The service keeps running in every test: only the controller halts. In simulated time with
the system simulator; every request goes through the world model's request protocol
(``ui.request`` / ``ui.request_seq`` / ``ui.request_arg``), answered by System Up/Down.
"""

from __future__ import annotations

import numpy as np
import pytest

from bit3.layout import ServiceState
from controller.decision import Status
from controller.layers import Request, Response
from controller.runtime import MAX_STEP_FRAMES
from ioservice.service import FAULT_NONE, FAULT_WATCHDOG
from ioservice.safety import HALT_CODE

S = Status
YAW = 1  # shoulder yaw in command-area order
WATCHDOG_FRAMES = 5  # 15 ms at 320 Hz: the service's watchdog


def _inputs(sim):
    return sim.client.read_inputs()


def _state(sim) -> ServiceState:
    return ServiceState(int(_inputs(sim).service_state))


def _halt(sim) -> None:
    code, text = sim.request(Request.HALT)
    assert code == Response.COMPLETE, text
    assert sim.rt.halted


def _moving(powered) -> None:
    """Shoulder yaw on its way to a goal 0.3 rad away (the arm is moving when halted)."""
    goal = powered.joint_angles_rad().copy()
    goal[YAW] += 0.3
    powered.rt.set_joint_goal(goal)
    powered.step(64)
    assert np.abs(_inputs(powered).dac_value[:6]).max() > 0.05  # rates on the DAC


def test_halt_on_a_moving_arm_holds_halted_not_a_watchdog_trip(powered):
    sim = powered
    _moving(sim)
    _halt(sim)
    sim.step(320)  # 1 s halted: 64 watchdog periods
    snap = _inputs(sim)
    assert _state(sim) == ServiceState.HALTED
    assert sim.svc.guard.trips == 0 and sim.svc.fault_code == FAULT_NONE
    assert int(snap.watchdog_tripped) == 0
    assert float(snap.command_age_s) < 0.015  # the halted controller keeps the heartbeat fresh
    assert np.all(sim.dac_volts() == 0.0)  # every channel, rates and current limits: 0 V
    assert int(snap.brakes_released) == 0 and int(snap.outputs_enabled) == 0
    # the service names it, once, as an INFO (not an error)
    notes = [m for m in sim.client.messages(0, "service") if m.code == HALT_CODE]
    assert [m.text for m in notes] == ["halted by the controller: outputs 0 V, brakes set"]
    assert int(notes[0].severity) == 1
    # the world model says so; nothing ran while halted, and the halted frames are not "missed"
    assert bool(sim.rt.wm.get("runtime.halted"))
    assert sim.rt.missed_frames == 0


def test_step_n_runs_exactly_n_frames_and_publishes_their_trace(powered):
    sim = powered
    _halt(sim)
    sim.step(20)
    before = sim.rt.frames_run
    sim.step(50)
    assert sim.rt.frames_run == before  # halted: no frames
    for n in (1, 7):
        before = sim.rt.frames_run
        code, text = sim.request(Request.STEP, n)
        assert code == Response.COMPLETE, text
        assert f"{n} frame(s) run" in text
        sim.step(30)
        assert sim.rt.frames_run - before == n
        trace = bytes(sim.rt.wm.get("runtime.step_trace")).rstrip(b"\0").decode().splitlines()
        assert trace[0].split()[:2] == ["frame", "t"] and len(trace) == 1 + n
        frames = [int(line.split()[0]) for line in trace[1:]]
        assert frames == list(range(frames[0], frames[0] + n))  # one per service frame, in order
    assert _state(sim) == ServiceState.HALTED and sim.svc.guard.trips == 0
    assert np.all(sim.dac_volts() == 0.0)  # single steps keep the outputs held safe
    assert sim.rt.all_status(S.START_UP_COMPLETE)  # the layers did not see a fault
    assert int(sim.rt.wm.get("runtime.step_frames")) == 8


def test_step_refused_when_running_or_out_of_range(powered):
    code, text = powered.request(Request.STEP, 1)
    assert code == Response.REFUSED and "not halted" in text
    _halt(powered)
    code, text = powered.request(Request.STEP, MAX_STEP_FRAMES + 1)
    assert code == Response.REFUSED and f"1..{MAX_STEP_FRAMES}" in text


def test_resume_needs_an_explicit_rearm_then_flies_again(powered):
    sim = powered
    _moving(sim)
    _halt(sim)
    sim.step(100)
    q_halt = sim.joint_angles_rad()[YAW]
    code, text = sim.request(Request.RESUME)  # no re-arm
    assert code == Response.REFUSED and "explicit re-arm" in text
    sim.step(50)
    assert sim.rt.halted and _state(sim) == ServiceState.HALTED
    code, text = sim.request(Request.RESUME, 1)
    assert code == Response.COMPLETE and "re-armed" in text, text
    assert not sim.rt.halted and _state(sim) == ServiceState.ARMED
    goal = sim.joint_angles_rad().copy()
    goal[YAW] = q_halt + 0.2
    sim.rt.set_joint_goal(goal)
    sim.step(960)  # 3 s
    assert abs(sim.joint_angles_rad()[YAW] - (q_halt + 0.2)) < 0.01  # it flies again
    assert sim.rt.all_status(S.START_UP_COMPLETE)
    assert sim.svc.guard.trips == 0 and sim.rt.missed_frames == 0
    assert not sim.rt.daq.fault_bits


def test_a_halted_controller_that_stops_holding_is_a_watchdog_fault(powered):
    """HALTED is not a way to hide a dead controller: its heartbeat is still watched."""
    sim = powered
    _halt(sim)
    sim.step(10)
    sim.controller_enabled = False
    sim.step(WATCHDOG_FRAMES + 3)
    assert _state(sim) == ServiceState.FAULT
    assert sim.svc.fault_code == FAULT_WATCHDOG and "(halted)" in sim.svc.guard.reason
    assert np.all(sim.dac_volts() == 0.0)


def test_halt_powered_down_then_resume_and_power_up(sim):
    _halt(sim)
    sim.step(20)
    assert _state(sim) == ServiceState.HALTED and sim.svc.guard.trips == 0
    code, text = sim.request(Request.RESUME, 1)
    assert code == Response.COMPLETE and "not armed" in text
    sim.step(5)
    assert _state(sim) == ServiceState.SAFE
    sim.power_up(max_frames=400)
    assert _state(sim) == ServiceState.ARMED


def test_release_halt_on_exit_leaves_the_service_safe(powered):
    sim = powered
    _halt(sim)
    sim.step(10)
    sim.rt.release_halt()
    sim.controller_enabled = False  # the process is gone
    sim.step(100)
    assert _state(sim) == ServiceState.SAFE and sim.svc.guard.trips == 0


@pytest.mark.parametrize("kind", [Request.HALT, Request.STEP, Request.RESUME])
def test_frame_control_requests_are_not_system_updown_commands(powered, kind):
    """The request task leaves them to the frame control: no 'unknown request' refusal."""
    powered.request(kind, 1)
    powered.step(5)
    texts = [m.text for m in powered.rt.messages.recent(50, source="updown")]
    assert not any("unknown request" in t for t in texts)


# --- pfma controller halt | step [N] | resume --rearm ---------------------------------------
@pytest.fixture
def shm_powered(monkeypatch):
    """A powered-up simulated system whose world model is in shared memory; the CLI's
    real-time wait for an answer steps the simulator one frame per poll (deterministic)."""
    from controller.worldmodel import WorldModel
    from sim.system import SystemSimulator
    from tests.controller import _wm_support as sup
    import tools.console.control as control
    monkeypatch.delenv("PFMA_WM_KEY", raising=False)
    name = sup.unique_name()
    s = SystemSimulator(wm_name=name)
    s.step(10)
    s.power_up(max_frames=400)
    monkeypatch.setattr(control.time, "sleep", lambda _s: s.step(1))
    yield s, name
    s.close()
    WorldModel.remove_segment(name)


def _pfma(capsys, *argv):
    from tools.cli import main
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def test_cli_halt_step_resume_on_a_running_controller(shm_powered, capsys):
    sim, name = shm_powered
    rc, out, err = _pfma(capsys, "controller", "halt", "--wm", name)
    assert rc == 0 and err == "" and "HALT: halted after frame" in out and "-> COMPLETE" in out
    sim.step(30)
    assert _state(sim) == ServiceState.HALTED and sim.svc.guard.trips == 0
    before = sim.rt.frames_run
    rc, out, err = _pfma(capsys, "controller", "step", "3", "--wm", name)
    assert rc == 0 and err == ""
    lines = out.splitlines()
    assert "SINGLE STEP: 3 frame(s) run" in lines[0]
    assert lines[1].split()[:2] == ["frame", "t"] and len(lines) == 5  # answer, header, 3 frames
    assert sim.rt.frames_run - before == 3
    rc, out, err = _pfma(capsys, "controller", "resume", "--wm", name)
    assert rc == 1 and "explicit re-arm" in out and "-> REFUSED" in out
    rc, out, err = _pfma(capsys, "controller", "resume", "--rearm", "--wm", name)
    assert rc == 0 and "re-armed" in out
    sim.step(10)
    assert _state(sim) == ServiceState.ARMED and not sim.rt.halted


def test_cli_frame_control_without_a_controller_is_one_message(capsys):
    rc, out, err = _pfma(capsys, "controller", "halt", "--wm", "pfma_wm_nobody_here")
    assert rc == 1 and out == ""
    assert err.startswith("pfma controller halt: no world model 'pfma_wm_nobody_here'")
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("argv, says", [
    (("halt", "5"), "takes no frame count"),
    (("step", "0"), "N must be 1.."),
    (("step", "--rearm"), "--rearm belongs to resume"),
])
def test_cli_frame_control_usage_mistakes_exit_2(capsys, argv, says):
    rc, out, err = _pfma(capsys, "controller", *argv, "--wm", "pfma_wm_nobody_here")
    assert rc == 2 and says in err and "Traceback" not in err


# --- found while halting a live controller on a loaded host ------------------------------------
def test_error_reset_after_a_missed_servo_period_shuts_down_and_powers_up_again(powered):
    """A servo fault for missed periods (code 12) is an event: nothing cleared its flag and
    the tables reset a layer only once its fault is gone, so ERROR RESET hung with the servo
    in ERROR (seen live: a third process starting on a 2-core host)."""
    from controller.servo import ERR_MISSED
    sim, rt = powered, powered.rt
    sim.controller_steps = lambda f: 0 if f % 100 < 3 else 1  # 3 frames missed (9 ms: no watchdog trip)
    sim.step(100)
    sim.controller_steps = None
    sim.step(300)
    assert rt.status("servo") == S.ERROR and rt.servo.error_code == ERR_MISSED
    assert sim.svc.guard.trips == 0
    code, text = sim.request(Request.ERROR_RESET, max_frames=600)
    assert code == Response.COMPLETE, text
    assert rt.all_status(S.SHUT_DOWN)
    sim.power_up(max_frames=400)
    assert rt.all_status(S.START_UP_COMPLETE)


def test_error_reset_after_a_watchdog_trip_then_power_up_rearms(powered):
    """The service's FAULT is latched until a new arm request; Data Acquisition counted it as
    a fault even after withdrawing its own arm request, so ERROR RESET never finished and
    power up could not come."""
    from ioservice.service import FAULT_WATCHDOG
    sim, rt = powered, powered.rt
    sim.controller_enabled = False
    sim.step(WATCHDOG_FRAMES + 3)  # the controller stops: the watchdog trips
    sim.controller_enabled = True
    assert _state(sim) == ServiceState.FAULT and sim.svc.fault_code == FAULT_WATCHDOG
    sim.run_until(lambda: rt.status("updown") == S.ERROR, 100)
    sim.step(400)  # safe tasks finished
    code, text = sim.request(Request.ERROR_RESET, max_frames=600)
    assert code == Response.COMPLETE, text
    assert rt.all_status(S.SHUT_DOWN) and _state(sim) == ServiceState.FAULT  # latched until re-armed
    sim.power_up(max_frames=400)
    assert rt.all_status(S.START_UP_COMPLETE) and _state(sim) == ServiceState.ARMED
