"""Small Linux process helpers shared by the service's helper processes."""

from __future__ import annotations

import os
import signal
from typing import Any


def set_parent_death_signal(sig: int = signal.SIGTERM) -> bool:
    """Ask Linux to send ``sig`` to this process when its parent dies (``PR_SET_PDEATHSIG``;
    sent when the *thread* that started this process ends, so start helpers from a thread
    that lives as long as the parent: the main thread). False where it is not available."""
    try:
        import ctypes
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(1, int(sig)) == 0  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return False


def process_state(pid: int) -> str:
    """The state letter of process ``pid`` from ``/proc/PID/stat`` (``R``, ``S``, ``T`` stopped,
    ``t`` traced, ``Z`` zombie ...); "" when there is no such process (or no /proc)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return ""


def cpu_seconds(pid: int) -> float:
    """User plus system CPU time of process ``pid``, s (``/proc/PID/stat``).

    :raises OSError: no such process (or no /proc)
    """
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


def rss_mb(pid: int) -> float | None:
    """Resident memory of process ``pid``, MB (``VmRSS``); None when it is gone."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def start_helper(argv: list[str], timeout_s: float, *, stdin_pipe: bool = False) -> tuple[Any, str]:
    """Start a helper process of this package (``python -m ...``; the package's root on its
    PYTHONPATH) and read the first line it prints (bounded by ``timeout_s``: "" when none
    came). Returns (the Popen, that line); the caller stops it with :func:`stop_helper`.

    :param stdin_pipe: the helper's stdin is a pipe from this process (``proc.stdin``): it
        reads end-of-file when this process is gone, whatever killed it
    """
    import select
    import subprocess
    from pathlib import Path
    root = Path(__file__).resolve().parent.parent
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(root), env.get("PYTHONPATH", "")) if p)
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stdin=subprocess.PIPE if stdin_pipe else subprocess.DEVNULL,
                            text=True, env=env)
    assert proc.stdout is not None
    try:
        ready, _, _ = select.select([proc.stdout], [], [], timeout_s)
        line = proc.stdout.readline().strip() if ready else ""
    finally:
        proc.stdout.close()
    return proc, line


def stop_helper(proc: Any, timeout_s: float = 5.0) -> None:
    """SIGTERM, then SIGKILL after ``timeout_s``; waits for the process (None: nothing)."""
    import subprocess
    if proc is None:
        return
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


__all__ = ["set_parent_death_signal", "process_state", "cpu_seconds", "rss_mb", "start_helper", "stop_helper"]
