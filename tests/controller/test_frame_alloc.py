"""The controller's minor frame allocates nothing that survives it (issue 16 item 6).

The system simulator runs powered up; after a warm-up (rings and caches full, traced
from the start of the warm-up so that the objects they hold are traced in both
snapshots) the controller runs 1,000 minor frames under ``tracemalloc``. The net growth
of the memory allocated while a ``controller/`` function was on the stack must be about
zero. Objects that are replaced every frame (the newest trace record, the latest pose)
make a few hundred bytes of noise either way; a per-frame list append of one float is
about 32 bytes a frame, 32 KB over the run. The second test shows the check catching
exactly that.

The lean frame's fast world-model paths are also checked here against the general ones
(:func:`controller.worldmodel.spec.coerce`, ``_decode_value``): the same bytes, the same
values and types, and the same errors for what they hand on.
"""

from __future__ import annotations

import math
import os
import tracemalloc

import numpy as np
import pytest

import controller
from controller.decision import Status
from controller.worldmodel import VarSpec, WorldModel, WorldModelValueError
from controller.worldmodel.model import _fast_raw
from controller.worldmodel.spec import coerce
from tests._alloc import TRACED_WARMUP, growth, running_system

#: frames measured (the issue's figure)
FRAMES = 1000
#: frames of the demonstration that the check can fail (shorter: it only has to exceed the limit)
LEAK_FRAMES = 400
#: net growth allowed over FRAMES frames (noise of replaced objects: floats come and go from
#: the interpreter's free list untraced; measured 0.5 KB with this 16-frame trace ring)
ALLOWED_BYTES = 4096
#: allocations that happened while the package's code was on the stack (its directory,
#: not a pattern: this test's own file lives in tests/controller/)
CONTROLLER = [tracemalloc.Filter(True, os.path.join(os.path.dirname(controller.__file__), "*"), all_frames=True)]


@pytest.fixture
def running():
    yield from running_system()


def test_controller_frame_allocates_nothing_that_survives(running):
    grown, objects, top = growth(running, FRAMES, CONTROLLER)
    assert grown <= ALLOWED_BYTES, (f"controller frames kept {grown} B ({objects} objects) over {FRAMES} frames; "
                                    f"largest: " + "; ".join(map(str, top)))


def test_the_check_sees_a_per_frame_append(running):
    """A layer that appends one float per frame to a list is caught (the check can fail)."""
    kept: list[float] = []
    servo = running.rt.servo
    table = servo.run_table

    def leaky_table(rt) -> None:
        table(rt)
        kept.append(rt.now * 1.5)  # a new float object every frame, kept

    servo.run_table = leaky_table  # type: ignore[method-assign]
    grown, _, _ = growth(running, LEAK_FRAMES, CONTROLLER)
    assert len(kept) == TRACED_WARMUP + LEAK_FRAMES
    assert grown > 2 * ALLOWED_BYTES  # ~32 B a frame: ~13 KB


# --- the fast world-model paths are the general ones ------------------------------------

SPECS = [
    VarSpec("t.f", "task_io", "f8", (), "t", 0.0),
    VarSpec("t.v", "task_io", "f8", (3,), "t", [0.0] * 3),
    VarSpec("t.m", "task_io", "f8", (2, 3), "t", [[0.0] * 3] * 2),
    VarSpec("t.i2", "task_io", "i2", (), "t", 0),
    VarSpec("t.i8", "task_io", "i8", (), "t", 0),
    VarSpec("t.b", "task_io", "b1", (), "t", False),
    VarSpec("t.bv", "task_io", "b1", (3,), "t", [False] * 3),
    VarSpec("t.iv", "task_io", "i4", (3,), "t", [0] * 3),
    VarSpec("t.s", "status_output", "i2", (), "t", 0),
]

VALUES = {
    "t.f": [1.5, -0.0, np.float64(2.25), 7, True, np.int64(3), math.inf, math.nan, np.float32(0.1), "x"],
    "t.v": [np.array([1.0, 2.0, 3.0]), [1.0, 2.0, 3.0], (1.0, -2.5, 1e300), [1, 2, 3], [1.0, 2.0],
            np.array([1.0, np.inf, 0.0]), (1.0, math.nan, 0.0), np.array([1e308, 1e308, 0.0]),
            np.array([1, 2, 3]), np.arange(6.0)[::2], np.array([1.0, 2.0, 3.0], dtype=np.float32),
            [1.0, "a", 2.0], (1.0, True, 2.0)],
    "t.m": [np.ones((2, 3)), np.ones((3, 2)).T, [[1.0] * 3] * 2, np.full((2, 3), np.nan)],
    "t.i2": [3, -32768, 32767, 32768, -1, Status.ERROR, True, 1.0, np.int16(5), np.int64(7)],
    "t.i8": [2 ** 62, 2 ** 63, -(2 ** 63), 0],
    "t.b": [True, False, np.bool_(True), 1, 0, 2, 1.0],
    "t.bv": [np.array([True, False, True]), [True, False, False], np.array([1, 0, 1])],
    "t.iv": [np.array([1, 2, 3], dtype=np.int32), np.array([1, 2, 3]), [1, 2, 3], np.array([2 ** 40, 0, 0])],
    "t.s": [0, 7, Status.START_UP, -5],
}


def _general(spec: VarSpec, value):
    try:
        return coerce(spec, value).tobytes()
    except WorldModelValueError as err:
        return ("error", str(err))


@pytest.mark.parametrize("spec", SPECS, ids=lambda s: s.name)
def test_fast_post_gives_the_general_bytes(spec):
    wm = WorldModel.create(SPECS)
    try:
        h = wm._hot[wm._index[spec.name]]
        taken = 0
        for value in VALUES[spec.name]:
            fast = _fast_raw(h, value)
            if fast is not None:  # taken: exactly what coerce gives
                taken += 1
                assert fast == _general(spec, value), (spec.name, value)
        assert taken, f"no fast path taken for {spec.name}"  # the first value of each list is a common case
    finally:
        wm.close()


def test_fast_reads_give_the_general_values():
    wm = WorldModel.create(SPECS)
    try:
        posts = {"t.f": 1.25, "t.v": [1.0, 2.0, 3.0], "t.m": np.arange(6.0).reshape(2, 3), "t.i2": -7,
                 "t.i8": 2 ** 40, "t.b": True, "t.bv": [True, False, True], "t.iv": [4, 5, 6], "t.s": 3}
        wm.post_task_outputs("t", posts)
        wm.communications_segment()
        names = tuple(posts)
        fast = wm.get_task_inputs(names)  # the owner's path
        for n in names:
            i = wm._index[n]
            o = wm._lay.offsets[i]
            general = wm._decode_value(i, bytes(wm._body[o:o + wm._specs[i].nbytes]))
            for got in (fast[n], wm.get(n)):
                assert type(got) is type(general), n
                assert np.array_equal(got, general), n
                if isinstance(got, np.ndarray):
                    assert got.shape == general.shape and got.dtype == general.dtype
                    assert not np.shares_memory(got, np.frombuffer(wm._body, np.uint8))
        assert wm.get_state_variable("t.s") == 3 and type(wm.get_state_variable("t.s")) is int
        with pytest.raises(WorldModelValueError):  # the general path's error, through the fast entry
            wm.post_state_variable("t", "t.s", 1 << 20)
        with pytest.raises(WorldModelValueError):
            wm.post_task_outputs("t", {"t.v": [1.0, math.inf, 0.0]})
    finally:
        wm.close()
