"""Snapshot tests of the console's screens (issue 18 item 7; pytest-textual-snapshot): the
primary display powered up, halted, the messages screen, the world-model browser, the
parameter display, the force displays, the camera routes and a live menu from a TOML file,
over the system simulator in simulated time (the same frames give the same text). The
camera and menu tests also assert on the rendered text (what the terminal shows:
``_pilot.screen_text``), so a wrong value fails by its words as well as by the SVG. Update
after an intended change with ``pytest tests/tools/console --snapshot-update`` and look at
the SVGs."""

from __future__ import annotations

import pytest

from bit3.client import Client
from sim.system import SystemSimulator
from tools.console import view
from tools.console.app import ConsoleApp
from tools.console.control import ControllerLink
from tests.tools.console._pilot import screen_text

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
    assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 300, ("u", "y")))


SIZES = [(80, 24), (120, 40), (200, 50)]  #: issue 29 item 4: the smallest usable, clean, wide


@pytest.mark.parametrize("size", SIZES, ids=[f"{w}x{h}" for w, h in SIZES])
def test_primary_display_at_size(rig, snap_compare, size):
    """Powered up, then halted with one step: every area titled on the terminal, the newest
    message in view, the joints measured (the halted line) at every size."""
    sim, app = rig

    async def run_before(pilot):
        await _then(sim, app, 300, ("u", "y", "h", "s"))(pilot)
        await pilot.pause()
        text = screen_text(app)
        assert all(title in text for title in view.AREAS)
        newest = max(app.sources.messages, key=lambda m: m.t_s)
        assert newest.text[:30] in text
        if size != (80, 24):  # at 80x24 World Status pages for the rest
            assert "HALTED: the motion below is measured" in text and "rad/s tach" in text
    assert snap_compare(app, terminal_size=size, run_before=run_before)


def test_messages_screen_80x24(rig, snap_compare):
    """The Messages screen at 80x24: newest first, its head says the filters."""
    sim, app = rig

    async def run_before(pilot):
        await _then(sim, app, 300, ("u", "y", "h", "m"))(pilot)
        rows = screen_text(app).splitlines()
        assert rows[0].strip().startswith(f"{len(app.sources.messages)} of {len(app.sources.messages)} messages, newest first")
        newest = max(app.sources.messages, key=lambda m: m.t_s)
        assert newest.text[:30] in rows[1]
    assert snap_compare(app, terminal_size=(80, 24), run_before=run_before)


def test_primary_display_halted(rig, snap_compare):
    sim, app = rig
    assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 300, ("u", "y", "h", "s")))


def test_messages_screen(rig, snap_compare):
    sim, app = rig
    assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 300, ("u", "y", "m")))


def test_world_model_browser(rig, snap_compare):
    sim, app = rig
    assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 300, ("u", "y", "w")))


def test_parameter_display(rig, snap_compare):
    sim, app = rig
    assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 300, ("u", "y", "p")))


def test_force_displays(rig, snap_compare):
    sim, app = rig
    sim.world.ft.set_load((12.0, -4.0, 30.0), (0.5, -0.25, 0.125))
    assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 40, ("u", "y", "escape", "escape", "f")))


def test_camera_screen(rig, snap_compare):
    """``v``, then camera 2 on monitor 1 and camera 3 on monitor 2: the route table as the
    switcher applied it, the selected monitor, the answer; the World Status under it."""
    sim, app = rig
    switcher = sim.world.bus["pio_video"].switcher

    async def run_before(pilot):
        for keys in (("v",), ("2",), ("down", "3")):
            await pilot.press(*keys)
            sim.step(24)  # 75 ms: the service applies a route at its 40 Hz PIO rate
            app.refresh_areas()
        await pilot.pause()
        assert switcher.monitors == (2, 3)
        lines = [ln.rstrip() for ln in screen_text(app).splitlines()]
        assert lines[:10] == [
            "Camera routes: the user I/F box's switches or the keys here (docs/cameras.md)",
            "",
            "  monitor 1: camera 2",
            "> monitor 2: camera 3",
            "",
            "camera routes: monitor 1: camera 2, monitor 2: camera 3",
            "",
            "1 2 3  that camera on the selected monitor   0  blank it",
            "up/down, tab  select the monitor   v, Escape  close",
            "last answer: request 2: CAMERA ROUTE: applied by the service: monitor 1: camera 2, monitor 2: camera 3 "
            "-> COMPLETE",
        ]
        assert any("│ camera routes: monitor 1: camera 2, monitor 2: camera 3" in ln for ln in lines[10:])  # World Status
    assert snap_compare(app, terminal_size=SIZE, run_before=run_before)


MENU = "snapshot-menu.toml"  #: beside this file; loaded by a relative name, so the page shows the same path anywhere


def test_live_menu(rig, snap_compare, monkeypatch):
    """``--menu snapshot-menu.toml``, key ``l``: each variable's label, its values in its own
    format and its units, live; the second page at its own rate; back to the first."""
    from pathlib import Path

    from tools.console import menu as menus
    from tools.console.app import MenuScreen
    sim, app = rig
    monkeypatch.chdir(Path(__file__).parent)
    app.menu = menus.load(MENU)  # what pfma console --menu does: read, then checked against the model
    app.menu.check(sim.rt.wm)
    wm = sim.rt.wm

    async def run_before(pilot):
        sim.step(300)
        await pilot.press("l")
        await pilot.pause()
        assert isinstance(app.screen, MenuScreen)
        sim.step(40)
        app.refresh_areas()  # 10 Hz page: redrawn at this refresh
        await pilot.pause()
        lines = [ln.rstrip() for ln in screen_text(app).splitlines()]
        q = wm.get("daq.joint_angle_rad")
        assert lines[0] == "snapshot menu: [Joints]  Servo"
        assert lines[1].startswith("page 1/2, refresh 10 Hz   <- -> / tab page   Escape/l close   (snapshot-menu.toml)")
        assert lines[2].startswith("up/down select   Enter/e modify")
        assert lines[3] == "> measured angle     " + "  ".join(f"{float(x):+.4f}" for x in q) + "  rad"
        assert lines[4] == f"  controller frames  {int(wm.get('runtime.frames'))}"
        await pilot.press("right")
        await pilot.pause()
        lines = [ln.rstrip() for ln in screen_text(app).splitlines()]
        assert lines[0] == "snapshot menu: Joints  [Servo]" and lines[1].startswith("page 2/2, refresh 2 Hz")
        kp, cl = wm.get("servo.kp_per_s"), wm.get("servo.current_limit_a")
        units_kp, units_cl = wm.spec("servo.kp_per_s").units, wm.spec("servo.current_limit_a").units
        assert lines[3] == "> gain K         " + "  ".join(f"{float(x):.2f}" for x in kp) + f"  {units_kp}"
        assert lines[4] == "  current limit  " + "  ".join(f"{float(x):.1f}" for x in cl) + f"  {units_cl}"
        await pilot.press("left")
        sim.step(40)
        app.refresh_areas()
        await pilot.pause()
        assert screen_text(app).splitlines()[4].rstrip() == f"  controller frames  {int(wm.get('runtime.frames'))}"
    assert snap_compare(app, terminal_size=SIZE, run_before=run_before)


def test_power_up_asks_for_the_shoulder_roll_index(snap_compare):
    """``u`` over a controller whose shoulder-roll index is +45 deg: the question names it,
    nothing is sent yet (issue 30 item 2)."""
    sim = SystemSimulator(shoulder_roll_deg=45)
    client = Client.attach(sim.name, layout=sim.rig.layout)
    try:
        sim.step(10)
        app = ConsoleApp(view.Sources(client, sim.rt.wm, rack="simulated"), ControllerLink(sim.rt.wm),
                         auto_refresh=False)
        assert snap_compare(app, terminal_size=SIZE, run_before=_then(sim, app, 20, ("u",)))
        assert int(sim.rt.wm.get("ui.request_seq")) == 0  # asked, not sent
    finally:
        client.close()
        sim.close()
