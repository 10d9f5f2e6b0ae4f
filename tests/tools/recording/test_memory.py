"""The recorder's memory does not grow with the length of the recording (issue 20 item 4).

Frames captured from the simulated rig (one second of them) are fed to the recorder
again and again with their frame numbers and sample times moved on, on a simulated wall
clock (a chunk is closed every 0.25 s of it, and whenever one passes 256 KiB, as live).
tracemalloc measures the Python memory after N and after 4N frames, each time right after
a flush (no chunk in progress). Before the chunk indexes were spooled to disk
(tools/recording/spool.py) this grew by about 25 bytes a frame (one ~1 kB ``ChunkIndex``
per ~40 frames; docs/reliability.md, the soak); now it does not grow.
"""

from __future__ import annotations

import gc
import os
import tracemalloc
import uuid

import numpy as np
import pytest
from mcap.reader import make_reader

from bit3.client import Snapshot
from sim.rig import SimRig as Rig
from tools.recording import RAW_TOPIC, Recorder, recover

#: frames fed before the first measurement; the second comes after 4N in all
N = 640
#: allowed growth of the recorder's traced memory per frame between N and 4N frames.
#: Measured: 25.0 B/frame with the library's in-memory chunk indexes, 0.14 B/frame with
#: the spool; 4 B/frame would be 4.6 MB in an hour at 320 Hz, inside the issue's 5 MB
BOUND_B_PER_FRAME = 4.0


@pytest.fixture(scope="module")
def captured():
    """(the rig, its inputs frames of one second in order, the frame period)."""
    rig = Rig(name="pfma-rec-mem-" + uuid.uuid4().hex[:8])
    snaps: list[Snapshot] = []

    def keep(_info) -> None:
        if rig.reader.changed("inputs"):
            snap = rig.reader.read_inputs().copy()
            if float(snap.record["t_s"]) > 0 and (
                    not snaps or int(snap.record["frame"]) != int(snaps[-1].record["frame"])):
                snaps.append(snap)  # not frame 0 (t_s 0), nor a frame published again
    rig.on_frame.append(keep)
    rig.run(1.0)
    rig.on_frame.remove(keep)
    yield rig, snaps, rig.svc.schedule.period_s
    rig.close()


def _time_fields(dtype: np.dtype) -> list[str]:
    """The inputs' sample-time fields (``t_s``, ``t_rtd_s`` ... ``ft_t_s``, ``hc_t_s``)."""
    return [n for n in dtype.names if n == "t_s" or (n.startswith("t_") and n.endswith("_s"))
            or n in ("ft_t_s", "hc_t_s")]


def _frames(snaps: list[Snapshot], period: float, k0: int, k1: int):
    """Frames k0..k1-1: the captured ones in a loop, frame numbers and times moved on."""
    n = len(snaps)
    lay = snaps[0].layout
    times = _time_fields(snaps[0].record.dtype)
    for k in range(k0, k1):
        c, i = divmod(k, n)
        r = snaps[i].record.copy()
        r["frame"] = int(r["frame"]) + c * n
        for f in times:
            v = r[f]
            r[f] = np.where(v > 0, v + c * n * period, v)
        yield Snapshot(r, "inputs", lay, 2 * (k + 1))


class _Feeder:
    def __init__(self, rig: Rig, snaps, period: float, out) -> None:
        self.snaps, self.period, self.k, self.t = snaps, period, 0, 0.0
        self.rec = Recorder(rig.reader, out, rack=rig.world.rack_config,
                            epoch_offset_ns=1_700_000_000_000_000_000, wall=lambda: self.t)

    def feed(self, n: int) -> None:
        rec = self.rec
        for snap in _frames(self.snaps, self.period, self.k, self.k + n):
            self.t += self.period
            assert rec.feed_inputs(snap) == 1
            rec.poll(inputs=False)
        self.k += n
        rec.flush()  # measured with no chunk in progress

    def close(self):
        self.rec.client = None  # as pfma record does: the frames came through feed_inputs only
        return self.rec.close()


def _traced_growth_per_frame(rig, snaps, period, out) -> tuple[float, _Feeder]:
    f = _Feeder(rig, snaps, period, out)
    tracemalloc.start()
    try:
        f.feed(N)
        gc.collect()
        a = tracemalloc.get_traced_memory()[0]
        f.feed(3 * N)
        gc.collect()
        b = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    return (b - a) / (3 * N), f


def test_recorder_memory_does_not_grow_with_the_recording(captured, tmp_path):
    rig, snaps, period = captured
    with open(os.devnull, "wb") as out:  # the file's bytes are not the recorder's memory
        per_frame, f = _traced_growth_per_frame(rig, snaps, period, out)
        cnt = f.close()
    rec = f.rec
    assert cnt.frames_recorded == 4 * N and cnt.lossless
    assert per_frame < BOUND_B_PER_FRAME, f"the recorder's memory grew {per_frame:.1f} B a frame over {3 * N} frames"
    assert rec.index_spool is not None, "mcap keeps its chunk indexes elsewhere: tools/recording/spool.py"
    assert rec.index_spool.count >= 4 * N // 80  # at least one chunk per 0.25 s: many chunks were measured


def test_spooled_indexes_make_the_same_summary(captured, tmp_path):
    """Chunk and message indexes are all in the summary, so seeking readers (mcap's, and
    Foxglove's, which refuses a chunk index without message indexes) read it as before;
    recover (which spools too) rewrites the file with the same frames."""
    rig, snaps, period = captured
    path = tmp_path / "long.mcap"
    f = _Feeder(rig, snaps, period, path)
    f.feed(4 * N)
    cnt = f.close()
    with open(path, "rb") as fh:
        r = make_reader(fh)
        s = r.get_summary()
        assert s is not None and len(s.chunk_indexes) == s.statistics.chunk_count == f.rec.index_spool.count
        assert all(ci.message_index_offsets and ci.message_index_length > 0 for ci in s.chunk_indexes)
        offsets = [ci.chunk_start_offset for ci in s.chunk_indexes]
        assert offsets == sorted(offsets) and len(set(offsets)) == len(offsets)
        frames = [int(np.frombuffer(m.data[:8], "<u8")[0])
                  for _, _, m in r.iter_messages(topics=[RAW_TOPIC], log_time_order=True)]
        # a time window read through the chunk indexes
        t_mid = s.chunk_indexes[len(s.chunk_indexes) // 2].message_start_time
        late = sum(1 for _ in r.iter_messages(topics=[RAW_TOPIC], starting_at=t_mid))
    first = int(snaps[0].record["frame"])
    assert frames == list(range(first, first + 4 * N)) and cnt.frames_recorded == 4 * N
    assert 0 < late < 4 * N
    rep = recover(path, tmp_path / "again.mcap")
    assert rep.frames == 4 * N and rep.frame_gaps == 0
    with open(rep.output, "rb") as fh:
        s2 = make_reader(fh).get_summary()
        assert s2 is not None and len(s2.chunk_indexes) == s2.statistics.chunk_count > 0
