"""The output guardian: a process beside the service that writes the DAC to 0 V when the
service can no longer do it itself.

The service makes its outputs safe whenever it runs: a stale heartbeat, a refused command,
a fault, its own stop (docs/safety.md). It cannot when it is killed (SIGKILL, a crash, the
OOM killer) or stopped (SIGSTOP, a debugger): the VMIVME-4100 then holds the last codes
written (hardware-registers reference: the DAC keeps its registers until written or reset),
and an arm moving on them keeps moving. ``pfma serve`` on a bus another process can reach
(a Modbus gateway, a VME device file, a CAEN bridge) therefore starts this guardian, with
its own connection to the bus and the DAC board's driver:

- **the service died**: the guardian's stdin, a pipe from the service, reads end-of-file
  (the kernel closes it when the last thread of the service is gone, whatever killed it), or
  its parent is no longer the service -> every DAC channel written 0 V at once (rates 0,
  current limits 0 V: brakes set), one line on stderr, the zeros written again over the next
  second (:data:`REWRITES_S`: a write the service sent just before it died may land after
  the first), exit;
- **the service is stopped** (``/proc`` state ``T``/``t``) for longer than the watchdog plus
  one frame -> 0 V, once per stop, one line; a service that runs again writes its own
  outputs in its next frame (it names the stall, and rates only follow commands of an age it
  accepts: docs/safety.md);
- **the service stops in order**: it writes ``stop`` to the guardian's stdin, and the
  guardian exits without writing (the service has written its safe outputs itself).

Why not the parent-death signal and ``getppid``: with them, 3 of 15 runs of the gateway test
left the DAC driving after a SIGKILL, the guardian leaving as on an orderly stop (most
likely because Linux sends that signal when the *thread* that started the child ends and
re-parents the child to a sibling thread of the same process first). SIGTERM alone is
ignored.

Each second the guardian reads the DAC's control register (a keep-alive for connection-based buses and a
check that it can still reach the board; the first failure is said once). On the
simulated rack inside the service's process there is no guardian: the simulated arm lives
and dies with that process.

The amplifier-enable charge pump (rack file ``[amplifier_enable]``, ``ioservice.chargepump``)
is the service's alone: the guardian never toggles it, so a service that died or stays
stopped has dropped the amplifiers through it whatever the guardian can write. When the
guardian cannot write the DAC either it says so and never calls the outputs safe: they may
hold their last values, and on a rack without that output only the hardware E-stop stops
the arm (issue 28 item 5, docs/safety.md "Honest outputs").

Assumption (named once, here): the guardian writes the data registers only; it leaves the
control register's P3 output enable as it is, so the service's idea of its outputs stays true when it
runs again.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import time
from typing import Any, Callable

from pfma.process import NO_WORD, bring_up, process_state, spawn_helper, stop_helper

#: how often the guardian looks at its parent, s
POLL_S = 0.002
#: how often it reads the DAC's CSR (keep-alive, reachability), s
KEEPALIVE_S = 1.0
_log = logging.getLogger(__name__)
#: how the guardian's stderr lines begin (``pfma.log.configure``): "pfma serve guardian: TEXT"
PROG = "pfma serve guardian"

#: the line the guardian prints when it is ready
READY = "guardian ready"
#: after the service died, the zeros are written again this long after the first write, s:
#: a write the service sent just before it died may still be carried out after the
#: guardian's (it sat in a gateway's socket buffer: seen once in CI, the DAC left driving);
#: the last rewrite comes after anything in flight (assumption: a gateway answers within 1 s)
REWRITES_S = (0.01, 0.05, 0.2, 1.0)


class Guardian:
    """Watches process ``parent_pid`` and writes ``dac`` to 0 V when it died or stays stopped.

    :param dac: the DAC board's driver on the guardian's own bus connection (``zero_all``,
        ``read_control``: drivers.dac.vmivme4100)
    :param hold_s: how long a stopped parent may stay stopped (the watchdog plus one frame)
    :param state: the parent's process state letter (injectable for tests)
    :param parent_alive: whether the parent is still this process's parent (injectable)
    :param amplifier_enable: the rack's charge pump (``AmplifierEnable.describe()``), "" for none
    """

    def __init__(self, dac, parent_pid: int, hold_s: float, *, now: Callable[[], float] = time.monotonic,
                 state: Callable[[int], str] = process_state,
                 parent_alive: Callable[[], bool] | None = None, say: Callable[[str], None] | None = None,
                 amplifier_enable: str = "") -> None:
        self.dac = dac
        self.parent_pid = parent_pid
        self.hold_s = hold_s
        self.now = now
        self.state = state
        self.parent_alive = parent_alive or (lambda: os.getppid() == parent_pid)
        self.say = say or _log.warning  # "pfma serve guardian: TEXT" (pfma.log, configured in main)
        self.stopped_since: float | None = None
        self.acted_this_stop = False
        self.safe_writes = 0  #: times the DAC was written to 0 V
        self._keepalive_t = now()
        self._bus_said = False
        self.amplifier_enable = amplifier_enable

    def not_written(self) -> str:
        """What a failed 0 V write means (never "safe"): the outputs may hold their last values."""
        amp = (f"the amplifier-enable charge pump ({self.amplifier_enable}) is no longer toggled: its relay "
               f"drops the amplifiers" if self.amplifier_enable else
               "this rack has no amplifier-enable output: only the hardware E-stop stops the arm")
        return (f"the DAC could NOT be written: its outputs may hold their last values; {amp}; "
                f"press the hardware E-stop if the arm moves")

    def write_safe(self) -> bool:
        try:
            self.dac.zero_all()  # every channel's 0 V code, one block write
        except Exception as err:  # noqa: BLE001 - said, never a traceback: this is the last net
            self.say(f"could not write the DAC to 0 V: {type(err).__name__}: {err}")
            return False
        self.safe_writes += 1
        return True

    def settle(self, sleep: Callable[[float], None] = time.sleep) -> int:
        """After the service died: the zeros again at :data:`REWRITES_S` after now, so that
        a write of the dead service still in flight lands before the last one. Returns the
        rewrites that succeeded."""
        t0, n = self.now(), 0
        for t in REWRITES_S:
            wait = t0 + t - self.now()
            if wait > 0:
                sleep(wait)
            n += self.write_safe()
        return n

    def step(self) -> str:
        """One look. Returns "died" (outputs written safe; the guardian's work is over),
        "stopped" (written safe for this stop), or "" (nothing to do)."""
        t = self.now()
        if not self.parent_alive():
            ok = self.write_safe()
            self.say(f"the service (pid {self.parent_pid}) is gone: "
                     + ("every DAC channel written to 0 V (rates 0, current limits 0: brakes set)"
                        if ok else self.not_written()))
            return "died"
        if self.state(self.parent_pid) in ("T", "t"):
            if self.stopped_since is None:
                self.stopped_since = t
            elif not self.acted_this_stop and t - self.stopped_since >= self.hold_s:
                self.acted_this_stop = True
                ok = self.write_safe()
                self.say(f"the service (pid {self.parent_pid}) has been stopped for "
                         f"{(t - self.stopped_since) * 1e3:.0f} ms: "
                         + ("every DAC channel written to 0 V" if ok else self.not_written()))
                return "stopped"
        else:
            if self.acted_this_stop:
                self.say(f"the service (pid {self.parent_pid}) runs again: its outputs are its own")
            self.stopped_since, self.acted_this_stop = None, False
        if t - self._keepalive_t >= KEEPALIVE_S:
            self._keepalive_t = t
            self._keepalive()
        return ""

    def _keepalive(self) -> None:
        try:
            self.dac.read_control()
            self._bus_said = False
        except Exception as err:  # noqa: BLE001
            if not self._bus_said:
                self._bus_said = True
                self.say(f"cannot reach the DAC board now ({type(err).__name__}: {err}); still watching")


class GuardianProcess:
    """The guardian in its own process (``python -m ioservice.guardian``), started by the
    service, which holds the write end of its stdin for as long as it lives, and stopped by
    it (``stop`` on that pipe) after its orderly stop. A :class:`pfma.process.Restartable`:
    ``pfma serve`` starts it again if it ends while the service runs."""

    label = "output guardian"
    lost = "the DAC is not guarded against this service's death until it is back"

    def __init__(self, bus_url: str, rack: str, hold_s: float) -> None:
        self.argv = [sys.executable, "-m", "ioservice.guardian", "--bus", bus_url, "--rack", rack,
                     "--parent-pid", str(os.getpid()), "--hold-ms", repr(hold_s * 1e3)]
        self.proc: Any = None  # subprocess.Popen once started

    def spawn(self) -> Any:
        """Start the process without waiting for it (its first line: :meth:`accept`)."""
        self.proc = spawn_helper(self.argv, stdin_pipe=True)
        return self.proc

    def accept(self, line: str) -> str:
        """"" when ``line`` says it is ready, else why not (one line)."""
        return "" if line == READY else (line.removeprefix("error: ") or NO_WORD)

    def start(self, timeout_s: float = 30.0) -> str:
        """Start it; "" once it is ready, else why it is not running (one line)."""
        why = bring_up(self, timeout_s)
        if why:
            self.stop()
        return why

    def stop(self, timeout_s: float = 5.0) -> None:
        """Tell it the service stops in order (``stop`` on its stdin: it leaves without
        writing), then wait; SIGKILL after ``timeout_s``."""
        proc, self.proc = self.proc, None
        if proc is None:
            return
        try:
            proc.stdin.write("stop\n")
            proc.stdin.flush()
        except (OSError, ValueError):
            pass  # it has gone already
        stop_helper(proc, timeout_s)
        try:
            proc.stdin.close()
        except (OSError, ValueError):
            pass

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ioservice.guardian", description=__doc__.split("\n\n")[0])
    p.add_argument("--bus", required=True)
    p.add_argument("--rack", default="fake")
    p.add_argument("--parent-pid", type=int, required=True)
    p.add_argument("--hold-ms", type=float, required=True)
    args = p.parse_args(argv)
    from pfma.log import configure
    configure(PROG)
    # a Ctrl-C goes to the service, which stops us; a SIGTERM decides nothing (above)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    if os.getppid() != args.parent_pid:
        print("error: the service died before its guardian started", flush=True)
        return 1
    from drivers.bus import open_bus
    from drivers.rackio import RackIO
    from pfma.errors import PfmaError
    from pfma.rack import load_rack
    try:
        rack = load_rack(args.rack)
        dacs = rack.boards_of("dac")
        if not dacs:
            raise PfmaError(f"rack {rack.name} has no DAC board")
        bus = open_bus(args.bus)
        dac = RackIO(bus, rack).driver(dacs[0])
    except (PfmaError, OSError, ValueError) as err:
        print(f"error: {err}", flush=True)
        return 1
    amp = rack.amplifier_enable
    g = Guardian(dac, args.parent_pid, args.hold_ms / 1e3, amplifier_enable=amp.describe() if amp else "")
    print(READY, flush=True)
    try:
        sys.stdout.close()
    except OSError:
        pass
    import select
    fd = sys.stdin.fileno()
    while True:
        ready, _, _ = select.select([fd], [], [], POLL_S)
        if ready:
            said = os.read(fd, 64)
            if b"stop" in said:
                return 0  # the service stops in order: it made its outputs safe itself
            if not said:  # end-of-file: the service is gone
                g.parent_alive = lambda: False
        if g.step() == "died":
            g.settle()
            return 0


if __name__ == "__main__":
    sys.exit(main())
