"""What the tests of live processes (``pfma serve``, ``pfma controller``) share: bounded
polling and an orderly end of every process a test started."""

from __future__ import annotations

import subprocess
import time


def wait_for(pred, timeout_s: float = 20.0) -> bool:
    """Poll ``pred`` every 50 ms until it is true or ``timeout_s`` has passed (a subprocess
    is waited for: bounded polling, not a sleep standing in for the world)."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.05)
    return False


def stop(*procs: subprocess.Popen | None) -> None:
    """SIGTERM each process still running, then SIGKILL one that does not end in 10 s."""
    for p in procs:
        if p is not None and p.poll() is None:
            p.terminate()
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
