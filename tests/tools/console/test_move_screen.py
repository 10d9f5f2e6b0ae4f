"""The console's MOVE TO (issue 30 item 5, docs/console.md "Move to"): ``t`` opens the move
screen, a typed pose (no orientation: the tool keeps its own) is checked, confirmed and sent
as a move-to request; the controller's answer shows on the screen, in the last answer and in
Messages; a refused move shows the point and the reason. Pilot key presses on the system
simulator in simulated time (the console's timer is off; a test redraws after stepping)."""

from __future__ import annotations

from controller.kinematics import fk
from controller.quat import q_angle
from tools.console import view
from tools.console.app import ConsoleApp, MoveScreen
from tools.console.control import ControllerLink
from tests.tools.console._pilot import frames, run_app


def test_move_to_a_pose_from_the_console(sim, reader):
    sim.power_up(max_frames=400)
    app = ConsoleApp(view.Sources(reader, sim.rt.wm, rack="simulated"), ControllerLink(sim.rt.wm),
                     auto_refresh=False)
    p0, q0 = fk(sim.joint_angles_rad())
    x, y, z = p0 + [0.0, 0.04, 0.0]

    async def body(pilot):
        frames(sim, app, 24)
        assert "t  move to (its screen)" in app.area_text("global")
        await pilot.press("t")
        assert isinstance(app.screen, MoveScreen)
        assert "MOVE TO   tool (" in app.screen.text() and "pose X,Y,Z" in app.screen.text()
        await pilot.press(*f"pose {x:.4f},{y:.4f},{z:.4f}", "enter")
        assert f"move the tool to {x:.4f},{y:.4f},{z:.4f}?  Enter: confirm and send" in app.screen.text()
        await pilot.press("enter")
        assert "move 1 sent: pose" in app.screen.text()
        for _ in range(60):  # 6 s simulated, redrawn as the 10 Hz timer would
            frames(sim, app, 32)
            if app.pending_move is None:
                break
        assert app.pending_move is None
        assert "last: move 1 done (worst tracking error" in app.screen.text()
        assert app.last_answer.startswith("move 1 done") and app.last_answer.endswith("-> OK")
        p1, q1 = fk(sim.joint_angles_rad())
        assert abs(p1[1] - y) < 0.01 and q_angle(q1, q0) < 0.035
        # the identity orientation: refused, the point and the reason shown
        await pilot.press(*["backspace"] * 60, *"pose 1.55,0,-0.33,1,0,0,0", "enter", "enter")
        for _ in range(10):
            frames(sim, app, 32)
        assert "move 2 refused before it started: the target: turns the tool" in app.screen.text()
        # a typing mistake: said on the screen, nothing sent
        await pilot.press(*["backspace"] * 60, *"pose 1,2", "enter")
        assert "not sent: pose: 3 numbers" in app.screen.text()
        await pilot.press("escape")
        assert not isinstance(app.screen, MoveScreen)
        app.refresh_areas()
        assert "cart.mode HOLD -> TRAJECTORY" in app.area_text("messages")
        assert "move 2 refused before it started" in app.area_text("messages")
    run_app(app, body)
