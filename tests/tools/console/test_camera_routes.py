"""The console's camera routes (issue 18 item 4, docs/cameras.md): ``v`` opens the camera
screen, ``1``/``2``/``3``/``0`` route the selected monitor through the CAMERA ROUTE request,
and the World Status names the applied route. Pilot key presses on the system simulator in
simulated time (the console's timer is off; a test redraws after stepping)."""

from __future__ import annotations



from controller.routes import switch_word
from tools.console import view
from tools.console.app import CameraScreen, ConsoleApp
from tools.console.control import ControllerLink
from tests.tools.console._pilot import frames, run_app


def _app(sim, client, link: bool = True) -> ConsoleApp:
    return ConsoleApp(view.Sources(client, sim.rt.wm, rack="simulated"),
                      ControllerLink(sim.rt.wm) if link else None, auto_refresh=False)


def test_route_a_camera_from_the_console(sim, reader):
    app = _app(sim, reader)
    sw = sim.world.bus["pio_video"].switcher

    async def body(pilot):
        frames(sim, app, 24)
        assert "camera routes: monitor 1: blank, monitor 2: blank" in app.area_text("world")
        await pilot.press("v")
        assert isinstance(app.screen, CameraScreen)
        assert "> monitor 1: blank" in app.screen.text()
        await pilot.press("2")  # camera 2 on monitor 1
        frames(sim, app, 24)
        assert sw.monitors == (2, 0)
        assert "> monitor 1: camera 2" in app.screen.text()
        await pilot.press("down", "3")  # camera 3 on monitor 2
        frames(sim, app, 24)
        assert sw.monitors == (2, 3)
        assert "> monitor 2: camera 3" in app.screen.text()
        assert ("CAMERA ROUTE: applied by the service: monitor 1: camera 2, monitor 2: camera 3 -> COMPLETE"
                in app.screen.text())
        await pilot.press("0")  # blank monitor 2
        frames(sim, app, 24)
        assert sw.monitors == (2, 0)
        await pilot.press("escape")
        assert not isinstance(app.screen, CameraScreen)
        app.refresh_areas()
        assert "camera routes: monitor 1: camera 2, monitor 2: blank" in app.area_text("world")
        assert "CAMERA ROUTE sent" in app.area_text("messages")
        assert "not yet" not in app.area_text("global").split("v  camera routes")[1].splitlines()[0]
    run_app(app, body)


def test_world_status_names_a_box_route_and_what_the_controller_asks(sim, reader):
    app = _app(sim, reader)

    async def body(pilot):
        sim.world.set_user_inputs(switch_word(2, 1))
        frames(sim, app, 24)
        assert "camera routes: monitor 1: blank, monitor 2: camera 1" in app.area_text("world")
        sim.world.bus["pio_video"].inject("switcher_silent")
        sim.world.set_user_inputs(switch_word(1, 3))
        frames(sim, app, 24)
        assert ("camera routes: monitor 1: blank, monitor 2: camera 1  (controller asks monitor 1: camera 3, "
                "monitor 2: camera 1)") in app.area_text("world")
    run_app(app, body)


def test_read_only_console_says_it_cannot_route(sim, reader):
    app = _app(sim, reader, link=False)

    async def body(pilot):
        await pilot.press("v", "1")
        texts = [m.text for m in app.sources.messages]
        assert "read-only console: no controller to route the cameras" in texts
        assert "read-only console: no controller to send requests to" in texts
        assert sim.world.bus["pio_video"].switcher.route in (None, 0)
    run_app(app, body)
