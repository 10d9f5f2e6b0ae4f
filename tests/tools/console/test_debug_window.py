"""The console's debug window (issue 18 item 2, docs/console.md "The debug window"): keyed
writes from the world-model browser, the parameter-modification display, live menus from
TOML and the force displays. Pilot key presses on the system simulator in simulated time
(the console's timer is off; a test steps the simulator and redraws)."""

from __future__ import annotations

import os
import uuid

import numpy as np
import pytest

from bit3.client import Client
from controller.worldmodel.spec import AREAS as WM_AREAS
from tools.console import view
from tools.console.app import BrowserScreen, ConsoleApp, EditScreen
from tools.console.control import ControllerLink
from tests.tools.console._pilot import frames, run_app


async def _browse_to(pilot, app, name: str) -> BrowserScreen:
    """``w``, then right to the variable's area and down to its row (keys only)."""
    await pilot.press("w")
    await pilot.pause()
    scr = app.screen
    assert isinstance(scr, BrowserScreen)
    spec = app.sources.wm.spec(name)
    await pilot.press(*["right"] * WM_AREAS.index(spec.area))
    names = view.browser_names(app.sources.wm, spec.area)
    k = names.index(name)
    await pilot.press(*["pagedown"] * (k // view.BROWSER_ROWS), *["down"] * (k % view.BROWSER_ROWS))
    await pilot.pause()
    assert scr.selected() == name
    assert f"> {name} " in scr.text()
    return scr


async def _type(pilot, text: str) -> None:
    await pilot.press("home", "ctrl+k", *text)


# --- (a) modify from the world-model browser -----------------------------------------------------
def test_a_permitted_write_lands_in_the_world_model(sim, console):
    async def body(pilot):
        scr = await _browse_to(pilot, console, "msp.speed_scale")
        await pilot.press("enter")
        await pilot.pause()
        assert isinstance(console.screen, EditScreen)
        await _type(pilot, "0.25")
        await pilot.press("enter")  # check: nothing sent yet
        await pilot.pause()
        assert "set msp.speed_scale = 0.25?" in str(console.screen.query_one("#edit-status").render())
        assert not console.writes
        await pilot.press("enter")  # confirm
        await pilot.pause()
        assert console.screen is scr and len(console.writes) == 1
        frames(sim, console, 2)
        await pilot.pause()
        assert float(sim.rt.wm.get("msp.speed_scale")) == 0.25
        assert "msp.speed_scale = 0.25 (write #" in scr.text()
        await pilot.press("escape")  # the areas are redrawn when the display closes
        await pilot.pause()
        assert "msp.speed_scale = 0.25 (write #" in console.area_text("messages")
    run_app(console, body)


def test_a_forbidden_write_is_refused_with_the_rules_reason(sim, console):
    async def body(pilot):
        before = sim.rt.wm.get("servo.q_cmd_rad").copy()
        scr = await _browse_to(pilot, console, "servo.q_cmd_rad")
        await pilot.press("e")
        await pilot.pause()
        assert console.screen is scr  # no editor: refused at once
        why = "servo.q_cmd_rad is an output of task joint; users may not set it"
        assert why in scr.text()
        await pilot.press("escape")
        await pilot.pause()
        assert why in console.area_text("messages")
        frames(sim, console, 2)
        assert np.array_equal(sim.rt.wm.get("servo.q_cmd_rad"), before)
    run_app(console, body)


def test_a_bad_value_is_named_in_the_editor_and_nothing_is_sent(sim, console):
    async def body(pilot):
        await _browse_to(pilot, console, "joint.goal_rad")
        await pilot.press("enter")
        await _type(pilot, "1,2")
        await pilot.press("enter")
        await pilot.pause()
        status = str(console.screen.query_one("#edit-status").render())
        assert status.startswith("not sent:") and "shape (2,) given, shape (6,) expected" in status
        assert not console.writes
        await pilot.press("escape")
        await pilot.pause()
        assert isinstance(console.screen, BrowserScreen)
    run_app(console, body)


def test_a_value_outside_an_enumeration_is_refused_and_a_name_is_taken(sim, console):
    """msp.mode = 7 was accepted by the editor and then warned about as unknown (issue 29):
    now the editor refuses it, listing the values, and takes the name PLAY for 2."""
    async def body(pilot):
        scr = await _browse_to(pilot, console, "msp.mode")
        assert "IDLE (0)" in scr.text()  # the browser shows the enumeration by name
        await pilot.press("enter")
        await pilot.pause()
        assert "values: 0 IDLE, 1 RECORD, 2 PLAY" in str(console.screen.query_one("#edit-info").render())
        await _type(pilot, "7")
        await pilot.press("enter")
        await pilot.pause()
        status = str(console.screen.query_one("#edit-status").render())
        assert status.startswith("not sent:") and "7 is not one of its values (0 IDLE, 1 RECORD, 2 PLAY)" in status
        await pilot.press("enter")  # the refused text is never confirmed
        await pilot.pause()
        assert not console.writes and isinstance(console.screen, EditScreen)
        await _type(pilot, "play")
        await pilot.press("enter")
        await pilot.pause()
        assert "set msp.mode = PLAY (2)?" in str(console.screen.query_one("#edit-status").render())
        await pilot.press("enter")
        await pilot.pause()
        assert console.screen is scr and len(console.writes) == 1
        frames(sim, console, 2)
        await pilot.pause()
        assert int(sim.rt.wm.get("msp.mode")) == 2 and "msp.mode = PLAY (2) (write #" in scr.text()
    run_app(console, body)


def test_a_wrong_key_is_refused_by_the_write_path(sim):
    client = Client.attach(sim.name, layout=sim.rig.layout)
    app = ConsoleApp(view.Sources(client, sim.rt.wm, rack="simulated"), ControllerLink(sim.rt.wm, key="wrong"),
                     auto_refresh=False)

    async def body(pilot):
        await _browse_to(pilot, app, "msp.speed_scale")
        await pilot.press("enter")
        await _type(pilot, "0.5")
        await pilot.press("enter", "enter")
        await pilot.pause()
        assert "wrong or missing access key" in app.screen.text()
        assert not app.writes
    try:
        run_app(app, body)
    finally:
        client.close()


# --- (b) the parameter-modification display ----------------------------------------------------
def test_parameter_edit_refused_powered_up_and_accepted_powered_down(sim, console):
    from controller.layers import Request
    from tools.console.app import ParamScreen

    async def body(pilot):
        sim.power_up(max_frames=400)
        assert sim.rt.wm.powered_up
        kp0 = sim.rt.wm.get("servo.kp_per_s").copy()
        await pilot.press("p")
        await pilot.pause()
        scr = console.screen
        assert isinstance(scr, ParamScreen)
        text = scr.text()
        assert text.splitlines()[1].startswith("LOCKED: the system is powered up")
        assert "servo compensators" in text and "servo limits" in text
        assert scr.names[:3] == ("servo.kp_per_s", "servo.tau_z_s", "servo.tau_p_s")
        await pilot.press("right", "right")  # joint 2 (elbow_pitch)
        await pilot.press("enter")
        await pilot.pause()
        assert console.screen is scr  # no editor
        why = "servo.kp_per_s is protected: it may be set only while powered down (the system is powered up)"
        assert why in scr.text()
        assert why in view.messages_area(console.sources.messages)  # the Messages area's text once shown
        assert sim.request(Request.POWER_DOWN)[0] == 2  # COMPLETE: shut down
        assert not sim.rt.wm.powered_up
        console.refresh_areas()
        await pilot.pause()
        assert scr.text().splitlines()[1].startswith("EDITABLE")
        assert "[" + f"{kp0[2]:.6g}" + "]" in scr.text()  # the selected cell
        await pilot.press("enter")
        await pilot.pause()
        assert isinstance(console.screen, EditScreen)
        await _type(pilot, "9.5")
        await pilot.press("enter", "enter")
        await pilot.pause()
        frames(sim, console, 2)
        await pilot.pause()
        kp = sim.rt.wm.get("servo.kp_per_s")
        assert kp[2] == 9.5 and np.array_equal(np.delete(kp, 2), np.delete(kp0, 2))  # one joint changed
        assert "servo.kp_per_s = " in scr.text() and "applied at frame" in scr.text()
    run_app(console, body)


# --- (c) live menus from TOML ------------------------------------------------------------------
EXAMPLE = __import__("pathlib").Path(__file__).resolve().parents[3] / "examples" / "console-menu.toml"


def test_the_example_menu_loads_and_its_pages_show_live_at_their_rates(sim):
    from tools.console import menu as menus
    from tools.console.app import MenuScreen
    m = menus.load(EXAMPLE)
    m.check(sim.rt.wm)
    assert [p.name for p in m.pages] == ["Joints", "Servo", "Layers"]
    client = Client.attach(sim.name, layout=sim.rig.layout)
    app = ConsoleApp(view.Sources(client, sim.rt.wm, rack="simulated"), ControllerLink(sim.rt.wm),
                     auto_refresh=False, menu=m)

    async def body(pilot):
        await pilot.press("l")
        await pilot.pause()
        scr = app.screen
        assert isinstance(scr, MenuScreen)
        assert scr.text().startswith("PFMA arm: [Joints]  Servo  Layers")
        q = sim.rt.wm.get("daq.joint_angle_rad")
        assert "measured angle   " + "  ".join(f"{float(x):+.4f}" for x in q) + "  rad" in scr.text()
        await pilot.press("right", "right")  # Layers, 5 Hz: every second console refresh
        await pilot.pause()
        assert "[Layers]" in scr.text()
        frames0 = scr.text().splitlines()[-1]
        draws = scr.draws
        frames(sim, app, 50)
        assert scr.draws == draws and scr.text().splitlines()[-1] == frames0  # not yet its turn
        app.refresh_areas()
        assert scr.draws == draws + 1
        assert scr.text().splitlines()[-1] == f"  controller frames      {int(sim.rt.wm.get('runtime.frames'))}"
        draws = scr.draws
        await pilot.press("left")  # Servo, 2 Hz: drawn at once, then every fifth
        for _ in range(10):
            app.refresh_areas()
        assert scr.draws == draws + 1 + 2
    try:
        run_app(app, body)
    finally:
        client.close()


BAD_MENUS = [  # (file text, line, field named, words of the message)
    ('[[page]]\nname = "a"\nrefresh_hz = 20\n[[page.var]]\nname = "runtime.frames"\n',
     3, "page 1 refresh_hz", "not a rate in (0, 10] Hz"),
    ('[[page]]\nname = "a"\n[[page.var]]\nname = "runtime.frames"\n\n[[page.var]]\nname = "x"\nformat = ".3q"\n',
     8, "page 1 var 2 format", "is not a format spec"),
    ('[[page]]\nname = "a"\n[[page.var]]\nname = "runtime.frames"\ncolour = "red"\n',
     5, "page 1 var 1 colour", "unknown field"),
    ('title = "t"\n[[page]]\nname = "a"\n', 2, "page 1 var", "a page needs variables"),
    ('[[page]]\nname = "a"\nrefresh_hz = \n', 3, "TOML", "Invalid value"),
]


@pytest.mark.parametrize("text,line,field,words", BAD_MENUS)
def test_a_bad_menu_file_exits_2_naming_file_line_and_field(tmp_path, capsys, text, line, field, words):
    from tools.cli import main
    f = tmp_path / "bad.toml"
    f.write_text(text)
    rc = main(["console", "--menu", str(f), "--buffer", "pfma_console_menu_nobody"])  # before any service check
    out, err = capsys.readouterr()
    assert rc == 2 and out == "" and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert err.startswith(f"pfma console: {f}:{line}: {field}: ") and words in err


def test_a_menu_variable_the_model_lacks_exits_2_before_the_console_starts(tmp_path, capsys):
    from tools.cli import main
    f = tmp_path / "typo.toml"
    f.write_text('[[page]]\nname = "a"\n\n[[page.var]]\nname = "runtime.frame"\nformat = "d"\n')
    name = f"pfma-menu-{uuid.uuid4().hex[:8]}"  # not make run's default names: tests run side by side
    rc = main(["console", "--sim", "--menu", str(f), "--buffer", name, "--wm", f"{name}_wm"])  # built, checked, closed
    out, err = capsys.readouterr()
    assert rc == 2 and "Traceback" not in err
    assert err.startswith(f"pfma console: {f}:5: page 1 var 1 name: no variable 'runtime.frame' in the world "
                          f"model; did you mean runtime.frames")
    assert len(err.strip().splitlines()) == 1
    assert not [n for n in os.listdir("/dev/shm") if n.startswith(name)]  # nothing left behind


def test_a_format_that_does_not_fit_the_variable_is_named(sim, tmp_path):
    from tools.console import menu as menus
    f = tmp_path / "m.toml"
    f.write_text('[[page]]\nname = "a"\n[[page.var]]\nname = "daq.joint_angle_rad"\nformat = "d"\n')
    with pytest.raises(menus.MenuError) as e:
        menus.load(f).check(sim.rt.wm)
    assert str(e.value).startswith(f"{f}:5: page 1 var 1 format: 'd' does not format a f8 value")


def test_a_missing_menu_file_is_one_message_exit_2(tmp_path, capsys):
    from tools.cli import main
    rc = main(["console", "--menu", str(tmp_path / "none.toml")])
    _out, err = capsys.readouterr()
    assert rc == 2 and err.startswith(f"pfma console: --menu {tmp_path / 'none.toml'}: cannot read it")


# --- (c') user menus modify what the ownership rules allow (issue 33 item 7, report 2.2.8) -------
EDIT_MENU = """title = "edit"
[[page]]
name = "Mixed"
[[page.var]]
name = "daq.joint_angle_rad"
format = "+.4f"
[[page.var]]
name = "msp.speed_scale"
format = ".3f"
[[page.var]]
name = "traj.v_lin_max_m_s"
format = ".3f"
"""


def _menu_console(sim, reader, tmp_path) -> ConsoleApp:
    from tools.console import menu as menus
    f = tmp_path / "edit.toml"
    f.write_text(EDIT_MENU)
    m = menus.load(f)
    m.check(sim.rt.wm)
    return ConsoleApp(view.Sources(reader, sim.rt.wm, rack="simulated"), ControllerLink(sim.rt.wm),
                      auto_refresh=False, menu=m)


async def _menu_to(pilot, app, row: int):
    """``l``, then down to the page's ``row``-th variable (keys only)."""
    from tools.console.app import MenuScreen
    await pilot.press("l", *["down"] * row)
    await pilot.pause()
    scr = app.screen
    assert isinstance(scr, MenuScreen) and scr.row == row
    assert scr.text().splitlines()[3 + row].startswith(f"> {scr.selected()} ")
    return scr


def test_a_user_menu_modifies_a_variable_the_rules_let_a_user_set(sim, reader, tmp_path):
    """From a live menu: Enter on msp.speed_scale (users may set it any time) and on
    traj.v_lin_max_m_s (powered down only; the system is) opens the browser's editor; the
    keyed write lands and the page says so."""
    app = _menu_console(sim, reader, tmp_path)

    async def body(pilot):
        assert not sim.rt.wm.powered_up
        scr = await _menu_to(pilot, app, 1)
        assert scr.selected() == "msp.speed_scale"
        await pilot.press("enter")
        await pilot.pause()
        assert isinstance(app.screen, EditScreen) and app.screen.var == "msp.speed_scale"
        await _type(pilot, "0.4")
        await pilot.press("enter", "enter")  # check, confirm and send
        await pilot.pause()
        assert app.screen is scr and len(app.writes) == 1
        frames(sim, app, 2)
        await pilot.pause()
        assert float(sim.rt.wm.get("msp.speed_scale")) == 0.4
        assert "> msp.speed_scale 0.400" in " ".join(scr.text().split())  # the page shows the new value
        assert "msp.speed_scale = 0.4 (write #" in scr.text() and "applied at frame" in scr.text()
        await pilot.press("down", "e")  # traj.v_lin_max_m_s: powered down only, and it is
        await pilot.pause()
        assert isinstance(app.screen, EditScreen) and app.screen.var == "traj.v_lin_max_m_s"
        await _type(pilot, "0.125")
        await pilot.press("enter", "enter")
        await pilot.pause()
        frames(sim, app, 2)
        await pilot.pause()
        assert float(sim.rt.wm.get("traj.v_lin_max_m_s")) == 0.125
        assert "traj.v_lin_max_m_s = 0.125 (write #" in scr.text()
    run_app(app, body)


def test_a_user_menu_write_the_rules_forbid_is_refused_naming_why(sim, reader, tmp_path):
    """From a live menu: a task output is refused (users may never set it), and a powered-down
    parameter while powered up (the rule's reason): no editor opens, nothing is written, the
    reason is the browser's own, on the page and in Messages."""
    from controller.worldmodel import WorldModelError
    app = _menu_console(sim, reader, tmp_path)
    wm = sim.rt.wm

    def rule(name: str) -> str:  # the ownership rule's reason, as the browser's write path gives it
        with pytest.raises(WorldModelError) as e:
            wm.check_user_settable(name)
        return f"{name}: refused: {e.value}"

    async def body(pilot):
        scr = await _menu_to(pilot, app, 0)
        before = wm.get("daq.joint_angle_rad").copy()
        await pilot.press("enter")
        await pilot.pause()
        assert app.screen is scr  # no editor: refused at once
        why = f"daq.joint_angle_rad is an output of task {wm.spec('daq.joint_angle_rad').writer}; users may not set it"
        assert why in scr.text() and scr.text().splitlines()[-1] == rule("daq.joint_angle_rad")
        assert why in view.messages_area(app.sources.messages)
        assert not app.writes
        frames(sim, app, 2)
        assert np.array_equal(wm.get("daq.joint_angle_rad"), before)
        sim.power_up(max_frames=400)
        assert wm.powered_up
        v0 = float(wm.get("traj.v_lin_max_m_s"))
        await pilot.press("up")  # round to the last: traj.v_lin_max_m_s
        await pilot.press("e")
        await pilot.pause()
        assert app.screen is scr and scr.selected() == "traj.v_lin_max_m_s"
        why = "traj.v_lin_max_m_s is protected: it may be set only while powered down (the system is powered up)"
        assert why in scr.text() and scr.text().splitlines()[-1] == rule("traj.v_lin_max_m_s")
        assert why in view.messages_area(app.sources.messages)
        frames(sim, app, 2)
        assert not app.writes and float(wm.get("traj.v_lin_max_m_s")) == v0
    run_app(app, body)


# --- (d) the force displays ----------------------------------------------------------------------
def test_the_force_view_shows_the_simulated_ft_values(sim, console):
    from tools.console.app import ForceScreen

    async def body(pilot):
        frames(sim, console, 40)
        sim.world.ft.set_load((12.0, -4.0, 30.0), (0.5, -0.25, 0.125))  # the fake sensor's load
        for _ in range(5):
            frames(sim, console, 40)  # 5 console refreshes, a new F/T record each
        await pilot.press("f")
        await pilot.pause()
        scr = console.screen
        assert isinstance(scr, ForceScreen)
        inp = sim.client.read_inputs()
        f, m = inp.ft_force_n, inp.ft_torque_nm
        assert np.allclose(f, (12.0, -4.0, 30.0), atol=0.1) and np.allclose(m, (0.5, -0.25, 0.125), atol=0.01)
        text = scr.text()
        assert f"F ({float(f[0]):+8.2f}, {float(f[1]):+8.2f}, {float(f[2]):+8.2f}) N" in text
        assert f"T ({float(m[0]):+8.3f}, {float(m[1]):+8.3f}, {float(m[2]):+8.3f}) N*m" in text
        assert "an axis is 50 N" in text  # |F| 32.6 N: auto-scaled to 50
        canvas = "".join(text.splitlines()[:16])
        assert any(0x2800 < ord(ch) <= 0x28FF for ch in canvas) and "F" in canvas  # the vector, labelled
        assert scr.series["Fz"][-1] == float(f[2]) and scr.series["Tx"][-1] == float(m[0])
        assert scr.series["Fz"][0] != scr.series["Fz"][-1]  # the history: before and after the load
        assert scr.series["t"][-1] == 0.0 and all(a < b for a, b in zip(scr.series["t"], scr.series["t"][1:]))
        draws = scr.series
        console.refresh_areas()  # no new F/T record: no new drawing
        assert scr.series is draws
    run_app(console, body)


def test_the_force_display_draws_one_plot_at_a_time_and_only_changed_vector_lines(sim, console):
    """The cost rules (docs/console.md "Force displays"): each plot every FT_PLOT_EVERY-th
    refresh with a new F/T record, the torque plot half a period after the force plot; the
    vector view repaints only the lines whose text changed (none for an unchanged force)."""
    from tools.console import debug
    from tools.console.app import ForceScreen, LinesView

    async def body(pilot):
        frames(sim, console, 40)
        await pilot.press("f")
        await pilot.pause()
        scr = console.screen
        assert isinstance(scr, ForceScreen)
        drawn: list[tuple[int, str]] = []
        for wid in ("#ft-force", "#ft-torque"):
            plot = scr.query_one(wid)
            real = plot.refresh
            plot.refresh = lambda *a, _w=wid, _r=real, **k: (drawn.append((tick, _w)), _r(*a, **k))[1]
        view_ = scr.query_one("#ft-vector", LinesView)
        real_v = view_.refresh
        repainted: list[int] = []
        view_.refresh = lambda *regions, **k: (repainted.extend(r.y for r in regions), real_v(*regions, **k))[1]
        sim.world.ft.set_load((5.0, 0.0, 10.0), (0.0, 0.0, 0.0))
        n = 2 * debug.FT_PLOT_EVERY
        for tick in range(1, n + 1):
            frames(sim, console, 32)  # 0.1 s: a new F/T record every refresh
        assert sorted(w for _, w in drawn) == ["#ft-force", "#ft-force", "#ft-torque", "#ft-torque"]
        assert len({t for t, _ in drawn}) == 4  # never both plots at one refresh
        assert repainted and len(repainted) < 20 * n  # some lines, not every line at every refresh
        repainted.clear()
        for tick in range(n + 1, n + 6):
            frames(sim, console, 32)  # the same force again: the vector's text does not change
        assert repainted == []
        assert f"F ({5.0:+8.2f}, {0.0:+8.2f}, {10.0:+8.2f}) N" in scr.text()
    run_app(console, body)


def test_a_display_pushed_but_not_yet_mounted_is_not_redrawn_by_the_timer(sim, console):
    """The 10 Hz timer can come between a key's push of a display and its mounting: the
    display is left to draw itself when it mounts (it crashed the console with NoMatches)."""
    from tools.console.app import ForceScreen

    async def body(pilot):
        frames(sim, console, 40)
        console.push_screen(ForceScreen(console.ft))
        assert isinstance(console.screen, ForceScreen) and not console.screen.is_mounted
        frames(sim, console, 32)  # the timer's refresh, before the display is mounted
        await pilot.pause()
        assert console.screen.is_mounted and "F (" in console.screen.text()
    run_app(console, body)
