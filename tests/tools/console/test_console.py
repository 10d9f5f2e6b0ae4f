"""The operator console (issue 18 items 1, 3, 6; docs/console.md) against the system
simulator in simulated time: Textual's ``App.run_test()`` with Pilot key presses. The
console's timer is off (``auto_refresh=False``): a test steps the simulator, then
redraws the areas itself, so nothing depends on the wall clock."""

from __future__ import annotations

import time


import numpy as np
import pytest

from bit3.client import Client
from bit3.layout import ServiceState
from controller.decision import Status
from tools.console import view
from tools.console.app import MessagesScreen
from tests.tools.console._pilot import frames, kept_messages, run_app


def test_five_areas_titled_as_the_report_names_them(console):
    async def body(pilot):
        titles = {w.id: str(w.border_title) for w in console.query(".area")}
        assert titles == {"local-area": "Local Status", "world-area": "World Status", "messages-area": "Messages",
                          "commands-area": "Local Commands", "global-area": "Global Commands"}
        assert len(console.query(".area Static")) == 5  # one text widget per area
        assert console.area_text("world").startswith("SIMULATED RACK")
    run_app(console, body)


def test_power_up_from_the_global_commands(sim, console):
    async def body(pilot):
        assert "SHUT DOWN" in console.area_text("local")
        await pilot.press("u", "y")
        frames(sim, console, 300)
        assert sim.rt.all_status(Status.START_UP_COMPLETE)
        local = console.area_text("local")
        assert local.count("START UP COMPLETE") >= 7
        assert "service ARMED" in console.area_text("world")
        assert "POWER UP: START UP COMPLETE -> COMPLETE" in console.area_text("global")
        assert "request 1: POWER UP sent" in kept_messages(console)
    run_app(console, body)


def test_halt_step_resume_from_the_console(sim, console):
    async def body(pilot):
        sim.power_up(max_frames=400)
        frames(sim, console, 20)
        await pilot.press("h")
        frames(sim, console, 40)
        world = console.area_text("world")
        ctl = next(ln for ln in world.splitlines() if ln.startswith("controller ("))
        assert "service HALTED" in world and "HALTED" in ctl
        assert "brakes set (commanded)" in world and "watchdog ok" in world  # halted: the service's word
        assert np.all(sim.dac_volts() == 0.0) and sim.svc.guard.trips == 0
        before = sim.rt.frames_run
        await pilot.press("s")
        frames(sim, console, 20)
        assert sim.rt.frames_run - before == 1
        assert "SINGLE STEP: 1 frame(s) run" in console.area_text("global")
        assert "trace " in console.area_text("messages")  # the step's trace lines
        before = sim.rt.frames_run
        await pilot.press("S")
        frames(sim, console, 40)
        assert sim.rt.frames_run - before == 10
        await pilot.press("r")  # no re-arm given
        frames(sim, console, 10)
        assert "explicit re-arm" in console.area_text("global") and "REFUSED" in console.area_text("global")
        assert sim.rt.halted
        await pilot.press("a")
        await pilot.pause()
        assert "[RE-ARM GIVEN]" in console.area_text("global")
        await pilot.press("r")
        frames(sim, console, 30)
        assert "resumed at frame" in console.area_text("global")
        assert "[RE-ARM GIVEN]" not in console.area_text("global")  # one re-arm, one resume
        assert not sim.rt.halted
        assert ServiceState(int(sim.client.read_inputs().service_state)) == ServiceState.ARMED
        assert sim.rt.all_status(Status.START_UP_COMPLETE)
    run_app(console, body)


def test_power_up_sent_while_halted_is_followed_through_the_steps_to_its_answer(sim, console):
    """Issue 30 item 4: POWER UP and a single step sent in one refresh are two requests, each
    followed to its answer; the steps walk the power-up, the resume with re-arm completes it."""
    async def body(pilot):
        await pilot.press("h")
        frames(sim, console, 5)
        await pilot.press("u", "y", "s")  # y: the shoulder-roll index confirmed (docs/console.md)
        frames(sim, console, 10)
        assert len(console.pending) == 1  # the step answered; the power-up waits for the resume
        msgs = console.area_text("messages")
        assert "POWER UP: queued (halted" in msgs and "SINGLE STEP: 1 frame(s) run" in msgs
        for _ in range(12):
            await pilot.press("S")
            frames(sim, console, 20)
        assert sim.rt.status("updown") not in (Status.SHUT_DOWN, Status.ERROR)
        assert np.all(sim.dac_volts() == 0.0) and sim.rt.halted
        await pilot.press("a", "r")
        frames(sim, console, 300)
        assert sim.rt.all_status(Status.START_UP_COMPLETE)
        assert "POWER UP: START UP COMPLETE -> COMPLETE" in console.area_text("messages")
        assert console.pending == []
    run_app(console, body)


def _selected(console) -> tuple[str, str]:
    """The layer each area shows as selected: Local Status's ``>`` row, Local Commands' heading."""
    row = next(ln for ln in console.area_text("local").splitlines() if ln.startswith("> "))
    status = next(title for _, title in view.LAYERS if row[2:].startswith(title))
    command = console.area_text("commands").splitlines()[0].partition(": command ")[0]
    return status, command


def test_local_status_and_local_commands_move_independently(sim, console):
    """Issue 33 item 7 (report 2.2.8): left/right move the layer Local Status details, up/down
    the layer Local Commands shows (the layer tree); neither moves the other, across refreshes."""
    titles = [title for _, title in view.LAYERS]

    async def body(pilot):
        assert console.area_text("local").splitlines()[0].split() == ["LAYER", "STATE", "COMMAND"]
        assert _selected(console) == (titles[0], titles[0])
        await pilot.press("right", "right")  # Local Status only
        frames(sim, console, 5)
        await pilot.pause()
        assert _selected(console) == (titles[2], titles[0])
        assert console.area_text("local").splitlines()[3].startswith("> Trajectory Planner")
        assert f"{titles[2]}: row " in console.area_text("local")  # the detail follows Local Status's layer
        assert console.area_text("commands").splitlines()[1] == "  sent by the user requests"
        await pilot.press("down")  # Local Commands only
        frames(sim, console, 5)
        await pilot.pause()
        assert _selected(console) == (titles[2], titles[1])
        assert console.area_text("commands").splitlines()[1] == f"  sent by {titles[0]}"
        await pilot.press("up", "up", "up")  # round the tree: 1 - 3 = Servo Control
        await pilot.pause()
        assert _selected(console) == (titles[2], titles[5])
        assert "servo.kp_per_s *" in console.area_text("commands")  # Servo's settable variables
        await pilot.press("left", "left", "left")  # round the layers: 2 - 3 = Data Acquisition
        await pilot.pause()
        assert _selected(console) == (titles[6], titles[5])
        assert console.area_text("local").splitlines()[7].startswith("> Data Acquisition")
        assert "hardware checks:" in console.area_text("local")
        assert console.status_layer == 6 and console.command_layer == 5
    run_app(console, body)


@pytest.mark.realtime
def test_record_starts_and_stops_a_recorder_of_this_system(console, tmp_path, monkeypatch):
    """`c` starts a `pfma record` process on the console's buffer (and world model); `c`
    again stops it cleanly: the MCAP file is complete (its summary readable)."""
    monkeypatch.chdir(tmp_path)
    from tools.recording.reader import read_metadata

    async def body(pilot):
        await pilot.press("c")
        await pilot.pause()
        rec = console.recording
        assert rec is not None and rec.active
        assert f"recording to {rec.path}" in console.area_text("messages")
        t_end = time.monotonic() + 20
        while not (tmp_path / rec.path).exists() and time.monotonic() < t_end:  # the recorder starting
            time.sleep(0.05)  # polling a subprocess, bounded
        await pilot.press("c")
        await pilot.pause()
        assert not rec.active
        assert f"recording stopped: {rec.path}" in console.area_text("messages")
        assert read_metadata(tmp_path / rec.path)  # a whole file, summary written
    run_app(console, body)


def test_messages_screen_shows_what_the_console_keeps_newest_first(sim, console):
    async def body(pilot):
        await pilot.press("u", "y")
        frames(sim, console, 200)
        await pilot.press("m")
        await pilot.pause()
        assert isinstance(console.screen, MessagesScreen)
        head, *lines = console.screen.text().splitlines()
        assert head.startswith(f"{len(lines)} of {len(console.sources.messages)} messages, newest first")
        times = [float(ln.split()[0]) for ln in lines]
        assert times == sorted(times, reverse=True) and 3 <= len(lines) <= view.MESSAGES_KEPT
        await pilot.press("escape")
        await pilot.pause()
        assert not isinstance(console.screen, MessagesScreen)
    run_app(console, body)


def test_the_console_claims_nothing(sim, console):
    async def body(pilot):
        await pilot.press("u", "y", "h")
        frames(sim, console, 50)
    run_app(console, body)
    owners = sim.client.owners()
    assert owners["commands"].pid == owners["inputs"].pid  # still the simulator's controller
    assert owners["commands"].name == "controller"


def test_a_live_buffer_that_does_not_say_is_not_called_real(sim):
    client = Client.attach(sim.name, layout=sim.rig.layout)
    try:
        text = view.world_status(view.Sources(client, sim.rt.wm).read(), "unknown")
    finally:
        client.close()
    assert text.startswith("rack: unknown") and "real hardware" not in text


# --- pfma console: no service, no controller -------------------------------------------------
def _pfma(capsys, *argv):
    from tools.cli import main
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def test_no_service_is_one_message_and_exit_1(capsys):
    rc, out, err = _pfma(capsys, "console", "--buffer", "pfma_console_nobody")
    assert rc == 1 and out == "" and "Traceback" not in err
    assert err.startswith("pfma console: no service buffer /dev/shm/pfma_console_nobody")
    assert len(err.strip().splitlines()) == 1


def test_no_controller_is_one_message_and_exit_1(sim, capsys):
    rc, out, err = _pfma(capsys, "console", "--buffer", sim.name, "--wm", "pfma_console_no_wm")
    assert rc == 1 and out == "" and "Traceback" not in err
    assert err.startswith("pfma console: no world model 'pfma_console_no_wm'")
    assert len(err.strip().splitlines()) == 1


# --- make run: the whole simulated system -----------------------------------------------------
def test_simulated_system_flies_the_demo_path_and_stops_at_0_v():
    """What `make run` runs behind the console (stepped here by hand, not by its thread)."""
    from tools.console.simrun import SimulatedSystem
    system = SimulatedSystem()
    try:
        sim = system.sim
        q0 = sim.joint_angles_rad().copy()
        for _ in range(500):  # 6.25 s simulated: powered up, first pose reached
            sim.step(4)
            system._fly()
        assert sim.rt.all_status(Status.START_UP_COMPLETE)
        assert np.abs(sim.joint_angles_rad() - q0).max() > 0.1  # it flies
        volts = system.stop()
        assert np.all(volts == 0.0)
        assert ServiceState(int(sim.client.read_inputs().service_state)) == ServiceState.STOPPED
        assert sim.svc.guard.trips == 0
    finally:
        system.close()


def test_simulated_system_stops_safe_while_halted():
    from controller.layers import Request
    from tools.console.simrun import SimulatedSystem
    system = SimulatedSystem(demo=False)
    try:
        system.sim.power_up(max_frames=400)
        assert system.sim.request(Request.HALT)[0] == 2
        volts = system.stop()
        assert np.all(volts == 0.0) and system.sim.svc.guard.trips == 0
    finally:
        system.close()


def test_world_model_browser_by_area_and_live(sim, console):
    from tools.console.app import BrowserScreen

    async def body(pilot):
        await pilot.press("w")
        await pilot.pause()
        scr = console.screen
        assert isinstance(scr, BrowserScreen)
        text = scr.text()
        assert "area task_io:" in text and "Enter/e modify" in text
        rows = text.splitlines()[3:-1]  # then the last write's status line
        assert 1 <= len(rows) <= 30 and all(sim.rt.wm.spec(r[2:].split()[0]).area == "task_io" for r in rows)
        assert rows[0].startswith("> ") and not any(r.startswith(">") for r in rows[1:])  # the cursor
        await pilot.press("right")
        await pilot.pause()
        assert "area task_status:" in scr.text()

        def frames_row():  # on whichever page of the area it falls (more than 30 rows: pagedown)
            return next((ln for ln in scr.text().splitlines() if ln[2:].startswith("runtime.frames ")), None)
        for _ in range(5):
            if frames_row() is not None:
                break
            await pilot.press("pagedown")
            await pilot.pause()
        row = frames_row()
        assert row is not None
        sim.step(200)
        sim.rt.publish_stats()
        sim.step(2)
        console.refresh_areas()  # the 10 Hz tick redraws the browser too
        await pilot.pause()
        row2 = frames_row()
        assert row2 is not None and row2 != row and int(row2.split()[-1]) >= 200  # live
        await pilot.press("escape")
        await pilot.pause()
        assert not isinstance(console.screen, BrowserScreen)
    run_app(console, body)
