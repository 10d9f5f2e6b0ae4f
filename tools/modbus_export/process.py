"""The export in its own process: ``python -m tools.modbus_export`` (:func:`main`), the
:class:`ExportProcess` that ``pfma serve --modbus`` starts, and ``--modbus HOST:PORT``
(:func:`parse_host_port`).
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading

from pfma.errors import ConfigError, PfmaError
from pfma.process import NO_WORD, bring_up, set_parent_death_signal, spawn_helper, stop_helper
from tools.modbus_export.export import ModbusExport
from tools.modbus_export.map import DEFAULT_PORT, ModbusExportError
from tools.modbus_export.server import ExportLimits

log = logging.getLogger("tools.modbus_export")  # one logger for the package: its records keep their name


def parse_host_port(host_port: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``"HOST:PORT"``, ``":PORT"``, ``"PORT"`` or ``"[v6addr]:PORT"`` -> (host, port)."""
    s = host_port.strip()
    host, port_s = default_host, s
    if s.startswith("["):
        end = s.find("]")
        if end < 0 or not s[end + 1:].startswith(":"):
            raise ConfigError(f"--modbus {host_port!r}: expected [IPv6]:PORT")
        host, port_s = s[1:end], s[end + 2:]
    elif ":" in s:
        h, _, port_s = s.rpartition(":")
        host = h or default_host
    try:
        port = int(port_s)
    except ValueError:
        raise ConfigError(f"--modbus {host_port!r}: expected HOST:PORT with a numeric port, "
                          f"e.g. 127.0.0.1:{DEFAULT_PORT}") from None
    if not 0 <= port <= 65535:
        raise ConfigError(f"--modbus {host_port!r}: port {port} out of range 0..65535")
    return host, port


#: the export process's priority below the service's (``os.nice`` increment): on a
#: loaded host the acquisition loop wins the CPU over Modbus clients
EXPORT_NICE = 5
#: the first line the export process prints when it listens
_READY = "modbus-export listening"


class ExportProcess:
    """The Modbus export in its own process (``python -m tools.modbus_export``), started
    by ``pfma serve --modbus``: Modbus clients cost the export's process CPU time, never
    the acquisition loop's interpreter (the in-process export shared the service's GIL:
    issue 20 measured ~50 extra dropped frames per 10 s under a 1,800 request/s flood).

    The process attaches to the buffer by name like any tool; it runs below the service
    (time-sharing even under ``pfma serve --realtime``, off the service's pinned CPU, nice
    :data:`EXPORT_NICE`), exits when its parent dies (``PR_SET_PDEATHSIG``) and stops
    cleanly on SIGTERM or SIGINT; its log lines (the refusal summaries) go to the
    service's stderr. Start it from a thread that lives as long as the service (the main
    thread): Linux sends the parent-death signal when the *thread* that started it ends.
    """

    def __init__(self, buffer_name: str, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 allow_writes: bool = False, *, rack: str | None = None,
                 limits: ExportLimits | None = None, nice: int = EXPORT_NICE,
                 requests_wm: str | None = None) -> None:
        self.buffer_name = buffer_name
        self.requests_wm = requests_wm
        self.host = host
        self.port = port
        self.allow_writes = allow_writes
        self.rack = rack
        self.limits = limits or ExportLimits()
        self.nice = nice
        self.proc: subprocess.Popen | None = None

    def argv(self) -> list[str]:
        lim = self.limits
        argv = [sys.executable, "-m", "tools.modbus_export", "--buffer", self.buffer_name,
                "--listen", self.address,
                "--max-connections", str(lim.max_connections),
                "--in-buffer-bytes", str(lim.in_buffer_bytes),
                "--out-buffer-bytes", str(lim.out_buffer_bytes),
                "--idle-timeout-s", repr(lim.idle_timeout_s),
                "--summary-interval-s", repr(lim.summary_interval_s),
                "--nice", str(self.nice), "--parent-pid", str(os.getpid())]
        if self.rack:
            argv += ["--rack", self.rack]
        if self.requests_wm is not None:
            argv += ["--requests", self.requests_wm]
        elif self.allow_writes:
            argv.append("--writes")
        return argv

    @property
    def address(self) -> str:
        """HOST:PORT as ``--listen`` takes it (an IPv6 host in brackets)."""
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"

    #: how :class:`pfma.process.HelperWatch` names it, and what its absence means
    label = "Modbus export"
    lost = "Modbus clients get no answers until it is back"

    def spawn(self) -> subprocess.Popen:
        """Start the process without waiting for it (its first line: :meth:`accept`); on the
        port it listens on (a restart keeps the port port 0 was given)."""
        self.proc = spawn_helper(self.argv())
        return self.proc

    def accept(self, line: str) -> str:
        """"" when ``line`` says it listens (its port noted), else why not (one line)."""
        if line.startswith(_READY):
            self.port = int(line.rsplit(":", 1)[1])
            return ""
        return line.removeprefix("error: ") or NO_WORD

    def start(self, timeout_s: float = 30.0) -> "ExportProcess":
        """Start the process; return once it listens.

        :raises ModbusExportError: it could not attach, claim or listen (its one-line
            reason), or did not say it listens within ``timeout_s``
        """
        why = bring_up(self, timeout_s)
        if not why:
            return self
        self.stop()
        raise ModbusExportError(why)

    def stop(self, timeout_s: float = 5.0) -> None:
        """SIGTERM, then SIGKILL after ``timeout_s``; waits for the process."""
        proc, self.proc = self.proc, None
        stop_helper(proc, timeout_s)

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


def start_export_from_args(buffer_name: str, host_port: str, allow_writes: bool,
                           rack: str | None = None, requests_wm: str | None = None) -> ExportProcess:
    """Parse ``HOST:PORT`` and start the export in its own process (for ``pfma serve
    --modbus``; :class:`ExportProcess`). The caller stops it (``export.stop()``) when the
    service stops.

    :param rack: the rack TOML of a buffer made from another rack file than the default
    :param requests_wm: the controller's world model: Modbus requests (HALT, CAMERA ROUTE)
        are posted to it (docs/modbus-map.md)
    """
    host, port = parse_host_port(host_port)
    return ExportProcess(buffer_name, host=host, port=port, allow_writes=allow_writes or requests_wm is not None,
                         rack=rack, requests_wm=requests_wm).start()


def _leave_the_service_alone(nice: int) -> None:
    """Run below the service: an ordinary time-sharing process (a ``pfma serve --realtime``
    parent's SCHED_FIFO is inherited by its children), off the CPU the service is pinned
    to (when it is pinned to fewer CPUs than there are), ``nice`` steps down. Best effort."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass
    try:
        pinned = os.sched_getaffinity(0)
        others = set(range(os.cpu_count() or 1)) - pinned
        if others and len(pinned) < (os.cpu_count() or 1):
            os.sched_setaffinity(0, others)
    except (OSError, AttributeError):
        pass
    if nice:
        try:
            os.nice(nice)
        except OSError:
            pass


def main(argv: list[str] | None = None) -> int:
    """``python -m tools.modbus_export``: one export process (what ``pfma serve --modbus``
    starts). Prints ``modbus-export listening on HOST:PORT`` once it listens, or one
    ``error: ...`` line and exits 1."""
    import argparse
    p = argparse.ArgumentParser(prog="python -m tools.modbus_export",
                                description="Serve a Bit3 buffer over Modbus TCP (docs/modbus-map.md).")
    d = ExportLimits()
    p.add_argument("--buffer", default="pfma", help="Bit3 shared-memory name (default pfma)")
    p.add_argument("--listen", default=f"127.0.0.1:{DEFAULT_PORT}", metavar="HOST:PORT",
                   help=f"address to serve (default 127.0.0.1:{DEFAULT_PORT}; port 0: any free one)")
    p.add_argument("--writes", action="store_true", help="accept camera-route requests (claims the controller role; never arms or moves the arm)")
    p.add_argument("--requests", default=None, metavar="WM",
                   help="post HALT and CAMERA ROUTE requests to the controller of world model WM "
                        "(holding registers 9000-9004; never arms or moves the arm)")
    p.add_argument("--rack", default=None, help="rack TOML of the buffer (default: the default rack)")
    p.add_argument("--max-connections", type=int, default=d.max_connections,
                   help=f"clients at once; one more is closed at once (default {d.max_connections})")
    p.add_argument("--in-buffer-bytes", type=int, default=d.in_buffer_bytes,
                   help=f"per connection: requests received, not yet answered (default {d.in_buffer_bytes})")
    p.add_argument("--out-buffer-bytes", type=int, default=d.out_buffer_bytes,
                   help=f"per connection: answers a slow reader has not taken (default {d.out_buffer_bytes})")
    p.add_argument("--idle-timeout-s", type=float, default=d.idle_timeout_s,
                   help=f"close a connection with no traffic for this long (default {d.idle_timeout_s:g})")
    p.add_argument("--summary-interval-s", type=float, default=d.summary_interval_s,
                   help=f"at most one log line about refused requests per interval "
                        f"(default {d.summary_interval_s:g})")
    p.add_argument("--nice", type=int, default=0, help="lower this process's priority by N")
    p.add_argument("--parent-pid", type=int, default=None,
                   help="exit when this process (the service) is gone")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="pfma serve: %(message)s")
    logging.getLogger().handlers[0].addFilter(lambda r: r.levelno >= logging.WARNING)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    if args.parent_pid is not None:
        set_parent_death_signal(signal.SIGTERM)
        if os.getppid() != args.parent_pid:  # the parent died before the signal was armed
            return 0
    _leave_the_service_alone(args.nice)
    export = None
    try:
        host, port = parse_host_port(args.listen)
        limits = ExportLimits(args.max_connections, args.in_buffer_bytes, args.out_buffer_bytes,
                              args.idle_timeout_s, args.summary_interval_s)
        layout = None
        if args.rack:
            from bit3.layout import build_layout
            from pfma.rack import load_rack
            layout = build_layout(load_rack(args.rack))
        export = ModbusExport(args.buffer, host, port, args.writes or args.requests is not None, layout=layout,
                              limits=limits, requests_wm=args.requests).start()
    except PfmaError as err:
        print(f"error: {err}", flush=True)
        return 1
    try:
        try:
            print(f"{_READY} on {export.host}:{export.port}", flush=True)
        except BrokenPipeError:
            # the service that started it died before reading the line (the kill matrix's
            # SIGKILL at start-up): nobody to serve; stop without a traceback, and point the
            # stdout Python flushes at exit somewhere that cannot break
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            log.warning("Modbus export %s:%d: the process that started it is gone; stopping", export.host,
                        export.port)
            return 1
        while not stop.wait(0.5):
            if args.parent_pid is not None and os.getppid() != args.parent_pid:
                break
            if not export.running:
                log.warning("Modbus export %s:%d: its server stopped", export.host, export.port)
                return 1
    finally:
        export.stop()
    return 0
