"""The service's frames under a Modbus read flood on loopback (issue 20 item 2).

``pfma serve --rack fake --modbus 127.0.0.1:PORT`` runs as a process of this venv's
python, twice for ``seconds`` each (after it publishes frames): once with nobody talking
to its Modbus export, once with this process flooding the export with valid reads
(function code 4: the whole ``inputs`` body, 125 registers, and the float32 channel
block, alternately) at ``rate`` requests per second over ``connections`` TCP connections,
each request waiting for its answer. Reported per run, from the service's stats area: frames,
dropped frames and overruns in the window, dropped frames per 10 s, the CPU of the service
and of its Modbus export process, and the requests answered, refused and timed out. The
goal (issue 20): the flood costs at most 5 extra dropped frames per 10 s.

The flood client runs on the same host (a 2-core VM here); on a lab PC the HMI is another
machine, so this is the harder case. Nothing controls the arm: the service stays SAFE.

Run: ``pfma bench flood [--seconds S] [--rounds N] [--realtime] [--check]`` (default 10 s,
one round, :data:`DEFAULT_RATE` requests per second; rounds alternate a quiet and a flooded
run, so a change in the host's load falls on both; ``--realtime`` runs ``pfma serve
--realtime``, SCHED_FIFO and pinned, as a lab PC does).

``--check`` judges the figures (:func:`judge`): at most :data:`MAX_EXTRA_DROPPED_PER_10S`
extra dropped frames per 10 s flooded against quiet, over all rounds, and the export
answering in every flooded run (at least :data:`MIN_ANSWERED_SHARE` of the requests asked
for answered per second, none refused, none timed out or cut). CI judges it with
``--realtime --rounds 5`` only (.ci/run): a time-sharing service on the shared 2-core VM
drops 0-204 frames per 10 s with nobody talking Modbus, so its difference is the host's
noise, not the flood's (docs/reliability.md).
"""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import threading
import time
import uuid

from pfma.process import children, cmdline, cpu_seconds, free_port

#: bound on the service's start
START_TIMEOUT_S = 30.0
#: longest wait for the service's next statistics publication (it publishes about once a second)
STATS_WAIT_S = 3.0
#: flood defaults (issue 20: "2,000 request/s valid-read flood")
DEFAULT_RATE = 2000.0
DEFAULT_CONNECTIONS = 4
#: the reads of the flood: (function code, first register, count), alternately
READS = ((4, 0, 125), (4, 20000, 64))
#: seconds per run when none is given (the goal is stated per 10 s)
DEFAULT_SECONDS = 10.0
#: issue 20's goal: the flood costs at most this many extra dropped frames per 10 s
MAX_EXTRA_DROPPED_PER_10S = 5.0
#: "the export answering": at least this share of the requests asked for is answered per
#: second in every flooded run. The flood client shares the host's CPUs with the service
#: and the export, so it does not always send the whole rate (71-100 % here, docs/chaos.md).
MIN_ANSWERED_SHARE = 0.5


def _recv_exact(s: socket.socket, n: int) -> bytes:
    out = bytearray()
    while len(out) < n:
        chunk = s.recv(n - len(out))
        if not chunk:
            raise ConnectionError("closed by the export")
        out += chunk
    return bytes(out)


class Flood:
    """``rate`` valid reads per second over ``connections`` blocking connections (one
    thread each, absolute send deadlines, no catch-up burst after a late answer)."""

    def __init__(self, port: int, rate: float = DEFAULT_RATE, connections: int = DEFAULT_CONNECTIONS) -> None:
        self.port = port
        self.rate = rate
        self.connections = connections
        self.answered = 0
        self.refused = 0  # exception responses
        self.failed = 0  # time-outs, closed connections
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()

    def _run(self, k: int) -> None:
        period = self.connections / self.rate
        answered = refused = failed = 0
        tid = 0
        s = None
        t_next = time.monotonic() + k * period / self.connections
        while not self._stop.is_set():
            try:
                if s is None:
                    s = socket.create_connection(("127.0.0.1", self.port), timeout=1.0)
                    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                fc, addr, count = READS[tid % len(READS)]
                tid = (tid + 1) & 0xFFFF
                s.sendall(struct.pack(">HHHBBHH", tid, 0, 6, 1, fc, addr, count))
                head = _recv_exact(s, 7)
                body = _recv_exact(s, struct.unpack(">H", head[4:6])[0] - 1)
                if body[0] & 0x80:
                    refused += 1
                else:
                    answered += 1
            except OSError:
                failed += 1
                if s is not None:
                    s.close()
                s = None
            t_next += period
            delay = t_next - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                t_next = time.monotonic()  # late: no burst to catch up
        if s is not None:
            s.close()
        with self._lock:
            self.answered += answered
            self.refused += refused
            self.failed += failed

    def start(self) -> "Flood":
        for k in range(self.connections):
            t = threading.Thread(target=self._run, args=(k,), name=f"flood-{k}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(5)


def _window(client, seconds: float, svc: subprocess.Popen) -> dict:
    """Frames, dropped frames and overruns between two statistics publications at least
    ``seconds`` apart (the service publishes its stats about once a second)."""

    def next_stats(after: int) -> dict:
        t_end = time.monotonic() + STATS_WAIT_S
        while True:
            st = client.read_stats()
            if int(st["frames"]) != after or time.monotonic() > t_end or svc.poll() is not None:
                return {k: int(st[k]) for k in ("frames", "overruns", "dropped_frames")}
            time.sleep(0.02)

    s0 = next_stats(int(client.read_stats()["frames"]))
    t0 = time.monotonic()
    time.sleep(seconds)
    s1 = next_stats(s0["frames"])
    wall = time.monotonic() - t0
    return {"window_s": round(wall, 2), **{k: s1[k] - s0[k] for k in s0}}


def one_run(seconds: float, flood_rate: float | None, connections: int = DEFAULT_CONNECTIONS,
            realtime: bool = False) -> dict:
    """One ``pfma serve --rack fake --modbus`` process measured for ``seconds``; with
    ``flood_rate`` requests/s of valid reads meanwhile; ``realtime``: ``pfma serve
    --realtime`` (SCHED_FIFO, pinned), as on a lab PC."""
    from tools.attach import wait_for_frames

    py = sys.executable
    port = free_port()
    name = "pfma-bench-flood-" + uuid.uuid4().hex[:6]
    svc = subprocess.Popen([py, "-m", "tools.cli", "serve", "--rack", "fake", "--buffer", name,
                            "--modbus", f"127.0.0.1:{port}", *(["--realtime"] if realtime else []),
                            "--duration", str(seconds + START_TIMEOUT_S + 2 * STATS_WAIT_S + 5)],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    client = None
    try:
        client = wait_for_frames(name, 320, timeout_s=START_TIMEOUT_S, alive=lambda: svc.poll() is None)
        if client is None and svc.poll() is not None:
            return {"error": f"pfma serve exited {svc.returncode}: "
                             f"{(svc.stderr.read() if svc.stderr else '').strip()[-300:]}"}
        if client is None:
            return {"error": f"pfma serve published no frames within {START_TIMEOUT_S:g} s"}
        if not _export_answers(port):
            return {"error": f"the Modbus export on 127.0.0.1:{port} did not answer"}
        time.sleep(1.0)  # settle
        return _measure(client, svc, port, seconds, flood_rate, connections)
    finally:
        if client is not None:
            client.close()
        _stop_service(svc, name)


def _export_answers(port: int) -> bool:
    """The export is ready once it answers: whether it does within START_TIMEOUT_S."""
    t_end = time.monotonic() + START_TIMEOUT_S
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
            return True
        except OSError:
            if time.monotonic() > t_end:
                return False
            time.sleep(0.1)


def _measure(client, svc: subprocess.Popen, port: int, seconds: float, flood_rate: float | None,
             connections: int) -> dict:
    """The figures of :func:`one_run` over a window of ``seconds``, flooded meanwhile at
    ``flood_rate`` (None: quiet): frames, dropped frames, overruns, CPU, the flood's answers."""
    export_pids = [p for p in children(svc.pid) if "tools.modbus_export" in cmdline(p)]
    cpu0 = {p: cpu_seconds(p) for p in [svc.pid, *export_pids]}
    flood = Flood(port, flood_rate, connections).start() if flood_rate else None
    try:
        t0 = time.monotonic()
        w = _window(client, seconds, svc)
        wall = time.monotonic() - t0
    finally:
        if flood is not None:
            flood.stop()
    cpu = {p: round(100 * (cpu_seconds(p) - c) / wall, 1) for p, c in cpu0.items() if os.path.exists(f"/proc/{p}")}
    out = {**w, "dropped_per_10s": round(10.0 * w["dropped_frames"] / w["window_s"], 1),
           "service_cpu_percent": cpu.get(svc.pid),
           "export_cpu_percent": sum(v for p, v in cpu.items() if p != svc.pid) if export_pids else None,
           "export_in": "its own process" if export_pids else "the service process"}
    if flood is not None:
        out.update(flood_rate=flood_rate, connections=connections,
                   answered_per_s=round(flood.answered / wall, 1), refused=flood.refused,
                   failed=flood.failed)
    return out


def _stop_service(svc: subprocess.Popen, name: str) -> None:
    """Stop the service (SIGTERM, SIGKILL after 15 s), close its pipes, remove its buffer and ring."""
    from bench.bench_modbus import stop_all
    from bit3.buffer import Bit3Buffer
    from bit3.ring import FrameRing

    stop_all((svc,), 15.0)
    Bit3Buffer.unlink(name)
    FrameRing.unlink(name)


def figures(seconds: float = 10.0, rate: float = DEFAULT_RATE, connections: int = DEFAULT_CONNECTIONS,
            rounds: int = 1, realtime: bool = False) -> dict:
    """``rounds`` pairs of a quiet run and a flooded run (alternated, so a change in the
    host's load falls on both), and the extra dropped frames per 10 s over all of them."""
    quiet, flooded = [], []
    for _ in range(rounds):
        q = one_run(seconds, None, realtime=realtime)
        if "error" in q:
            return {"error": f"quiet run: {q['error']}"}
        quiet.append(q)
        f = one_run(seconds, rate, connections, realtime=realtime)
        if "error" in f:
            return {"error": f"flooded run: {f['error']}", "quiet": quiet}
        flooded.append(f)

    def per_10s(runs: list[dict]) -> float:
        return round(10.0 * sum(r["dropped_frames"] for r in runs) / sum(r["window_s"] for r in runs), 1)

    return {"seconds": seconds, "rounds": rounds, "realtime": realtime, "quiet": quiet, "flooded": flooded,
            "quiet_dropped_per_10s": per_10s(quiet), "flooded_dropped_per_10s": per_10s(flooded),
            "extra_dropped_per_10s": round(per_10s(flooded) - per_10s(quiet), 1),
            "load_average": round(os.getloadavg()[0], 2)}


def judge(rep: dict) -> list[str]:
    """Issue 20's flood criteria on a :func:`figures` report: one line per criterion that
    failed, naming it and its figure; empty when the flood passed."""
    if "error" in rep:
        return [f"flood: FAILED the runs ran: {rep['error']}"]
    bad = []
    extra = rep["extra_dropped_per_10s"]
    if extra > MAX_EXTRA_DROPPED_PER_10S:
        bad.append(f"at most {MAX_EXTRA_DROPPED_PER_10S:g} extra dropped frames per 10 s under the flood: "
                   f"{extra:+g} (quiet {rep['quiet_dropped_per_10s']:g}, flooded "
                   f"{rep['flooded_dropped_per_10s']:g} per 10 s, {rep['rounds']} round(s))")
    mute = []
    for k, r in enumerate(rep["flooded"]):
        share = r["answered_per_s"] / r["flood_rate"]
        if share < MIN_ANSWERED_SHARE or r["refused"] or r["failed"]:
            mute.append(f"run {k + 1}: {r['answered_per_s']:g} of {r['flood_rate']:g} requests/s answered, "
                        f"{r['refused']} refused, {r['failed']} timed out or cut")
    if mute:
        bad.append(f"the export answering (>= {MIN_ANSWERED_SHARE:.0%} of the requests asked for, none refused "
                   f"or lost): " + "; ".join(mute))
    return [f"flood: FAILED {b}" for b in bad]


def passed_line(rep: dict) -> str:
    """The one line of a flood :func:`judge` passed: the figures it judged."""
    answered = min(r["answered_per_s"] for r in rep["flooded"])
    return (f"flood: passed ({rep['rounds']} round(s) of {rep['seconds']:g} s"
            f"{', --realtime' if rep['realtime'] else ''}: {rep['extra_dropped_per_10s']:+g} dropped frames per "
            f"10 s under the flood (quiet {rep['quiet_dropped_per_10s']:g}, flooded "
            f"{rep['flooded_dropped_per_10s']:g}; at most {MAX_EXTRA_DROPPED_PER_10S:g}), the export answered "
            f">= {answered:g} requests/s)")


def _line(what: str, r: dict) -> str:
    s = (f"  {what}: {r['frames']} frames in {r['window_s']:g} s, {r['dropped_frames']} dropped "
         f"({r['dropped_per_10s']:g} per 10 s), {r['overruns']} overruns; CPU service "
         f"{r['service_cpu_percent']} %, export {r['export_cpu_percent']} % ({r['export_in']})")
    if "flood_rate" in r:
        s += (f"\n    flood {r['flood_rate']:g} req/s over {r['connections']} connections: "
              f"{r['answered_per_s']:g} answered/s, {r['refused']} refused, {r['failed']} failed")
    return s


def run(seconds: float = DEFAULT_SECONDS, rate: float = DEFAULT_RATE, rounds: int = 1, realtime: bool = False) -> dict:
    f = figures(seconds, rate, rounds=rounds, realtime=realtime)
    if "error" in f:
        print(f"Modbus flood: {f['error']}")
        return f
    print(f"pfma serve --rack fake --modbus 127.0.0.1:PORT{' --realtime' if realtime else ''}, "
          f"{seconds:g} s per run, {rounds} round(s) "
          f"(load average {f['load_average']:.2f} at the end):")
    for k, (q, fl) in enumerate(zip(f["quiet"], f["flooded"])):
        print(_line(f"quiet   {k + 1}", q))
        print(_line(f"flooded {k + 1}", fl))
    print(f"  dropped frames per 10 s: quiet {f['quiet_dropped_per_10s']:g}, flooded "
          f"{f['flooded_dropped_per_10s']:g}: extra {f['extra_dropped_per_10s']:g} (goal: <= 5)")
    return f
