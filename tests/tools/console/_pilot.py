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
