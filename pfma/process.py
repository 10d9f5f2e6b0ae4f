"""Small Linux process helpers shared by the service's helper processes and the benchmarks."""

from __future__ import annotations

import contextlib
import math
import os
import re
import signal
import socket
import subprocess
import time
import uuid
from pathlib import Path
from typing import Any, Callable, Protocol

#: the root of this package's tree (the directory holding ``pfma/``)
ROOT = Path(__file__).resolve().parent.parent


#: what a live stack prints when the host, not the software, kept a process from its frames:
#: the controller's servo fault 12 (descheduled past its missed-frame limit,
#: controller/servo.py), the service's watchdog trip on a late heartbeat (ioservice/safety.py),
#: a command computed from inputs too old (ioservice/command.py) and Data Acquisition's
#: fault 32 on a service frame that did not move (the service itself descheduled,
#: controller/daq_layer.py; a test that kills the service does not ask). On a 2-core VM these
#: come even under SCHED_FIFO (the vCPU itself is descheduled); live tests and the kill
#: matrix start a process again, or a test once more, on these causes only, and say so. The
#: controller's own catch-up warning ("missed service frames 12..13 (2): caught up") is not one.
HOST_TIMING_CAUSE = re.compile(r"fault 12: controller missed (?:service|own) frames[^\n]*"
                               r"|stale heartbeat [\d.]+>[\d.]+ ms[^\n]*|command stale[^\n]*"
                               r"|fault 32: service frame \d+ unchanged for \d+ frames[^\n]*")


def host_timing_cause(text: str) -> str | None:
    """The first host-timing cause (:data:`HOST_TIMING_CAUSE`) ``text`` names, or None."""
    m = HOST_TIMING_CAUSE.search(text)
    return m.group(0) if m else None


def package_env(drop: tuple[str, ...] = ()) -> dict[str, str]:
    """This process's environment with the package's root first on PYTHONPATH (so a child
    ``python -m ...`` finds this tree), without the variables named in ``drop``."""
    env = {k: v for k, v in os.environ.items() if k not in drop}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    return env


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


def cpu_seconds_or_none(pid: int) -> float | None:
    """:func:`cpu_seconds`, or None when process ``pid`` is gone (or its stat unreadable)."""
    try:
        return cpu_seconds(pid)
    except (OSError, IndexError, ValueError):
        return None


def pid_alive(pid: int) -> bool:
    """Process ``pid`` runs (it exists and is not a zombie)."""
    return process_state(pid) not in ("", "Z")


def shm_maps(pid: int) -> set[str]:
    """The /dev/shm files process ``pid`` has mapped (from /proc/PID/maps; empty when gone)."""
    out = set()
    try:
        with open(f"/proc/{pid}/maps") as f:
            for line in f:
                i = line.find("/dev/shm/")
                if i >= 0:
                    out.add(line[i:].strip().removesuffix(" (deleted)"))
    except OSError:
        pass
    return out


def children(pid: int) -> list[int]:
    """The pids of process ``pid``'s children (``/proc/PID/task/PID/children``; empty when gone)."""
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(x) for x in f.read().split()]
    except OSError:
        return []


def cmdline(pid: int) -> str:
    """Process ``pid``'s command line, its arguments joined by spaces ("" when gone)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


def listen_port(pid: int) -> int | None:
    """The TCP port process ``pid`` listens on (from /proc/net/tcp and its fds); None when
    it listens on none (or is gone)."""
    try:
        inodes = set()
        for fd in os.listdir(f"/proc/{pid}/fd"):
            with contextlib.suppress(OSError):
                t = os.readlink(f"/proc/{pid}/fd/{fd}")
                if t.startswith("socket:["):
                    inodes.add(t[8:-1])
        with open("/proc/net/tcp") as f:
            for line in f.readlines()[1:]:
                parts = line.split()
                if parts[3] == "0A" and parts[9] in inodes:
                    return int(parts[1].split(":")[1], 16)
    except OSError:
        return None
    return None


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` a moment ago (the kernel's pick; another process may take
    it before the caller binds it)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def until(cond: Callable[[], Any], timeout_s: float, must_live: tuple = (), poll_s: float = 0.01) -> Any:
    """Poll ``cond`` until it is truthy and return its value; None on time-out, or when one
    of ``must_live`` (anything with ``alive()``, such as a :class:`Child`) has ended. An
    exception from ``cond`` counts as not yet (a buffer being replaced, a torn read)."""
    end = time.monotonic() + timeout_s
    while True:
        try:
            v = cond()
        except Exception:  # noqa: BLE001 - not there yet
            v = None
        if v:
            return v
        if time.monotonic() > end or any(not p.alive() for p in must_live):
            return None
        time.sleep(poll_s)


def default_sigint() -> None:
    """In a child before exec: SIGINT back to default, so Python installs its handler even
    when the parent runs as a background job (whose shell ignores SIGINT for it)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class Child:
    """A child process in its own session (a Ctrl-C on the parent reaches only the parent),
    SIGINT at its default in it, stdin from /dev/null, its output (stdout and stderr) in a
    file ``workdir/ROLE-xxxx.log`` (no pipe to fill); run from the package's root with
    :func:`package_env` (no COLUMNS, LINES). :meth:`stop` is bounded: ask, wait, then
    SIGKILL its group. The /dev/shm files it mapped are noted (:attr:`maps`) whenever it is
    signalled or stopped, so they can be looked for after it has gone."""

    def __init__(self, role: str, argv: list[str], workdir: Path) -> None:
        self.role = role
        self.argv = argv
        self.log_path = Path(workdir) / f"{role}-{uuid.uuid4().hex[:4]}.log"
        self._log = open(self.log_path, "w")
        self.p = subprocess.Popen(argv, stdout=self._log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                  cwd=ROOT, env=package_env(("COLUMNS", "LINES")), start_new_session=True,
                                  preexec_fn=default_sigint, text=True)
        self.t0 = time.monotonic()
        self.stopped = False  #: SIGSTOPped and not continued
        self.killed = False  #: SIGKILLed by the parent (its output may end anywhere)
        self.exit_how = ""  #: how :meth:`stop` ended it
        self.maps: set[str] = set()

    @property
    def pid(self) -> int:
        return self.p.pid

    def alive(self) -> bool:
        return self.p.poll() is None

    def note_maps(self) -> None:
        if self.alive():
            self.maps |= shm_maps(self.pid)

    def send(self, sig: int) -> float:
        """Signal the process (not its group); the time it was sent (CLOCK_MONOTONIC)."""
        self.note_maps()
        t = time.monotonic()
        try:
            os.kill(self.pid, sig)
        except ProcessLookupError:
            return t
        if sig == signal.SIGSTOP:
            self.stopped = True
        elif sig == signal.SIGCONT:
            self.stopped = False
        elif sig == signal.SIGKILL:
            self.killed = True
        return t

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 15.0) -> str:
        """Ask it to stop with ``sig`` (SIGCONT first if stopped); SIGKILL its group when it
        has not exited ``timeout_s`` later. How it ended: "had exited (RC)", "SIGINT -> exit
        RC" or "needed SIGKILL (...)" (also :attr:`exit_how`)."""
        if not self.alive():
            self.exit_how = self.exit_how or f"had exited ({self.p.returncode})"
            return self.exit_how
        self.note_maps()
        if self.stopped:
            self.send(signal.SIGCONT)
        with contextlib.suppress(ProcessLookupError):
            os.kill(self.pid, sig)
        try:
            rc = self.p.wait(timeout=timeout_s)
            self.exit_how = f"{signal.Signals(sig).name} -> exit {rc}"
        except subprocess.TimeoutExpired:
            self.before_kill()
            self.kill_group()
            self.exit_how = f"needed SIGKILL ({timeout_s:g} s after {signal.Signals(sig).name})"
        return self.exit_how

    def before_kill(self) -> None:
        """Called when :meth:`stop` gives up, before the SIGKILL (a subclass asks for a dump)."""

    def wait_exit(self, timeout_s: float = 10.0) -> bool:
        try:
            self.p.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return False
        return True

    def kill_group(self) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.pid, signal.SIGCONT)
            os.killpg(self.pid, signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.p.wait(timeout=10)

    def text(self) -> str:
        """Its output so far."""
        with contextlib.suppress(ValueError, OSError):
            self._log.flush()
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def lines(self, n: int) -> list[str]:
        """The last ``n`` lines of its output."""
        return self.text().splitlines()[-n:]

    def tail(self, n: int = 6) -> str:
        """The last ``n`` lines of its output on one line, `` | `` between them."""
        return " | ".join(line.strip() for line in self.lines(n))

    def close(self) -> None:
        """SIGKILL its group if it still runs; close its output file."""
        if self.alive():
            self.kill_group()
        self._log.close()


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
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stdin=subprocess.PIPE if stdin_pipe else subprocess.DEVNULL,
                            text=True, env=package_env())


def first_line(proc: Any, timeout_s: float = 0.0) -> str | None:
    """The first line a :func:`spawn_helper` process printed, stripped, once it has printed
    one or ended ("" for an end without a line); None while it has said nothing within
    ``timeout_s`` (0: do not wait). Never blocks past ``timeout_s``: the pipe is read with
    ``os.read`` as bytes arrive (a part of a line is kept on ``proc`` for the next call), so
    a helper that prints half a line cannot hang the service's thread. Its stdout is closed
    once the line is read."""
    import select
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


__all__ = ["set_parent_death_signal", "process_state", "cpu_seconds", "cpu_seconds_or_none", "pid_alive", "shm_maps",
           "children", "cmdline", "listen_port",
           "rss_mb", "free_port", "until", "default_sigint", "Child", "package_env", "ROOT", "spawn_helper",
           "first_line", "stop_helper", "HelperWatch", "bring_up", "NO_WORD"]
