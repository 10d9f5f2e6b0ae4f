"""Area latency across the bridge on loopback beside shared memory, in the same run
(issue 19's performance figures, quoted in docs/bridge.md and docs/deployment.md).
``pfma bench bridge`` (``bench/bench_bridge.py``, ``bridge.*`` in ``pfma bench --json``)
runs :func:`measure`; by hand:

    .venv/bin/python -m tools.bridge.latency [SECONDS]

It starts a real-time ``pfma serve`` (320 Hz) and ``pfma bridge`` on tcp/127.0.0.1 (a
free port); a shared-memory reader process (polling every 0.2 ms) and a Zenoh subscriber
process each note, for every inputs body, ``time.monotonic()`` at arrival minus the body's
``t_s`` (the frame's start on the service's monotonic clock). Also: the share of frames
the subscriber received in its window, the publishes the bridge itself missed (its poll
came after the next frame) and the rest lost on the link (from the sequence numbers the
bridge attaches), and the bridge process's CPU.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]

SHM_READER = r'''
import sys, time, json
from bit3.client import Client
c = Client.attach(sys.argv[1])
end = time.monotonic() + float(sys.argv[2])
lat, frames = [], []
while time.monotonic() < end:
    if c.changed("inputs"):
        s = c.read_inputs()
        lat.append(time.monotonic() - s.t_s)
        frames.append(s.frame)
    time.sleep(0.0002)
c.close()
print(json.dumps({"lat": lat, "frames": frames}))
'''

ZENOH_READER = r'''
import sys, time, json
import numpy as np
from tools.bridge.bridge import seq_of
from tools.bridge.remote import RemoteBuffer
r = RemoteBuffer.connect(sys.argv[1], sys.argv[2], timeout_s=20)
got = []
sub = r.session.declare_subscriber("pfma/%s/inputs" % sys.argv[2],
                                   lambda smp: got.append((time.monotonic(), smp.payload.to_bytes(), seq_of(smp))))
print("ready", flush=True)
time.sleep(float(sys.argv[3]))
sub.undeclare()
r.close()
dt = r.layout.area("inputs").body_dtype
rec = [np.frombuffer(b, dtype=dt, count=1)[0] for _, b, _ in list(got)]
print(json.dumps({"lat": [t - float(x["t_s"]) for (t, _, _), x in zip(got, rec)],
                  "frames": [int(x["frame"]) for x in rec], "seqs": [s for _, _, s in got]}))
'''


def _cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


def _us(x: list[float]) -> dict:
    a = np.array(x) * 1e6
    if not len(a):
        return {"p50_us": None, "p99_us": None, "max_us": None, "n": 0}
    return {"p50_us": float(np.percentile(a, 50)), "p99_us": float(np.percentile(a, 99)),
            "max_us": float(a.max()), "n": int(len(a))}


def _wait(cond, what: str, limit_s: float, procs=()) -> None:
    end = time.monotonic() + limit_s
    while not cond():
        for p in procs:
            if p.poll() is not None:
                raise RuntimeError(f"{what}: {' '.join(p.args[2:5])} exited with {p.returncode}")
        if time.monotonic() > end:
            raise RuntimeError(f"{what}: not within {limit_s:g} s")
        time.sleep(0.05)


def measure(seconds: float = 10.0) -> dict:
    """The figures of one run: ``shm`` and ``bridge`` latency quantiles (us); of the
    service's inputs publishes in the subscriber's window, the share received
    (``delivered_percent``, from the sequence numbers; ``frames_percent`` also counts frame
    numbers the service itself skipped as missing); the publishes the bridge missed in its
    whole run; the bridge's CPU (% of a core) over the window."""
    name = "pfma-lat-" + uuid.uuid4().hex[:6]
    a, b, bridge_said, cpu_percent = _run(name, _free_endpoint(), seconds)
    return _figures(seconds, a, b, bridge_said, cpu_percent)


def _free_endpoint() -> str:
    """A free TCP port on loopback as a Zenoh endpoint."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _start(*argv: str, out=subprocess.PIPE, err=subprocess.DEVNULL) -> subprocess.Popen:
    """A Python process in the project's root with the project on its path."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen([sys.executable, *argv], cwd=ROOT, env=env, stdout=out, stderr=err, text=True)


def _run(name: str, endpoint: str, seconds: float) -> tuple[dict, dict, list[str], float]:
    """The service, the bridge and both readers on buffer ``name``: the shared-memory
    reader's and the subscriber's results, the bridge's last words and its CPU (% of a
    core) over the shared-memory reader's window. Every process is stopped at the end."""
    from bit3.buffer import Bit3Buffer
    serve = _start("-m", "tools.cli", "serve", "--buffer", name, "--duration", str(seconds + 60),
                   out=subprocess.DEVNULL)
    procs = [serve]
    try:
        _wait(lambda: Bit3Buffer.owner_alive(name)[0], "the service up", 30, procs)
        bridge = _start_bridge(name, endpoint, procs)
        zen = _start("-c", ZENOH_READER, endpoint, name, str(seconds + 1.0), err=subprocess.PIPE)
        procs.append(zen)
        assert zen.stdout is not None
        zen.stdout.readline()  # "ready": subscribed
        time.sleep(0.5)  # the subscription reaches the bridge (a measurement: a crude wait is fine)
        c0, t0 = _cpu_s(bridge.pid), time.monotonic()
        shm = _start("-c", SHM_READER, name, str(seconds))
        a = json.loads(shm.communicate(timeout=seconds + 60)[0])
        c1, t1 = _cpu_s(bridge.pid), time.monotonic()
        b = _subscriber_result(zen, seconds)
        procs.remove(zen)
        bridge.send_signal(signal.SIGINT)
        bridge_said = bridge.communicate(timeout=30)[1].strip().splitlines()
        procs.remove(bridge)
    finally:
        _stop_all(procs, name)
    return a, b, bridge_said, 100.0 * (c1 - c0) / (t1 - t0)


def _start_bridge(name: str, endpoint: str, procs: list[subprocess.Popen]) -> subprocess.Popen:
    """``pfma bridge`` on ``endpoint``, added to ``procs``, once it says it publishes."""
    bridge = _start("-m", "tools.cli", "bridge", "--buffer", name, "--listen", endpoint, err=subprocess.PIPE)
    procs.append(bridge)
    assert bridge.stderr is not None
    said = bridge.stderr.readline()  # "pfma bridge: buffer ... on ...": it publishes
    if not said.startswith("pfma bridge: buffer"):
        raise RuntimeError(f"pfma bridge did not start: {said.strip()}")
    return bridge


def _subscriber_result(zen: subprocess.Popen, seconds: float) -> dict:
    """The Zenoh subscriber's results (latencies, frame and sequence numbers)."""
    out, err = zen.communicate(timeout=seconds + 60)
    if zen.returncode:
        raise RuntimeError(f"the Zenoh subscriber failed: {err.strip().splitlines()[-1:]}")
    return json.loads(out)


def _stop_all(procs: list[subprocess.Popen], name: str) -> None:
    """Stop what still runs (SIGINT, then kill after 30 s) and unlink the measurement's buffer."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for p in procs:
        try:
            p.communicate(timeout=30)
        except subprocess.TimeoutExpired:  # never leave a service or bridge running
            p.kill()
            p.communicate()
    from bit3.buffer import Bit3Buffer
    Bit3Buffer.unlink(name)  # the measurement's own buffer (a stopped service leaves it)


def _missed(bridge_said: list[str]) -> int | None:
    """The publishes the bridge says it missed (its ``stopped`` line), None if it did not say."""
    return next((int(w) for line in bridge_said if "missed" in line
                 for w, nxt in zip(line.split(), line.split()[1:]) if nxt == "publishes"), None)


def _figures(seconds: float, a: dict, b: dict, bridge_said: list[str], cpu_percent: float) -> dict:
    """:func:`measure`'s figures from the readers' results and the bridge's last words."""
    frames, seqs = b["frames"], b["seqs"]
    seen = set(frames)
    span = max(seen) - min(seen) + 1 if seen else 0
    gaps = [(s1 - s0) // 2 - 1 for s0, s1 in zip(seqs, seqs[1:]) if s0 is not None and s1 is not None]
    lost = sum(g for g in gaps if g > 0)
    return {"seconds": seconds, "rate_hz": 320.0, "shm": _us(a["lat"]), "bridge": _us(b["lat"]),
            "frames_delivered": len(seen), "frames_window": span,
            "delivered_percent": 100.0 * len(seen) / (len(seen) + lost) if seen else None,
            "frames_percent": 100.0 * len(seen) / span if span else None,
            "publishes_lost": lost, "bridge_missed_total": _missed(bridge_said),
            "bridge_cpu_percent": cpu_percent,
            "host_cores": os.cpu_count(), "host_load_1min": os.getloadavg()[0]}


def report(f: dict) -> str:
    def q(d: dict) -> str:
        return f"p50 {d['p50_us']:.0f} us, p99 {d['p99_us']:.0f} us, max {d['max_us']:.0f} us (n={d['n']})" \
            if d["n"] else "no samples"
    return "\n".join([
        f"inputs area latency, pfma serve at {f['rate_hz']:g} Hz, {f['seconds']:g} s window:",
        f"  shared memory reader: {q(f['shm'])}",
        f"  across the bridge   : {q(f['bridge'])}",
        f"  the subscriber received {f['delivered_percent'] or 0:.2f} % of the service's publishes in its window "
        f"({f['publishes_lost']} lost: sequence gaps); {f['frames_delivered']} of {f['frames_window']} frame "
        f"numbers ({f['frames_percent'] or 0:.2f} %: the rest the service skipped or were lost); "
        f"the bridge missed {f['bridge_missed_total']} publishes in its whole run (polled too late)",
        f"  bridge CPU {f['bridge_cpu_percent']:.1f} % of a core",
        f"  host: {f['host_cores']} cores, load average {f['host_load_1min']:.2f}"])


def main(secs: float = 10.0) -> None:
    print(report(measure(secs)))


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else 10.0)
