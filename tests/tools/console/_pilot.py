"""Running a console under Textual's Pilot, and stepping the simulator behind it."""

from __future__ import annotations

import asyncio

SIZE = (180, 50)


def run_app(app, body) -> None:
    """``await body(pilot)`` inside ``app.run_test`` at :data:`SIZE`."""
    async def go():
        async with app.run_test(size=SIZE) as pilot:
            await body(pilot)
    asyncio.run(go())


def frames(sim, app, n: int) -> None:
    """n simulated frames, then one console refresh (what the 10 Hz timer does)."""
    sim.step(n)
    app.refresh_areas()


def screen_text(app) -> str:
    """What the terminal shows now, as plain text: the characters of
    ``App.export_screenshot`` (the same compositor render of the screen stack), without
    styles, one line per terminal row. For asserting on rendered content beside a snapshot."""
    import io

    from rich.console import Console
    width, height = app.size
    console = Console(width=width, height=height, file=io.StringIO(), force_terminal=True, color_system=None,
                      record=True, legacy_windows=False, safe_box=False)
    console.print(app.screen._compositor.render_update(full=True, screen_stack=app._background_screens))
    return console.export_text(styles=False)


def kept_messages(app) -> str:
    """Every message the console keeps, newest first: what its messages screen (``m``) lists.
    The main area shows only the newest 50; a power-up alone posts more than that."""
    from tools.console import view
    return view.messages_screen(app.sources.messages)
