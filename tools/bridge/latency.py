"""Area latency across the bridge on loopback beside shared memory, in the same run
(issue 19's performance figures, quoted in docs/bridge.md). A measurement run by hand,
not a test:

    .venv/bin/python -m tools.bridge.latency [SECONDS]

It starts a real-time ``pfma serve`` (320 Hz) and ``pfma bridge`` on tcp/127.0.0.1 (a
free port); a shared-memory reader process (polling every 0.2 ms) and a Zenoh subscriber
process each note, for every inputs body, ``time.monotonic()`` at arrival minus the body's
``t_s`` (the frame's start on the service's monotonic clock). Also: the share of frames
the bridge delivered, and the bridge process's CPU.
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
from tools.bridge.remote import RemoteBuffer
r = RemoteBuffer.connect(sys.argv[1], sys.argv[2], timeout_s=20)
got = []
sub = r.session.declare_subscriber("pfma/%s/inputs" % sys.argv[2],
                                   lambda smp: got.append((time.monotonic(), smp.payload.to_bytes())))
time.sleep(float(sys.argv[3]))
sub.undeclare()
r.close()
dt = r.layout.area("inputs").body_dtype
rec = [np.frombuffer(b, dtype=dt, count=1)[0] for _, b in list(got)]
print(json.dumps({"lat": [t - float(x["t_s"]) for (t, _), x in zip(got, rec)],
                  "frames": [int(x["frame"]) for x in rec]}))
'''


def _cpu_s(pid: int) -> float:
    f = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def _quantiles(x: list[float]) -> str:
    a = np.array(x) * 1e6
    return (f"p50 {np.percentile(a, 50):.0f} us, p99 {np.percentile(a, 99):.0f} us, "
            f"max {a.max():.0f} us (n={len(a)})")


def main(secs: float = 10.0) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    name = "pfma-lat-" + uuid.uuid4().hex[:6]
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"

    def start(*argv: str, out=subprocess.PIPE) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, *argv], cwd=ROOT, env=env, stdout=out, text=True)
    serve = start("-m", "tools.cli", "serve", "--buffer", name, "--duration", str(secs + 15),
                  out=subprocess.DEVNULL)
    try:
        time.sleep(3)  # the service up (a measurement: crude waits are fine here)
        bridge = start("-m", "tools.cli", "bridge", "--buffer", name, "--listen", endpoint)
        time.sleep(1.5)
        zen = start("-c", ZENOH_READER, endpoint, name, str(secs))
        time.sleep(1.5)
        c0, t0 = _cpu_s(bridge.pid), time.monotonic()
        shm = start("-c", SHM_READER, name, str(secs - 3))
        a = json.loads(shm.communicate()[0])
        c1, t1 = _cpu_s(bridge.pid), time.monotonic()
        b = json.loads(zen.communicate()[0])
        bridge.send_signal(signal.SIGINT)
        bridge.communicate(timeout=30)
    finally:
        serve.send_signal(signal.SIGINT)
        serve.communicate(timeout=30)
    seen = set(b["frames"])
    span = max(seen) - min(seen) + 1 if seen else 0
    print("shared memory reader:", _quantiles(a["lat"]))
    print("across the bridge   :", _quantiles(b["lat"]))
    print(f"bridge delivered {len(seen)} of {span} frames in its window "
          f"({100 * len(seen) / max(span, 1):.2f} %)")
    print(f"bridge CPU over {t1 - t0:.1f} s: {100 * (c1 - c0) / (t1 - t0):.1f} % of a core")
    print(f"host: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main(float(sys.argv[1]) if len(sys.argv) > 1 else 10.0)
