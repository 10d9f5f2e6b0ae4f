"""Requests queue, each answered; a power-up, a power-down and an error reset stepped
frame by frame (issue 30 item 4, docs/controller.md "User requests", docs/console.md).

In simulated time with the system simulator; every request goes through the world model
(one keyed write of ``ui.request`` each), is taken by System Up/Down in order and answered
with its number in the answer log. The service keeps running: only the controller halts.
"""

from __future__ import annotations

import numpy as np
import pytest

from bit3.layout import ServiceState
from controller.daq_layer import ARM_TIMEOUT_S, INIT_TIMEOUT_S
from controller.decision import SHORT, Status
from controller.layers import QUEUE_SLOTS, Request, Response
from controller.servo import BRAKE_RELEASE_TIMEOUT_S
from controller.routes import route_request_arg
from sim.faults import FaultSet

S = Status
R = Response
#: the power-up sequence of report 2.2.6 as a layer with a subordinate goes through it (the
#: bottom layer, Data Acquisition, has no subordinate to wait for), up to START UP: there a
#: halted controller's Data Acquisition waits for the resume's re-arm
POWER_UP_SEEN = [S.SHUT_DOWN, S.INITIALIZATION_IN_PROGRESS, S.WAITING_FOR_SUBORDINATE_TO_INIT,
                 S.INITIALIZATION_COMPLETE, S.START_UP]
POWER_UP_SEEN_BOTTOM = [s for s in POWER_UP_SEEN if s != S.WAITING_FOR_SUBORDINATE_TO_INIT]


def _service(sim) -> ServiceState:
    return ServiceState(int(sim.client.read_inputs().service_state))


def _answer(sim, seq: int) -> tuple[int, str]:
    a = sim.rt.answer(seq)
    assert a is not None, f"request {seq} has no answer"
    return a


def _answers_in_order(sim) -> list[tuple[int, int, str]]:
    """The answer log, oldest first: (request number, code, text)."""
    wm = sim.rt.wm
    n = int(wm.get("ui.answer_count"))
    seqs, codes, texts = wm.get("ui.answer_seq"), wm.get("ui.answer_code"), wm.get("ui.answer_text")
    size = len(seqs)
    return [(int(seqs[j % size]), int(codes[j % size]), bytes(texts[j % size]).rstrip(b"\0").decode())
            for j in range(max(0, n - size), n)]


def _halt(sim) -> None:
    code, text = sim.request(Request.HALT)
    assert code == R.COMPLETE, text


def _step(sim, n: int = 1) -> list[str]:
    """One SINGLE STEP request of ``n`` frames; the last trace lines it published (no header)."""
    before = sim.rt.frames_run
    code, text = sim.request(Request.STEP, n)
    assert code == R.COMPLETE and f"{n} frame(s) run" in text, text
    assert sim.rt.frames_run - before == n
    lines = bytes(sim.rt.wm.get("runtime.step_trace")).rstrip(b"\0").decode().splitlines()
    assert lines[0].split()[:2] == ["frame", "t"]
    return lines[-n:] if len(lines) == 1 + n else lines[2:]  # a long run keeps its last lines


def _trace_statuses(line: str) -> list[str]:
    """The status of each layer in one trace line (``COMMAND>STATUS rN`` cells)."""
    cells = line.split("  ", 2)[-1].rsplit("  ", 1)[0].split(" | ")
    return [c.strip().lstrip("*").split(">")[1].split()[0] for c in cells]


def _held_safe(sim) -> None:
    assert _service(sim) == ServiceState.HALTED
    assert np.all(sim.dac_volts() == 0.0)  # every channel: rates and current limits 0 V (brakes set)
    assert sim.svc.guard.trips == 0


def _seen(history: list[dict], key: str) -> list[Status]:
    out: list[Status] = []
    for st in history:
        if not out or out[-1] != st[key]:
            out.append(st[key])
    return out


# --- power-up frame by frame -------------------------------------------------------------
def test_power_up_while_halted_walks_the_layers_frame_by_frame_with_outputs_safe(sim):
    rt = sim.rt
    _halt(sim)
    seq = rt.request(Request.POWER_UP)
    sim.step(50)  # halted: queued, not lost, nothing runs
    code, text = _answer(sim, seq)
    assert code == R.QUEUED and "halted" in text, text
    assert rt.all_status(S.SHUT_DOWN) and rt.updown.queued() == ((seq, Request.POWER_UP, 0),)
    assert [tuple(r) for r in rt.wm.get("ui.queue")[:2]] == [(seq, Request.POWER_UP, 0), (0, 0, 0)]
    history = [rt.statuses()]
    for _ in range(200):  # one frame per step
        (line,) = _step(sim)
        st = rt.statuses()
        history.append(st)
        # each frame's trace line says what the layers' tables decided in that frame
        assert _trace_statuses(line) == [SHORT[s] for s in st.values()]
        _held_safe(sim)
        if st["daq"] == S.START_UP:
            break
    assert _answer(sim, seq)[0] == R.IN_PROGRESS  # taken in the first stepped frame
    assert tuple(rt.wm.get("ui.active")) == (seq, Request.POWER_UP)
    for key in rt.statuses():
        assert _seen(history, key) == (POWER_UP_SEEN_BOTTOM if key == "daq" else POWER_UP_SEEN), key
    # arming waits for the resume: stepping on past every start-up time-out arms nothing, faults nothing
    frames = int((ARM_TIMEOUT_S + INIT_TIMEOUT_S + BRAKE_RELEASE_TIMEOUT_S) / sim.period_s) + 10
    _step(sim, frames)
    _held_safe(sim)
    assert rt.status("daq") == S.START_UP and rt.status("servo") == S.START_UP and rt.daq.arm_request
    assert not any(s == S.ERROR for s in rt.statuses().values()) and not rt.daq.fault_bits
    assert any("arming waits for resume --rearm" in m.text for m in rt.messages.recent(source="daq"))
    # resume --rearm completes the sequence
    code, text = sim.request(Request.RESUME, 1)
    assert code == R.COMPLETE and "re-armed" in text, text
    sim.run_until(lambda: _answer(sim, seq)[0] != R.IN_PROGRESS, 400)
    assert _answer(sim, seq) == (R.COMPLETE, "POWER UP: START UP COMPLETE")
    assert rt.all_status(S.START_UP_COMPLETE) and _service(sim) == ServiceState.ARMED and not rt.halted
    assert sim.svc.guard.trips == 0


def test_halted_during_the_brake_release_it_waits_for_the_resume(sim):
    """Halted after the arm, while the servo raises the current limits: the brakes stay set
    (outputs safe), the brake-release wait does not time out, the resume completes it."""
    rt = sim.rt
    rt.request(Request.POWER_UP)
    sim.run_until(lambda: rt.status("daq") == S.START_UP_COMPLETE, 400)
    _halt(sim)
    assert rt.status("servo") == S.START_UP and int(rt.wm.get("servo.brake_phase")) in (1, 2)
    _step(sim, int(BRAKE_RELEASE_TIMEOUT_S / sim.period_s) + 20)
    _held_safe(sim)
    assert rt.status("servo") == S.START_UP and not bool(rt.wm.get("daq.brakes_released"))
    code, text = sim.request(Request.RESUME, 1)
    assert code == R.COMPLETE and "re-armed" in text, text
    sim.run_until(lambda: rt.all_status(S.START_UP_COMPLETE), 400)
    assert _service(sim) == ServiceState.ARMED and sim.svc.guard.trips == 0


def test_power_down_while_halted_walks_the_layers_to_shut_down(powered):
    sim, rt = powered, powered.rt
    _halt(sim)
    seq = rt.request(Request.POWER_DOWN)
    sim.step(5)
    assert _answer(sim, seq)[0] == R.QUEUED and rt.all_status(S.START_UP_COMPLETE)
    history = [rt.statuses()]
    for _ in range(400):
        _step(sim)
        history.append(rt.statuses())
        _held_safe(sim)
        if rt.all_status(S.SHUT_DOWN):
            break
    for key in rt.statuses():
        assert _seen(history, key) == [S.START_UP_COMPLETE, S.SHUT_DOWN_IN_PROGRESS, S.SHUT_DOWN], key
    _step(sim)  # the request task sees SHUT DOWN in the frame after the table decided it
    assert _answer(sim, seq) == (R.COMPLETE, "POWER DOWN: SHUT DOWN")
    assert rt.daq.arm_request == 0
    code, text = sim.request(Request.RESUME, 1)  # nothing to re-arm: HALTED -> SAFE
    assert code == R.COMPLETE and "not armed" in text, text
    sim.step(5)
    assert _service(sim) == ServiceState.SAFE


def test_error_reset_while_halted_walks_the_layers_to_shut_down(powered):
    sim, rt = powered, powered.rt
    faults = FaultSet(sim.world)
    faults.inject("resolver-los:shoulder_pitch_angle")
    sim.run_until(lambda: rt.status("updown") == S.ERROR, 200)
    faults.clear("resolver-los:shoulder_pitch_angle")
    sim.step(400)  # the safe tasks finished
    _halt(sim)
    seq = rt.request(Request.ERROR_RESET)
    sim.step(5)
    assert _answer(sim, seq)[0] == R.QUEUED and rt.all_status(S.ERROR)
    history = [rt.statuses()]
    for _ in range(400):
        _step(sim)
        history.append(rt.statuses())
        _held_safe(sim)
        if rt.all_status(S.SHUT_DOWN):
            break
    for key in rt.statuses():
        assert _seen(history, key) == [S.ERROR, S.ERROR_RESET, S.SHUT_DOWN], key
    _step(sim)
    assert _answer(sim, seq) == (R.COMPLETE, "ERROR RESET: SHUT DOWN")


# --- cancellation --------------------------------------------------------------------------
def test_a_halt_cancels_the_requests_queued_before_it_never_run_later(sim):
    rt = sim.rt
    _halt(sim)
    up = rt.request(Request.POWER_UP)
    route = rt.request(Request.ROUTE, route_request_arg(1, 2))
    sim.step(3)
    assert [_answer(sim, s)[0] for s in (up, route)] == [R.QUEUED, R.QUEUED]
    code, text = sim.request(Request.HALT)
    assert code == R.COMPLETE and "already halted" in text
    for s, name in ((up, "POWER UP"), (route, "CAMERA ROUTE")):
        code, text = _answer(sim, s)
        assert code == R.CANCELLED and text.startswith(f"{name}: cancelled, never run: HALT (request "), text
    after = rt.request(Request.POWER_UP)  # queued after the HALT: not cancelled
    sim.step(3)
    assert _answer(sim, after)[0] == R.QUEUED and rt.updown.queued() == ((after, Request.POWER_UP, 0),)
    _step(sim, 5)
    assert _answer(sim, after)[0] == R.IN_PROGRESS and rt.status("updown") != S.SHUT_DOWN
    assert int(rt.wm.get("updown.route_request_seq")) == 0  # the cancelled route never went out
    assert [_answer(sim, s)[0] for s in (up, route)] == [R.CANCELLED, R.CANCELLED]


def test_a_power_down_cancels_the_requests_queued_before_it(powered):
    sim, rt = powered, powered.rt
    _halt(sim)
    route = rt.request(Request.ROUTE, route_request_arg(1, 3))
    reset = rt.request(Request.ERROR_RESET)
    down = rt.request(Request.POWER_DOWN)
    sim.step(3)
    for s in (route, reset):
        code, text = _answer(sim, s)
        assert code == R.CANCELLED and f"POWER DOWN (request {down}) came after it" in text, text
    assert _answer(sim, down)[0] == R.QUEUED and rt.updown.queued() == ((down, Request.POWER_DOWN, 0),)
    for _ in range(400):
        _step(sim)
        if _answer(sim, down)[0] in R.FINAL:
            break
    assert _answer(sim, down) == (R.COMPLETE, "POWER DOWN: SHUT DOWN") and rt.all_status(S.SHUT_DOWN)
    assert int(rt.wm.get("updown.route_request_seq")) == 0


def test_the_systems_error_fails_the_active_request_and_cancels_the_queued_ones(sim):
    rt = sim.rt
    _halt(sim)
    up = rt.request(Request.POWER_UP)
    for _ in range(200):
        _step(sim)
        if rt.status("daq") == S.INITIALIZATION_COMPLETE:
            break
    reset = rt.request(Request.ERROR_RESET)  # waits behind the POWER UP in progress
    sim.step(3)
    code, text = _answer(sim, reset)
    assert code == R.QUEUED and f"POWER UP {up} in progress" in text, text
    faults = FaultSet(sim.world)
    faults.inject("resolver-los:shoulder_pitch_angle")
    for _ in range(100):
        _step(sim)
        if rt.status("updown") == S.ERROR:
            break
    _step(sim, 2)
    assert _answer(sim, up) == (R.FAILED, "POWER UP: System Up/Down in ERROR")
    code, text = _answer(sim, reset)
    assert code == R.CANCELLED and "System Up/Down entered ERROR" in text, text
    assert rt.updown.queued() == ()
    _step(sim, 50)  # never run later: the system stays in ERROR
    assert rt.status("updown") == S.ERROR and _answer(sim, reset)[0] == R.CANCELLED
    # a reset asked for after the ERROR runs
    faults.clear("resolver-los:shoulder_pitch_angle")
    again = rt.request(Request.ERROR_RESET)
    for _ in range(400):
        _step(sim)
        if _answer(sim, again)[0] in R.FINAL:
            break
    assert _answer(sim, again) == (R.COMPLETE, "ERROR RESET: SHUT DOWN") and rt.all_status(S.SHUT_DOWN)


def test_a_power_down_supersedes_a_power_up_in_progress(sim):
    rt = sim.rt
    up = rt.request(Request.POWER_UP)
    sim.run_until(lambda: rt.status("updown") == S.START_UP, 400)
    code, text = sim.request(Request.POWER_DOWN)
    assert code == R.COMPLETE and text == "POWER DOWN: SHUT DOWN", text
    code, text = _answer(sim, up)
    assert code == R.CANCELLED and "POWER DOWN (request" in text and "supersedes it" in text, text
    assert rt.all_status(S.SHUT_DOWN)


# --- order and answers ---------------------------------------------------------------------
def test_power_up_and_a_step_in_one_segment_are_both_answered(sim):
    """The bug this fixes: one request slot; the STEP overwrote the POWER UP, never answered."""
    rt = sim.rt
    _halt(sim)
    up = rt.request(Request.POWER_UP)
    step = rt.request(Request.STEP, 1)
    assert step > up
    sim.step(4)
    assert _answer(sim, step)[0] == R.COMPLETE
    assert _answer(sim, up) == (R.IN_PROGRESS, "POWER UP (shoulder-roll index 0 deg: no sensor, "
                                                 "as set in joint.shoulder_roll_deg)")  # taken in the stepped frame
    assert rt.status("updown") == S.SHUT_DOWN  # its command reaches the table next frame
    _step(sim)
    assert rt.status("updown") == S.INITIALIZATION_IN_PROGRESS


def test_requests_wait_their_turn_and_are_answered_in_order(powered):
    """POWER DOWN then POWER UP in one segment: the power-up waits for the power-down's
    answer, then runs (a restart)."""
    sim, rt = powered, powered.rt
    down = rt.request(Request.POWER_DOWN)
    up = rt.request(Request.POWER_UP)
    sim.step(2)
    assert _answer(sim, down) == (R.IN_PROGRESS, "POWER DOWN")
    code, text = _answer(sim, up)
    assert code == R.QUEUED and text == "POWER UP: queued (1 ahead)", text
    assert [tuple(r) for r in rt.wm.get("ui.queue")[:1]] == [(up, Request.POWER_UP, 0)]
    assert tuple(rt.wm.get("ui.active")) == (down, Request.POWER_DOWN)
    sim.run_until(lambda: _answer(sim, up)[0] in R.FINAL, 800)
    assert _answer(sim, up) == (R.COMPLETE, "POWER UP: START UP COMPLETE")
    finals = [(s, c) for s, c, _ in _answers_in_order(sim) if c in R.FINAL and s in (down, up)]
    assert finals == [(down, R.COMPLETE), (up, R.COMPLETE)]
    assert rt.response() == (up, R.COMPLETE)  # ui.response: the newest request's answer


def test_a_full_queue_refuses_with_a_clear_answer_and_the_rest_run_in_order(sim):
    rt = sim.rt
    _halt(sim)
    seqs = [rt.request(Request.ROUTE, route_request_arg(1 + i % 2, 1 + i % 3)) for i in range(QUEUE_SLOTS + 1)]
    sim.step(3)
    assert [_answer(sim, s)[0] for s in seqs[:-1]] == [R.QUEUED] * QUEUE_SLOTS
    code, text = _answer(sim, seqs[-1])
    assert code == R.REFUSED and text.startswith(f"CAMERA ROUTE: request queue full ({QUEUE_SLOTS} waiting: "
                                                 f"CAMERA ROUTE {seqs[0]}, "), text
    assert [int(r[0]) for r in rt.wm.get("ui.queue")] == seqs[:-1]
    code, text = sim.request(Request.RESUME, 1)
    assert code == R.COMPLETE, text
    sim.run_until(lambda: all(_answer(sim, s)[0] in R.FINAL for s in seqs[:-1]), 2000)
    # taken in order, one route at a time, each answered
    taken = [s for s, c, _ in _answers_in_order(sim) if c == R.IN_PROGRESS and s in seqs]
    assert taken == sorted(taken) and set(taken) <= set(seqs[:-1])
    assert [_answer(sim, s)[0] for s in seqs[:-1]] == [R.COMPLETE] * QUEUE_SLOTS
    assert rt.updown.queued() == ()


def test_an_unknown_request_kind_is_refused_naming_the_kinds(sim):
    seq = sim.rt.request(99)
    sim.step(2)
    code, text = _answer(sim, seq)
    assert code == R.REFUSED and text.startswith("unknown request 99 (kinds: 1 POWER UP, 2 POWER DOWN"), text


@pytest.mark.parametrize("kind", [Request.POWER_UP, Request.ROUTE])
def test_requests_while_running_are_taken_in_the_frame_they_arrive_without_queued(sim, kind):
    """Nothing waits, nothing is said twice: the running system takes it at once."""
    seq = sim.rt.request(kind, route_request_arg(1, 2) if kind == Request.ROUTE else 0)
    sim.step(2)
    assert [c for s, c, _ in _answers_in_order(sim) if s == seq][0] == R.IN_PROGRESS


# --- pfma controller power-up | power-down | reset (the Global Commands from the shell) --------
# (shm_sim: tests/conftest.py)
def _pfma(capsys, *argv):
    from tools.cli import main
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def test_cli_power_up_while_halted_then_steps_then_resume_rearm(shm_sim, capsys):
    sim, name = shm_sim
    rt = sim.rt
    rc, out, err = _pfma(capsys, "controller", "halt", "--wm", name)
    assert rc == 0 and "-> COMPLETE" in out, (out, err)
    rc, out, err = _pfma(capsys, "controller", "power-up", "--wm", name)
    assert rc == 0 and err == "", (out, err)
    roll, brake, answer, hint = out.splitlines()
    assert roll.startswith("POWER UP with the shoulder-roll index 0 deg (joint.shoulder_roll_deg")
    assert brake.startswith("the power-up tests every brake: each joint moves a little out and back")
    assert answer.endswith("POWER UP: queued (halted: taken at the next frame run, a step or the resume) -> QUEUED")
    assert hint.startswith("the controller is halted: `pfma controller step [N]` runs the POWER UP frame by frame "
                           "and `pfma controller resume --rearm` arms the outputs")
    assert rt.all_status(S.SHUT_DOWN)
    rc, out, err = _pfma(capsys, "controller", "step", "40", "--wm", name)
    assert rc == 0 and "SINGLE STEP: 40 frame(s) run" in out
    lines = out.splitlines()
    assert _trace_statuses(lines[-1]) == [SHORT[s] for s in rt.statuses().values()]
    assert rt.status("updown") in (S.WAITING_FOR_SUBORDINATE_TO_INIT, S.INITIALIZATION_COMPLETE, S.START_UP)
    _held_safe(sim)
    rc, out, err = _pfma(capsys, "controller", "resume", "--rearm", "--wm", name)
    assert rc == 0 and "RESUME: resumed" in out, (out, err)
    sim.run_until(lambda: rt.all_status(S.START_UP_COMPLETE), 400)
    assert _service(sim) == ServiceState.ARMED
    # running: the command waits for the final answer
    rc, out, err = _pfma(capsys, "controller", "power-down", "--wm", name)
    assert rc == 0 and out.strip().endswith("POWER DOWN: SHUT DOWN -> COMPLETE"), (out, err)
    assert rt.all_status(S.SHUT_DOWN)
    rc, out, err = _pfma(capsys, "controller", "reset", "--wm", name)
    assert rc == 1 and out.strip().endswith("ERROR RESET: system is SHUT DOWN, not ERROR -> REFUSED"), (out, err)
    rc, out, err = _pfma(capsys, "controller", "power-up", "--wm", name)
    assert rc == 0 and out.strip().endswith("POWER UP: START UP COMPLETE -> COMPLETE"), (out, err)


def test_cli_reset_after_an_error_shuts_down(shm_sim, capsys):
    sim, name = shm_sim
    rt = sim.rt
    sim.power_up(max_frames=400)
    faults = FaultSet(sim.world)
    faults.inject("resolver-los:shoulder_pitch_angle")
    sim.run_until(lambda: rt.status("updown") == S.ERROR, 200)
    faults.clear("resolver-los:shoulder_pitch_angle")
    sim.step(400)
    rc, out, err = _pfma(capsys, "controller", "reset", "--wm", name)
    assert rc == 0 and out.strip().endswith("ERROR RESET: SHUT DOWN -> COMPLETE"), (out, err)
    assert rt.all_status(S.SHUT_DOWN)


@pytest.mark.parametrize("argv, says", [
    (("power-up", "5"), "takes no frame count"),
    (("reset", "--rearm"), "--rearm belongs to resume"),
    (("power-down", "--wm", "none"), "needs the running controller's world model"),
])
def test_cli_power_requests_usage_mistakes_exit_2(capsys, argv, says):
    rc, out, err = _pfma(capsys, "controller", *argv)
    assert rc == 2 and says in err and "Traceback" not in err


def test_cli_power_up_without_a_controller_is_one_message(capsys):
    rc, out, err = _pfma(capsys, "controller", "power-up", "--wm", "pfma_wm_nobody_here")
    assert rc == 1 and out == ""
    assert err.startswith("pfma controller power-up: no world model 'pfma_wm_nobody_here'")
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
