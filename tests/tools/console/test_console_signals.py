"""`pfma console --sim` on a terminal (a pty) stopped by SIGTERM or SIGHUP, as a process
manager or a closed terminal stops it: it ends as `q` does - the terminal given back (the
alternate screen left), the simulated system stopped with its outputs at 0 V, exit 0, its names
(the default buffer and world model, tools/runnames.py) removed.
Before, either signal killed it at once, the terminal left in the alternate screen and the
simulated system's buffer left in /dev/shm. A process on a pty with bounded waits: realtime."""

from __future__ import annotations

import os
import pty
import re
import select
import signal
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.realtime

PFMA = str(Path(sys.executable).with_name("pfma"))
WAIT_S = 60.0


def _read(fd: int, until, limit_s: float) -> bytes:
    out = b""
    end = time.monotonic() + limit_s
    while time.monotonic() < end and not until(out):
        r, _, _ = select.select([fd], [], [], 0.1)
        if r:
            try:
                data = os.read(fd, 65536)
            except OSError:  # the child closed the pty
                break
            if not data:
                break
            out += data
    return out


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_a_signal_ends_the_console_as_q_does(sig):
    pid, fd = pty.fork()
    if pid == 0:  # the child: the console on the pty
        os.environ["TERM"] = "xterm-256color"
        os.execv(PFMA, [PFMA, "console", "--sim"])
    try:
        drawn = _read(fd, lambda out: b"SIMULATED" in out, WAIT_S)
        assert b"SIMULATED" in drawn, drawn[-500:]
        os.kill(pid, sig)
        tail = _read(fd, lambda out: b"simulated system stopped" in out, WAIT_S)
        _, status = os.waitpid(pid, 0)
    finally:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        os.close(fd)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0, status
    assert b"\x1b[?1049l" in tail  # the alternate screen left: the terminal is the user's again
    assert b"simulated system stopped; DAC outputs 0.000 V max" in tail
    # make run's names (the defaults, or a private pair while another system has them), as its
    # last line says: none left (other names come and go: tests of other checkouts may run)
    said = re.search(rb"buffer (\S+) and world model (\S+) removed", tail)
    assert said, tail[-500:]
    buffer, wm = (n.decode() for n in said.groups())
    left = [n for n in (buffer, f"{buffer}.ring", f"{buffer}.faults", wm) if os.path.exists(f"/dev/shm/{n}")]
    assert not left, left
