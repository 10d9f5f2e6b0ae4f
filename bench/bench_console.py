"""The operator console's CPU in real time (issue 18 "Performance": at most 10 % of a core).

The system simulator (the simulated rack, the real I/O service and the real controller on
one simulated clock, paced to the wall clock as ``make run`` paces it) runs in a child
process on a named Bit3 buffer and world model, powered up; an operator pushes on the tool
(a slow sinusoid added to the arm's own load on the fake F/T sensor, :data:`_SIMULATOR`), so
every console refresh has a new force: the worst case for the force displays. ``pfma
console --buffer NAME --wm NAME`` runs as another process, on a pseudo-terminal of
:data:`COLS` x :data:`ROWS` (a real terminal driver: Textual writes every frame it draws to
the pty, which this process reads and throws away). The console's CPU time (utime + stime
from ``/proc/PID/stat``, what psutil reads) is taken over ``seconds`` of wall time, first on
the primary display, then with the force displays open (key ``f``: the F/T time plots and
the pseudo-3D vector), after :data:`SETTLE_S` for each to settle. The simulator is another
process, so its CPU is not counted; on a host with fewer free cores than the two processes
want, the figure includes what contention costs the console (cache, wake-ups).

``pfma bench console --seconds 20`` (the issue's measurement). Figures, never an assert.
"""

from __future__ import annotations

import fcntl
import os
import signal
import struct
import subprocess
import sys
import termios
import threading
import time
import uuid

from pfma.process import cpu_seconds, default_sigint

#: the console's terminal (the size the console's tests and snapshots use)
COLS, ROWS = 180, 50
#: seconds a display is given before its CPU is measured (start-up, the first drawings)
SETTLE_S = 3.0
#: the console must draw its areas within this
START_TIMEOUT_S = 60.0


class _Pty:
    """``pfma console`` on a pseudo-terminal; its output read (and counted) by a thread."""

    def __init__(self, argv: list[str]) -> None:
        master, slave = os.openpty()
        fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", ROWS, COLS, 0, 0))
        env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "LINES")}
        env["TERM"] = "xterm-256color"
        self.p = subprocess.Popen(argv, stdin=slave, stdout=slave, stderr=slave, env=env,
                                  start_new_session=True, close_fds=True)
        os.close(slave)
        self.fd = master
        self.bytes = 0
        self.tail = b""
        self._t = threading.Thread(target=self._drain, name="bench-console-pty", daemon=True)
        self._t.start()

    def _drain(self) -> None:
        while True:
            try:
                data = os.read(self.fd, 65536)
            except OSError:
                return
            if not data:
                return
            self.bytes += len(data)
            self.tail = (self.tail + data)[-65536:]

    def wait_for(self, text: bytes, timeout_s: float) -> bool:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            if text in self.tail:
                return True
            if self.p.poll() is not None:
                return False
            time.sleep(0.05)
        return False

    def key(self, k: str) -> None:
        os.write(self.fd, k.encode())

    def close(self) -> None:
        for _ in range(3):  # q closes an open display, then quits
            if self.p.poll() is not None:
                break
            self.key("q")
            try:
                self.p.wait(3)
            except subprocess.TimeoutExpired:
                pass
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait()
        try:
            os.close(self.fd)
        except OSError:
            pass


#: the child process: the system simulator paced to the wall clock, powered up, an operator's
#: push on the tool (N, N*m, a few seconds' period) added to the arm's load on the F/T sensor
_SIMULATOR = """
import math, sys, time
from controller.layers import Request
from sim.system import SystemSimulator
name, wm, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3])
sim = SystemSimulator(name=name, wm_name=wm)
arm = sim.world.ft.load_fn
def load(t):
    f, m = arm(t) if arm is not None else ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    push = (12.0 * math.sin(1.3 * t), 6.0 * math.cos(0.9 * t), 20.0 * math.sin(0.4 * t))
    twist = (0.4 * math.sin(1.1 * t), 0.3 * math.cos(0.7 * t), 0.1 * math.sin(0.5 * t))
    return tuple(a + b for a, b in zip(f, push)), tuple(a + b for a, b in zip(m, twist))
sim.world.ft.load_fn = load
sim.step(10)
sim.rt.request(Request.POWER_UP)
print("ready", flush=True)
w0, s0 = time.monotonic(), sim.clock.now()
try:
    while time.monotonic() - w0 < seconds:
        if sim.clock.now() - s0 > time.monotonic() - w0:
            time.sleep(0.002)
            continue
        sim.step(4)
except KeyboardInterrupt:
    pass
finally:
    sim.close()
"""


def _measure(pid: int, seconds: float, pty: _Pty, buffer: str) -> dict:
    """The console's CPU over ``seconds``, and how many different F/T forces the service
    published meanwhile (sampled at 10 Hz, as the console samples them)."""
    from bit3.client import Client
    forces: set[tuple[float, ...]] = set()
    with Client.attach(buffer) as c:
        c0, t0, b0 = cpu_seconds(pid), time.monotonic(), pty.bytes
        while time.monotonic() - t0 < seconds:
            forces.add(tuple(round(float(x), 2) for x in c.read_inputs().ft_force_n))
            time.sleep(0.1)
        c1, t1, b1 = cpu_seconds(pid), time.monotonic(), pty.bytes
    wall = t1 - t0
    return {"cpu_percent": 100.0 * (c1 - c0) / wall, "wall_s": wall, "cpu_s": c1 - c0,
            "terminal_kb_per_s": (b1 - b0) / 1e3 / wall, "ft_forces_seen": len(forces)}


def figures(seconds: float = 20.0) -> dict:
    name = "pfma-benchcon-" + uuid.uuid4().hex[:6]
    wm = "pfma_benchcon_" + uuid.uuid4().hex[:6]
    py = sys.executable
    procs: list[subprocess.Popen] = []
    out: dict = {"seconds": seconds, "terminal": f"{COLS}x{ROWS}", "cpus": os.cpu_count(),
                 "loadavg_before": os.getloadavg()[0]}
    con = None
    try:
        sim = subprocess.Popen([py, "-c", _SIMULATOR, name, wm, str(2 * seconds + 4 * SETTLE_S + START_TIMEOUT_S)],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
                               preexec_fn=default_sigint)
        procs.append(sim)
        if sim.stdout is None or sim.stdout.readline().strip() != "ready":
            out["error"] = "the simulator did not start: " + (sim.stdout.read()[-400:] if sim.stdout else "")
            return out
        con = _Pty([py, "-m", "tools.cli", "console", "--buffer", name, "--wm", wm])
        if not con.wait_for(b"Global Commands", START_TIMEOUT_S):
            out["error"] = "the console did not draw its areas: " + con.tail[-400:].decode(errors="replace")
            return out
        time.sleep(SETTLE_S)
        out["primary"] = _measure(con.p.pid, seconds, con, name)
        con.key("f")
        if not con.wait_for(b"Escape/f close", START_TIMEOUT_S):  # the line under the plots
            out["error"] = (f"the force displays did not open (console exit {con.p.poll()}): "
                            + con.tail[-400:].decode(errors="replace"))
            return out
        time.sleep(SETTLE_S)
        out["force"] = _measure(con.p.pid, seconds, con, name)
        out["loadavg_after"] = os.getloadavg()[0]
    finally:
        if con is not None:
            con.close()
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(15)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
        try:  # normally gone with the simulator already
            from bit3.buffer import Bit3Buffer
            from controller.worldmodel import WorldModel
            WorldModel.remove_segment(wm)
            Bit3Buffer.unlink(name)
        except Exception:  # noqa: BLE001
            pass
    return out


def run(seconds: float = 20.0) -> dict:
    f = figures(seconds)
    print(f"pfma console on a {f['terminal']} pty over the system simulator (powered up, a changing push on the "
          f"F/T sensor; real time), {seconds:g} s each, {f['cpus']} CPUs, load {f['loadavg_before']:.2f} before")
    if "error" in f:
        print(f"  error: {f['error']}")
        return f
    for key, what in (("primary", "primary display"), ("force", "force displays (f)")):
        m = f[key]
        print(f"  {what:<20} {m['cpu_percent']:5.1f} % of one core ({m['cpu_s']:.2f} s CPU in {m['wall_s']:.1f} s), "
              f"{m['terminal_kb_per_s']:.1f} kB/s to the terminal, {m['ft_forces_seen']} different F/T forces "
              f"at 10 Hz")
    return f
