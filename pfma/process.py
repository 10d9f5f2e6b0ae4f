"""Small Linux process helpers shared by the service's helper processes."""

from __future__ import annotations

import signal


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


__all__ = ["set_parent_death_signal", "process_state"]
