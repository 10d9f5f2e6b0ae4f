"""Small Linux process helpers shared by the service's helper processes."""

from __future__ import annotations

import math
import os
import signal
from typing import Any, Callable, Protocol


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


def spawn_helper(argv: list[str], *, stdin_pipe: bool = False) -> Any:
    """Start a helper process of this package (``python -m ...``; the package's root on its
    PYTHONPATH) without waiting for it: the Popen, its stdout a pipe whose first line says
    whether it came up (:func:`first_line`).

    :param stdin_pipe: the helper's stdin is a pipe from this process (``proc.stdin``): it
        reads end-of-file when this process is gone, whatever killed it
    """
    import subprocess
    from pathlib import Path
    root = Path(__file__).resolve().parent.parent
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(root), env.get("PYTHONPATH", "")) if p)
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stdin=subprocess.PIPE if stdin_pipe else subprocess.DEVNULL,
                            text=True, env=env)


def first_line(proc: Any, timeout_s: float = 0.0) -> str | None:
    """The first line a :func:`spawn_helper` process printed, stripped, once it has printed
    one or ended ("" for an end without a line); None while it has said nothing within
    ``timeout_s`` (0: do not wait). Never blocks past ``timeout_s``: the pipe is read with
    ``os.read`` as bytes arrive (a part of a line is kept on ``proc`` for the next call), so
    a helper that prints half a line cannot hang the service's thread. Its stdout is closed
    once the line is read."""
    import select
    import time
    out = proc.stdout
    if out is None or out.closed:
        return ""
    fd = out.fileno()
    end = time.monotonic() + timeout_s
    got: bytes = getattr(proc, "_pfma_first_line", b"")
    while True:
        ready, _, _ = select.select([fd], [], [], max(0.0, end - time.monotonic()))
        if not ready:
            proc._pfma_first_line = got
            return None
        chunk = os.read(fd, 4096)
        got += chunk
        if not chunk or b"\n" in got:
            out.close()
            return got.split(b"\n", 1)[0].decode(errors="replace").strip()


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


#: how often :class:`HelperWatch` looks at its helpers, s (a ``waitpid`` each: cheap)
WATCH_EVERY_S = 0.5
#: how long a restarted helper may take to print its first line, s
READY_WITHIN_S = 30.0
#: the waits after a restart that failed, s: 1 s, then 5 s, then every 30 s (assumed: a
#: port still held or a bus not answering clears within seconds or needs a person)
RESTART_BACKOFF_S = (1.0, 5.0, 30.0)


class Restartable(Protocol):
    """A helper process :class:`HelperWatch` keeps running (the service's output guardian,
    its Modbus export)."""

    label: str  #: how messages name it ("output guardian")
    lost: str  #: what its absence means, said when it ends ("the DAC is not guarded ...")
    proc: Any  #: the running Popen, or None

    def spawn(self) -> Any:
        """Start it again (:func:`spawn_helper`, not waiting); sets and returns ``proc``."""
        ...

    def accept(self, line: str) -> str:
        """Its first line: "" when it says it is up, else why it is not (one line)."""
        ...


def bring_up(helper: Restartable, timeout_s: float) -> str:
    """Start ``helper`` and wait for its first line (bounded by ``timeout_s``): "" once it is
    up, else why not (one line; the caller stops it)."""
    try:
        helper.spawn()
    except OSError as err:
        return f"could not start: {err}"
    line = first_line(helper.proc, timeout_s)
    return helper.accept(line) if line is not None else f"{helper.label}: not ready within {timeout_s:g} s"


#: what a helper's ``accept`` says for an end without a first line
NO_WORD = "it ended without a word"


class HelperWatch:
    """Restarts the helper processes of a service that end while it runs, and says so.

    :meth:`tick` runs in the service's thread between frames (a ``TickingClock`` hook) and
    never waits on a helper: at most every :data:`WATCH_EVERY_S` it polls each helper's exit
    status; a helper that ended is said (``say(True, text)``: its pid, how it ended, what
    that means) and spawned again; its first line is picked up at a later tick (``say(False,
    "... restarted: pid N")``), or the restart failed (no line within
    :data:`READY_WITHIN_S`, or an error line) and is said and tried again after
    :data:`RESTART_BACKOFF_S`. Start the helpers, and tick, from the thread that lives as
    long as the service (the main thread): a helper with a parent-death signal gets it when
    the thread that started it ends.
    """

    def __init__(self, say: Callable[[bool, str], None], now: Callable[[], float] | None = None) -> None:
        import time
        self.say = say
        self.now = now or time.monotonic
        self._helpers: list[Restartable] = []
        self._state: dict[int, tuple[str, float, int]] = {}  # id -> (phase, since/until, failures)
        self._last = -math.inf
        self.restarts = 0  #: helpers restarted and up again

    def add(self, helper: Restartable) -> None:
        """Watch ``helper`` (already started and up)."""
        self._helpers.append(helper)
        self._state[id(helper)] = ("up", 0.0, 0)

    def remove(self, helper: Restartable) -> None:
        """Stop watching ``helper`` (before stopping it in order)."""
        if helper in self._helpers:
            self._helpers.remove(helper)
            self._state.pop(id(helper), None)

    def tick(self, now: float | None = None) -> None:
        t = self.now()
        if t - self._last < WATCH_EVERY_S:
            return
        self._last = t
        for h in list(self._helpers):
            self._look(h, t)

    def _look(self, h: Restartable, t: float) -> None:
        phase, when, fails = self._state[id(h)]
        proc = h.proc
        if phase == "up":
            rc = proc.poll() if proc is not None else 0
            if rc is None:
                return
            how = f"killed by {signal.Signals(-rc).name}" if rc < 0 and -rc in signal.valid_signals() else f"exit {rc}"
            self.say(True, f"{h.label} (pid {proc.pid if proc is not None else '?'}) ended ({how}): "
                           f"{h.lost}; restarting it")
            self._spawn(h, t, fails)
        elif phase == "starting":
            line = first_line(proc, 0.0)
            if line is None and proc.poll() is None and t - when <= READY_WITHIN_S:
                return
            why = h.accept(line) if line is not None else f"no ready line within {READY_WITHIN_S:g} s"
            if not why:
                self.restarts += 1
                self._state[id(h)] = ("up", t, 0)
                self.say(False, f"{h.label} restarted: pid {proc.pid}")
                return
            self._failed(h, t, fails, why)
        elif t >= when:  # waiting out a failed restart
            self._spawn(h, t, fails)

    def _spawn(self, h: Restartable, t: float, fails: int) -> None:
        try:
            h.spawn()
        except OSError as err:
            self._failed(h, t, fails, f"could not start: {err}")
            return
        self._state[id(h)] = ("starting", t, fails)

    def _failed(self, h: Restartable, t: float, fails: int, why: str) -> None:
        proc = h.proc
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        h.proc = None
        wait = RESTART_BACKOFF_S[min(fails, len(RESTART_BACKOFF_S) - 1)]
        self._state[id(h)] = ("waiting", t + wait, fails + 1)
        self.say(True, f"{h.label} did not restart: {why}; trying again in {wait:g} s")


__all__ = ["set_parent_death_signal", "process_state", "cpu_seconds", "rss_mb", "spawn_helper", "first_line",
           "stop_helper", "HelperWatch", "bring_up", "NO_WORD"]
