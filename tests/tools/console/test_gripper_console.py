"""The gripper from the console (docs/console.md "The gripper"): Global Commands ``o`` open,
``g`` grip (close), ``x`` stop, ``+``/``-`` the grip force, answered in Global Commands and
Messages; World Status shows the gripper's state, force and jaw. Simulated time, Pilot key
presses, the console's timer off."""

from __future__ import annotations

from controller.decision import Status
from pfma.arm import GRIPPER
from tests.tools.console._pilot import frames, run_app


def _gripper_line(console) -> str:
    return next(ln for ln in console.area_text("world").splitlines() if ln.startswith("gripper "))


def test_open_grip_force_and_stop_from_the_keys_and_world_status_shows_the_jaw(sim, console):
    arm = sim.world.sim.arm

    async def body(pilot):
        assert _gripper_line(console).startswith("gripper OFF")  # powered down: the drive is off
        await pilot.press("u", "y")  # y: the shoulder-roll index confirmed
        frames(sim, console, 300)
        assert sim.rt.all_status(Status.START_UP_COMPLETE)
        assert _gripper_line(console) == "gripper STOPPED  grip 40 N set, motor 0 N  jaw not known (not sensed)"
        arm.q[6] = 0.095
        await pilot.press("o")
        frames(sim, console, 200)  # 0.6 s: 5 mm to the stop, then the stall
        assert "gripper request 1: OPEN: at the open stop" in console.area_text("global")
        assert _gripper_line(console).startswith("gripper OPEN  grip 40 N set")
        assert "jaw ~100 mm (tach estimate)" in _gripper_line(console)
        await pilot.press("plus")  # 40 -> 50 N
        frames(sim, console, 20)
        assert "FORCE: grip force 50 N, current limit 1.25 A -> COMPLETE" in console.area_text("global")
        arm.place_jaw_object(0.09)
        await pilot.press("g")
        frames(sim, console, 320)  # 10 mm at 20 mm/s, the stall, the hold
        line = _gripper_line(console)
        assert line.startswith("gripper GRIPPING  grip 50 N set, motor 50 N") and "jaw ~90 mm" in line, line
        assert abs(arm.jaw_force_n - 50.0) <= GRIPPER.coulomb_n + 0.5
        assert "gripper request 3: GRIPPING after" in console.area_text("messages")
        await pilot.press("minus", "minus")  # two presses before the refresh: each from the force shown (50)
        frames(sim, console, 20)
        assert _gripper_line(console).startswith("gripper GRIPPING  grip 40 N set")
        await pilot.press("x")
        frames(sim, console, 20)
        assert "STOP: stopped (GRIPPING ended)" in console.area_text("global")
        assert _gripper_line(console).startswith("gripper STOPPED")
    run_app(console, body)


def test_a_refused_gripper_request_is_said_in_global_commands(sim, console):
    async def body(pilot):
        await pilot.press("g")  # powered down
        frames(sim, console, 20)
        glob = console.area_text("global")
        assert "gripper request 1: CLOSE: Servo Control is SHUT DOWN: the gripper drive is off (power up first) " \
               "-> REFUSED" in glob
        assert "o g x  gripper open, grip, stop" in glob and "+ -  grip force +-10 N" in glob
    run_app(console, body)


def test_make_runs_demo_opens_and_closes_the_gripper_and_the_console_shows_it():
    """What `make run` runs behind the console (stepped here by hand, not by its thread): the demo
    path's gripper events (sim.demo.DEMO_GRIPPER) open the jaw at the first pose and close it on
    the part between the jaws (sim.demo.DEMO_JAW_OBJECT_M) at the third."""
    from bit3.client import Client
    from sim.demo import DEMO_GOAL_EVERY_S, DEMO_GRIPPER, DEMO_JAW_OBJECT_M
    from tools.console import view
    from tools.console.app import ConsoleApp
    from tools.console.control import ControllerLink
    from tools.console.simrun import SimulatedSystem
    assert DEMO_GRIPPER == {0: "open", 2: "close"}
    system = SimulatedSystem()
    reader = Client.attach(system.sim.name, layout=system.sim.rig.layout)
    console = ConsoleApp(view.Sources(reader, system.sim.rt.wm, rack="simulated"), ControllerLink(system.sim.rt.wm),
                         auto_refresh=False)
    sim = system.sim
    try:
        async def body(pilot):
            seen: list[str] = []
            t_end = 2 * DEMO_GOAL_EVERY_S + 4.0  # the close starts with the third pose (8 s) and takes ~3 s
            while sim.clock.now() < t_end:
                sim.step(8)
                system._fly()
                console.refresh_areas()
                state = _gripper_line(console).split()[1]
                if not seen or seen[-1] != state:
                    seen.append(state)
            assert seen == ["OFF", "STOPPED", "OPENING", "OPEN", "CLOSING", "GRIPPING"], seen
            line = _gripper_line(console)
            assert line.startswith("gripper GRIPPING  grip 40 N set, motor 40 N"), line
            assert f"jaw ~{DEMO_JAW_OBJECT_M * 1e3:.0f} mm (tach estimate)" in line
            assert abs(sim.world.sim.arm.jaw_force_n - 40.0) <= 2.5
            messages = console.area_text("messages")
            assert "gripper request 1: OPEN: at the open stop" in messages
            assert "gripper request 2: GRIPPING after" in messages
        run_app(console, body)
    finally:
        reader.close()
        system.stop()
        system.close()
