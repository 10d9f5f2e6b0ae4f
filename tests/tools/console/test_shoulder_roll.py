"""The console and the shoulder-roll index (issue 30 item 2; docs/console.md "Power-up and the
shoulder-roll index"): ``u`` asks the operator to confirm the index before POWER UP (the
joint has no sensor), ``p`` from that question opens the parameters on the index, whose
editor refuses anything but an index position, and World Status shows the index. Against the
system simulator with its arm pinned at +45 deg, in simulated time (the console's timer off)."""

from __future__ import annotations

import re

import pytest

from bit3.client import Client
from controller.decision import Status
from sim.system import SystemSimulator
from tools.console import view
from tools.console.app import ConsoleApp, EditScreen, ParamScreen, PowerUpScreen
from tools.console.control import ControllerLink
from tests.tools.console._pilot import frames, kept_messages, run_app


@pytest.fixture
def sim45():
    s = SystemSimulator(shoulder_roll_deg=45)
    s.step(10)
    yield s
    s.close()


@pytest.fixture
def console45(sim45):
    client = Client.attach(sim45.name, layout=sim45.rig.layout)
    yield ConsoleApp(view.Sources(client, sim45.rt.wm, rack="simulated"), ControllerLink(sim45.rt.wm),
                     auto_refresh=False)
    client.close()


def _world_roll_line(console) -> str:
    return next(ln for ln in console.area_text("world").splitlines() if ln.startswith("shoulder roll"))


def test_power_up_asks_for_the_index_and_sends_nothing_until_confirmed(sim45, console45):
    sim, console = sim45, console45

    async def body(pilot):
        frames(sim, console, 1)
        assert _world_roll_line(console) == "shoulder roll +45 deg (indexed by hand, no sensor)"
        await pilot.press("u")
        await pilot.pause()
        assert isinstance(console.screen, PowerUpScreen)
        assert "is the shoulder roll pinned at +45 deg?" in console.screen.text()
        await pilot.press("n")  # cancel
        frames(sim, console, 20)
        assert int(sim.rt.wm.get("ui.request_seq")) == 0 and sim.rt.status() == Status.SHUT_DOWN
        assert "POWER UP cancelled (the shoulder-roll index was not confirmed)" in console.area_text("messages")
        await pilot.press("u", "y")
        frames(sim, console, 300)
        assert sim.rt.all_status(Status.START_UP_COMPLETE)
        msgs = kept_messages(console)
        assert "shoulder-roll index +45 deg confirmed by the operator" in msgs
        assert re.search(r"request \d+: POWER UP sent", msgs), msgs  # (the sim set the index by a user write)
        assert _world_roll_line(console) == "shoulder roll +45 deg (indexed by hand, no sensor)"
    run_app(console, body)


def test_p_from_the_question_edits_the_index_which_refuses_other_values(sim45, console45):
    sim, console = sim45, console45

    async def body(pilot):
        await pilot.press("u", "p")
        await pilot.pause()
        scr = console.screen
        assert isinstance(scr, ParamScreen) and scr.selected() == ("joint.shoulder_roll_deg", None)
        assert "> joint.shoulder_roll_deg  deg" in scr.text()
        await pilot.press("enter")
        await pilot.pause()
        assert isinstance(console.screen, EditScreen)
        await pilot.press("home", "ctrl+k", "3", "0", "enter")
        await pilot.pause()
        status = str(console.screen.query_one("#edit-status").render())
        assert status == "not sent: joint.shoulder_roll_deg: 30 deg is not one of its values (-90, -45, 0, 45, 90 deg)"
        await pilot.press("home", "ctrl+k", "-", "4", "5", "enter", "enter")  # checked, then confirmed
        await pilot.pause()
        frames(sim, console, 2)
        await pilot.pause()
        assert sim.rt.wm.get("joint.shoulder_roll_deg") == -45.0
        await pilot.press("escape")
        frames(sim, console, 1)
        assert _world_roll_line(console) == "shoulder roll -45 deg (indexed by hand, no sensor)"
        assert sim.rt.status() == Status.SHUT_DOWN  # nothing was powered up on the way
    run_app(console, body)
