"""The console at the terminal it is given (issue 29 item 4; docs/console.md "Sizes"):
every area present at 80x24 and each scrolls; no cut lines at 120x40; the Messages screen
newest first, paged, filtered by source and level; the main screen's Messages in time
order; while halted, World Status shows the motion the service measures and the outputs
it holds, not the controller's frozen copy. Simulated time; the console's timer is off."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from tools.console import view
from tools.console.app import Area, MessagesScreen
from tests.tools.console._pilot import frames, screen_text

SIZES = [(80, 24), (120, 40), (200, 50)]


def run_at(app, size, body) -> None:
    async def go():
        async with app.run_test(size=size) as pilot:
            await body(pilot)
    asyncio.run(go())


def _notes(console, n: int, level: str = "INFO") -> None:
    """n console messages at distinct simulated times after the system's (what answers and
    refusals add)."""
    t0 = max((m.t_s for m in console.sources.messages), default=0.0)
    for k in range(n):
        console.sources.note(t0 + 0.01 * (k + 1), level, f"note {k:03d}")


def _times(lines) -> list[float]:
    out = []
    for ln in lines:
        first = (ln.split() or [""])[0]
        if "." in first:  # a message's time (s), not the head's count
            out.append(float(first))
    return out


@pytest.mark.parametrize("size", SIZES, ids=[f"{w}x{h}" for w, h in SIZES])
def test_every_area_is_on_screen_at_every_size(sim, console, size):
    async def body(pilot):
        await pilot.press("u", "y")
        frames(sim, console, 300)
        await pilot.pause()
        text = screen_text(console)
        for title in view.AREAS:
            assert title in text, (title, size)
        for area in console.query(Area):  # each area has rows of its own on the terminal
            assert area.content_region.height >= 1 and area.content_region.width >= 30, (area.id, size)
        assert "START UP COMPLETE" in text and "service ARMED" in text
    run_at(console, size, body)


def test_no_line_is_cut_at_120x40(sim, console):
    """The IRSS areas' lines fit their areas: the selected layer's detail line, the joints,
    the camera routes and every command are whole on the terminal (no ellipsis, no wrap)."""
    async def body(pilot):
        await pilot.press("u", "y")
        frames(sim, console, 300)
        await pilot.press("right", "right", "right", "right", "right", "right")  # Data Acquisition: the longest
        frames(sim, console, 1)
        await pilot.pause()
        text = screen_text(console)
        for key in ("local", "world", "commands", "global"):
            for line in console.area_text(key).splitlines():
                if key == "global" and line.startswith("last answer:"):
                    continue  # the answer is also whole in Messages
                assert line.rstrip() in text, (key, line)
        assert "Data Acquisition: row" in text and "camera routes: monitor 1:" in text
        rows = text.splitlines()
        assert len(rows) == 40 and all(len(r) <= 120 for r in rows)
        await pilot.press("h")  # halted: World Status's longest
        frames(sim, console, 40)
        await pilot.pause()
        text = screen_text(console)
        assert all(line.rstrip() in text for line in console.area_text("world").splitlines())
    run_at(console, (120, 40), body)


def test_at_80x24_an_area_pages_for_more(sim, console):
    """Tab focuses the next area; pgdn scrolls it (World Status has more lines than rows)."""
    async def body(pilot):
        await pilot.press("u", "y")
        frames(sim, console, 300)
        await pilot.pause()
        world = console.query_one("#world-area", Area)
        assert world.max_scroll_y > 0  # more than it shows at 80x24
        while console.focused is not world:
            await pilot.press("tab")
        assert "camera routes:" not in screen_text(console)
        await pilot.press("pagedown")
        await pilot.pause()
        assert world.scroll_y > 0 and "camera routes:" in screen_text(console)
    run_at(console, (80, 24), body)


def test_main_messages_in_time_order_the_newest_in_view(sim, console):
    async def body(pilot):
        await pilot.press("u", "y")
        frames(sim, console, 300)
        _notes(console, 30)
        frames(sim, console, 1)
        await pilot.pause()
        await pilot.pause()
        lines = console.area_text("messages").splitlines()
        times = _times(lines)
        assert len(times) == min(view.MAIN_MESSAGES, len(console.sources.messages))
        assert times == sorted(times)
        sources = [ln.split()[1] for ln in lines]
        assert len(set(sources)) >= 3  # the sources interleaved by time, not grouped
        assert "note 029" in screen_text(console)  # the newest, in view at 80x24
    run_at(console, (80, 24), body)


def test_messages_screen_newest_first_pages_to_older(sim, console):
    async def body(pilot):
        await pilot.press("u", "y")
        frames(sim, console, 300)
        _notes(console, 60)
        await pilot.press("m")
        await pilot.pause()
        assert isinstance(console.screen, MessagesScreen)
        shown = screen_text(console).splitlines()
        first = _times(shown)
        assert first == sorted(first, reverse=True) and "note 059" in shown[1]
        await pilot.press("pagedown")
        await pilot.pause()
        after = _times(screen_text(console).splitlines())
        assert after[0] < first[-1]  # a page further: only older messages
        await pilot.press("pageup")
        await pilot.pause()
        assert _times(screen_text(console).splitlines()) == first
    run_at(console, (80, 24), body)


def test_messages_screen_filters_by_source_and_level(sim, console):
    async def body(pilot):
        await pilot.press("u", "y")
        frames(sim, console, 300)
        _notes(console, 3, "WARNING")
        _notes(console, 3, "INFO")
        await pilot.press("m")
        await pilot.pause()
        scr = console.screen
        assert isinstance(scr, MessagesScreen)
        sources = view.message_sources(console.sources.messages)
        assert sources[:2] == ["console", "service"] and len(sources) >= 4
        for src in sources:
            await pilot.press("s")
            await pilot.pause()
            head, *lines = scr.text().splitlines()
            assert f"source: {src} (s)" in head
            assert lines and all(ln.split()[1] == src for ln in lines)
            assert len(lines) == sum(m.source == src for m in console.sources.messages)
        await pilot.press("s")  # back to all sources
        await pilot.press("l")  # WARNING and above
        await pilot.pause()
        head, *lines = scr.text().splitlines()
        assert "level: WARNING and above (l)" in head and "source: all" in head
        assert len(lines) == sum(m.level in ("WARNING", "ERROR", "FATAL") for m in console.sources.messages) >= 3
        assert all(ln.split()[2] in ("WARNING", "ERROR", "FATAL") for ln in lines)
        await pilot.press("l", "l", "l")  # ERROR and above, FATAL, all again
        await pilot.pause()
        head, *lines = scr.text().splitlines()
        assert "level: all (l)" in head and len(lines) == len(console.sources.messages)
    run_at(console, (80, 24), body)


def test_halted_world_status_shows_measured_motion_and_held_outputs(sim, console):
    """The finding: halted while the elbow moved, World Status kept the controller's last
    rate (its ``daq.joint_rate_rad_s``, frozen while no frame runs) for seconds while the
    service read 0. Now the joints' rows are the service's inputs (tach, resolver, DAC)."""
    from fakes.arm_params import AXES
    arm = sim.world.sim.arm
    i = [a.joint for a in AXES].index("elbow_pitch")

    async def body(pilot):
        sim.power_up(max_frames=400)
        frames(sim, console, 20)
        qdot = np.zeros(len(AXES))
        qdot[i] = -0.23  # rad/s: the elbow moving when the operator halts
        arm.set_state(qdot=qdot)
        sim.world.sim.settle_filters()  # the anti-aliasing filters at rest on that rate
        sim.step(2)  # one A/D scan: the controller's last frame sees the elbow moving
        await pilot.press("h")
        frames(sim, console, 320)  # 1 s halted: the brakes have stopped the arm
        await pilot.pause()
        frozen = float(sim.rt.wm.get("daq.joint_rate_rad_s")[list(sim.client.layout.joint_names).index("elbow_pitch")])
        snap = console.reading.inputs
        lay = snap.layout
        names = list(lay.joint_names)
        tach = [float(snap.adc_value[lay.joint_entry("adc", j, "rate").slot]) for j in names]
        assert abs(frozen) > 0.05 and abs(tach[names.index("elbow_pitch")]) < 0.005  # the case of the finding
        world = console.area_text("world").splitlines()
        assert any(ln.startswith("HALTED: the motion below is measured, the outputs as the service holds") for ln in world)
        rates = next(ln for ln in world if ln.startswith("rad/s tach"))
        assert rates.split()[2:] == [f"{v:+.4f}" for v in tach]
        assert f"{frozen:+.4f}" not in rates
        volts = next(ln for ln in world if ln.startswith("V out"))
        assert volts.split()[2:] == ["+0.000"] * len(names)  # the held outputs: 0 V
        assert any("outputs safe (0 V)  brakes set (commanded)" in ln for ln in world)
        angles = next(ln for ln in world if ln.startswith("rad ")).split()[1:]
        assert all(-np.pi < float(a) <= np.pi for a in angles)
    run_at(console, (120, 40), body)


@pytest.mark.parametrize("a", [0.0, 1.0, -1.0, np.pi, -np.pi, 3 * np.pi / 2, 4.71239, -4.71239, 7.0, -7.0])
def test_angles_are_shown_in_minus_pi_to_pi(a):
    w = view.wrap_angle(a)
    assert -np.pi < w <= np.pi and np.isclose(np.cos(w), np.cos(a)) and np.isclose(np.sin(w), np.sin(a))


def test_at_80x24_the_selected_layer_stays_in_view(sim, console):
    async def body(pilot):
        await pilot.press("u", "y")
        frames(sim, console, 300)
        for _ in range(6):  # down the tree to Data Acquisition, the last row of Local Status
            await pilot.press("right")
            await pilot.pause()
        assert "> Data Acquisition" in screen_text(console)
        await pilot.press("right")  # round to System Up/Down, the first
        await pilot.pause()
        assert "> System Up/Down" in screen_text(console)
    run_at(console, (80, 24), body)


@pytest.mark.parametrize("size", SIZES, ids=[f"{w}x{h}" for w, h in SIZES])
def test_the_outputs_banner_heads_every_size_and_the_areas_stay(sim, console, size):
    """issue 28 item 5's banner (the DAC not answering) docked above the areas at each size,
    whole (it wraps to the width), and every area still titled on the terminal."""
    from sim.faults import FaultSet
    faults = FaultSet(sim.world)

    async def body(pilot):
        frames(sim, console, 2)
        faults.inject("bus-error:dac")
        frames(sim, console, 2)
        await pilot.pause()
        text = screen_text(console)
        rows = text.splitlines()
        assert "OUTPUTS NOT KNOWN SAFE" in rows[1] or "OUTPUTS NOT KNOWN SAFE" in rows[0]
        flat = " ".join(r.strip(" ┃━┏┓┗┛") for r in rows)
        assert "PRESS THE HARDWARE E-STOP" in flat and "without one only the E-stop stops the arm." in flat
        for title in view.AREAS:
            assert title in text, (title, size)
    run_at(console, size, body)


def test_the_brakes_by_the_sensors_one_word_when_alike_a_row_when_not():
    """World Status's brakes (issue 30 item 3): the controller's ``servo.brake_state`` in one
    word when every joint's is the same, a row under the joint names when not, the service's
    commanded state while no controller runs or it is halted."""
    from types import SimpleNamespace

    from controller.params import JOINT_NAMES
    from tools.console.view import brake_row, brake_summary

    def reading(states, alive=True, halted=False):
        wm = {"servo.brake_state": states, "runtime.halted": halted}
        return SimpleNamespace(wm=SimpleNamespace(get=lambda n, d=None: wm.get(n, d)), controller_alive=alive)
    s = SimpleNamespace(layout=SimpleNamespace(joint_names=JOINT_NAMES), brakes_released=1)
    assert brake_summary(reading([2] * 6), s) == "brakes released (sensed)" and brake_row(reading([2] * 6), s) == []
    mixed = reading([2, 2, 0, 2, 1, 2])
    assert brake_summary(mixed, s) == "brakes mixed (sensed, by joint below)"
    row = brake_row(mixed, s)[0].split()
    assert row == ["brake", "released", "released", "SET", "released", "unproven", "released"]
    assert brake_summary(reading([0] * 6, alive=False), s) == "brakes released (commanded)"
    assert brake_summary(reading([2] * 6, halted=True), s) == "brakes released (commanded)"
    assert brake_row(reading([2, 0, 0, 0, 0, 0], halted=True), s) == []
