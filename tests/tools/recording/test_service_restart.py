"""`pfma record` across a crashed and restarted `pfma serve` (separate processes, real time).

The restarted service replaces the frame ring the recorder has mapped: the recorder must
neither die (SIGBUS from a ring truncated under it) nor mix the two services' frames
into one session. Nothing here is timed: the test waits for the processes' own
messages (with generous time-outs) and checks the file afterwards.
"""

from __future__ import annotations

import json
import queue
import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from tools.recording.reader import read_frames, read_metadata
from bit3.ring import FrameRing
from bit3.buffer import Bit3Buffer

pytestmark = pytest.mark.realtime

REPO = Path(__file__).resolve().parents[3]
_RECORD = ("import sys; import tools.stacks.recorder as r; r.STALE_S = 3600.0; from tools.cli import main; "
           "sys.exit(main(['record', sys.argv[1], '--buffer', sys.argv[2]]))")


def _lines(stream) -> queue.Queue:
    q: queue.Queue = queue.Queue()

    def pump() -> None:
        for line in stream:
            q.put(line)
        q.put(None)
    threading.Thread(target=pump, daemon=True).start()
    return q


def _wait_for(q: queue.Queue, text: str, seen: list[str], timeout_s: float = 60.0) -> None:
    while True:
        try:
            line = q.get(timeout=timeout_s)
        except queue.Empty:
            raise AssertionError(f"no {text!r} within {timeout_s} s:\n{''.join(seen)}") from None
        assert line is not None, f"stream ended before {text!r}:\n{''.join(seen)}"
        seen.append(line)
        if text in line:
            return


def _wait_for_frames(name: str, n: int) -> None:
    """Until the current ring of ``name`` has grown by ``n`` frames (the service runs)."""
    ring = FrameRing.attach(name)
    try:
        start = ring.count()
        for _ in range(60_000):  # a bound, not a timing: 60 s of 1 ms naps
            if ring.count() >= start + n:
                return
            time.sleep(0.001)
        raise AssertionError(f"ring of {name} did not grow by {n} frames")
    finally:
        ring.close()


def _first_ring_frame(name: str) -> int:
    """The service frame in the first slot of ``name``'s current ring. A service starting on
    a loaded host may skip its first frame numbers (deadlines it never caught up, counted
    in its ``stats.dropped_frames``), so its first published frame is not always 0."""
    buf = Bit3Buffer.attach(name)
    ring = FrameRing.attach(name)
    try:
        data = ring.read(0)
        assert data is not None, f"the first slot of {name}'s ring was overwritten before it was read"
        return int(np.ndarray((), buf.layout.area("inputs").body_dtype, buffer=data)["frame"])
    finally:
        ring.close()
        buf.close()


def _serve(name: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "tools.cli", "serve", "--buffer", name, "--duration", "120"],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def test_recorder_survives_a_service_restart_and_starts_a_new_session(tmp_path):
    name = "pfma-rst-" + uuid.uuid4().hex[:8]
    out = tmp_path / "r.mcap"
    procs: list[subprocess.Popen] = []
    try:
        s1 = _serve(name)
        procs.append(s1)
        s1_out: list[str] = []
        _wait_for(_lines(s1.stdout), "Ctrl-C stops", s1_out)
        # the recorder's own "no frame for 1 s" check is pushed out of the way, so the
        # restart reaches it through the replaced ring (which it has mapped), every time
        rec = subprocess.Popen([sys.executable, "-c", _RECORD, str(out), name],
                               cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        procs.append(rec)
        rec_err: list[str] = []
        rq = _lines(rec.stderr)
        _wait_for(rq, "recording /dev/shm/", rec_err)
        _wait_for_frames(name, 200)  # the recorder maps the ring and has frames of session 1
        s1.kill()  # a crash: buffer and ring stay behind, the recorder still maps the ring
        s1.wait(30)
        s2 = _serve(name)
        procs.append(s2)
        _wait_for(rq, "was replaced", rec_err)
        _wait_for(rq, "recording continues as session 2", rec_err)
        first = _first_ring_frame(name)  # read now, long before the ring wraps (256 slots)
        _wait_for_frames(name, 200)  # and frames of session 2
        rec.send_signal(signal.SIGINT)
        rec.wait(60)
        assert rec.returncode == 0, (rec.returncode, "".join(rec_err))  # -7 would be SIGBUS
        summary = read_metadata(out)["pfma.recorder.summary"]
        assert int(summary["sessions"]) == 2 and int(summary["recorder_missed"]) == 0
        frames = [int(r["frame"]) for _, _, r in read_frames(out)]
        (cut,) = [i for i in range(1, len(frames)) if frames[i] < frames[i - 1]]  # one restart
        for part in (frames[:cut], frames[cut:]):  # each service's frames, in order (the
            # service may skip a frame number itself when late; recorder_missed counts ours)
            assert len(part) >= 100 and part == sorted(set(part))
        assert frames[cut] == first  # the new service's ring from its first frame
        assert json.loads(summary["topic_counts"])["/pfma/inputs_raw"] == len(frames)
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait(30)
        Bit3Buffer.unlink(name)
        FrameRing.unlink(name)
        Path(f"/dev/shm/{name}.faults").unlink(missing_ok=True)  # the killed service's fault endpoint
