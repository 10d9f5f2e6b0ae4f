"""What the frame-allocation tests of the controller and the service share: a settled
whole-system simulator and the traced-memory growth over a number of frames."""

from __future__ import annotations

import gc
import tracemalloc
from collections.abc import Iterator

from controller.decision import Status
from sim.system import SystemSimulator

#: frames run under tracemalloc before the first snapshot: longer than the trace ring, so
#: every record the ring holds was allocated (and traced) in the warm-up
TRACED_WARMUP = 100
#: the runtime's trace ring while measuring (objects it replaces come and go untraced)
TRACE_FRAMES = 16


def running_system() -> Iterator[SystemSimulator]:
    """A simulator powered up and settled (servo, Cartesian engine and force layer in their
    periodic work); closed afterwards. Use as the body of a fixture (``yield from``)."""
    sim = SystemSimulator(trace_frames=TRACE_FRAMES)
    try:
        sim.step(10)
        sim.power_up(400)
        sim.step(200)
        assert sim.rt.all_status(Status.START_UP_COMPLETE)
        yield sim
    finally:
        sim.close()


def growth(sim: SystemSimulator, frames: int, filters) -> tuple[int, int, list]:
    """(bytes, objects, top lines) the traced memory matching ``filters`` grew by over ``frames``."""
    gc.collect()
    tracemalloc.start(8)
    try:
        sim.step(TRACED_WARMUP)
        gc.collect()
        before = tracemalloc.take_snapshot().filter_traces(filters)
        sim.step(frames)
        gc.collect()
        after = tracemalloc.take_snapshot().filter_traces(filters)
    finally:
        tracemalloc.stop()
    diff = after.compare_to(before, "lineno")
    top = sorted(diff, key=lambda d: -d.size_diff)[:5]
    return sum(d.size_diff for d in diff), sum(d.count_diff for d in diff), top
