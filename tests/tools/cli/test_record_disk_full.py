"""`pfma record` when its file cannot grow (a full disk, here a file-size limit, RLIMIT_FSIZE
with SIGXFSZ ignored, so each write past it fails with EFBIG as on a full disk it fails
with ENOSPC): one line naming the file and what to do, exit 1, and the file keeps what was
written before it - `pfma record recover` makes a whole recording of it. Processes:
realtime."""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from bit3.buffer import Bit3Buffer
from bit3.ring import FrameRing

pytestmark = pytest.mark.realtime

PFMA = str(Path(sys.executable).with_name("pfma"))
LIMIT_BYTES = 256 * 1024  # a few hundred frames


def _limit_file_size() -> None:
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (LIMIT_BYTES, LIMIT_BYTES))


def test_a_recording_that_cannot_grow_ends_in_one_line_and_is_recoverable(tmp_path):
    name = "pfma-test-efbig-" + uuid.uuid4().hex[:6]
    path = tmp_path / "full.mcap"
    svc = subprocess.Popen([PFMA, "serve", "--rack", "fake", "--buffer", name],
                           stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        end = time.monotonic() + 30
        while not os.path.exists(f"/dev/shm/{name}.ring") and svc.poll() is None and time.monotonic() < end:
            time.sleep(0.05)
        rec = subprocess.run([PFMA, "record", str(path), "--buffer", name, "--duration", "30"],
                             stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=90,
                             preexec_fn=_limit_file_size)
    finally:
        svc.send_signal(signal.SIGINT)
        svc.wait(timeout=30)
        Bit3Buffer.unlink(name)
        FrameRing.unlink(name)
    assert rec.returncode == 1, rec.stderr
    lines = [line for line in rec.stderr.splitlines() if line.strip()]
    assert f"pfma record: cannot write {path}: File too large" in lines[-1]
    assert f"pfma record recover {path}" in lines[-1]
    assert "Traceback" not in rec.stderr
    assert 0 < path.stat().st_size <= LIMIT_BYTES
    fixed = subprocess.run([PFMA, "record", "recover", str(path)], capture_output=True, text=True, timeout=60)
    assert fixed.returncode == 0, fixed.stderr
    assert "recovered" in fixed.stdout + fixed.stderr
    assert (tmp_path / "full-recovered.mcap").exists()
