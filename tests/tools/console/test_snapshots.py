"""Snapshot tests of the console's screens (issue 18 item 7; pytest-textual-snapshot): the
primary display powered up, halted, the messages screen, the world-model browser, the
parameter display and the force displays, over
the system simulator in simulated time (the same frames give the same text). Update after
an intended change with ``pytest tests/tools/console --snapshot-update`` and look at the
SVGs."""

from __future__ import annotations

import pytest

from bit3.client import Client
from sim.system import SystemSimulator
from tools.console import view
from tools.console.app import ConsoleApp
from tools.console.control import ControllerLink

SIZE = (180, 50)


@pytest.fixture
def rig():
    sim = SystemSimulator()
    sim.step(10)
    client = Client.attach(sim.name, layout=sim.rig.layout)
    app = ConsoleApp(view.Sources(client, sim.rt.wm, rack="simulated"), ControllerLink(sim.rt.wm),
                     auto_refresh=False)
    yield sim, app
    client.close()
    sim.close()


def _then(sim, app, frames: int, keys: tuple[str, ...] = ()):
    async def run_before(pilot):
        for k in keys:
            await pilot.press(k)
            sim.step(frames)
            app.refresh_areas()
        if not keys:
            sim.step(frames)
            app.refresh_areas()
        await pilot.pause()
    return run_before


def test_primary_display_powered_up(rig, snap_compare):
    sim, app = rig
    assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 300, ("u",)))


def test_primary_display_halted(rig, snap_compare):
    sim, app = rig
    assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 300, ("u", "h", "s")))


def test_messages_screen(rig, snap_compare):
    sim, app = rig
    assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 300, ("u", "m")))


def test_world_model_browser(rig, snap_compare):
    sim, app = rig
    assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 300, ("u", "w")))


def test_parameter_display(rig, snap_compare):
    sim, app = rig
    assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 300, ("u", "p")))


def test_force_displays(rig, snap_compare):
    sim, app = rig
    sim.world.ft.set_load((12.0, -4.0, 30.0), (0.5, -0.25, 0.125))
    assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 40, ("u", "u", "u", "u", "f")))
