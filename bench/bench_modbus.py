"""The service over a Modbus TCP gateway on loopback, measured from outside.

``pfma gateway`` (the simulated rack behind a pymodbus server on 127.0.0.1, the physics
in real time) and ``pfma serve --bus modbus://127.0.0.1:PORT --schedule slow`` run as two
processes of this venv's python. The service measures what the bus costs at start and
runs the 320 Hz schedule if the gateway keeps it, else the best slower one, which it
names on its first line (reported as ``schedule``). Reported from its stats area after
``seconds``: the frame rate and the device rates reached (resolvers, ADC, DAC; no F/T:
serial lines do not cross a register gateway), the frame work (p50/p99: on this bus it
is mostly waiting for the gateway's answers), overruns, dropped frames, and the CPU of
both processes. No controller runs: the service stays SAFE and writes 0 V.

Run: ``pfma bench modbus`` or ``pfma bench --json``.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
import time
import uuid

from pfma.process import cpu_seconds, free_port

#: bound on the gateway's and the service's start
START_TIMEOUT_S = 30.0


def available() -> str | None:
    """Why this benchmark cannot run here, or None."""
    for mod in ("pymodbus", "fakes.modbus_gateway", "tools.cli.gateway"):
        try:
            found = importlib.util.find_spec(mod) is not None
        except ImportError:
            found = False
        if not found:
            return f"the Modbus gateway is not available here (no module {mod})"
    return None


#: longest wait for the service's next statistics publication after a short measurement
STATS_WAIT_S = 3.0


def figures(seconds: float = 5.0) -> dict:
    """The service over a loopback gateway for ``seconds`` (after it publishes frames)."""
    from bit3.buffer import Bit3Buffer
    from tools.attach import wait_for_frames

    why = available()
    if why:
        return {"skipped": why}
    py = sys.executable
    port = free_port()
    name = "pfma-bench-mb-" + uuid.uuid4().hex[:6]
    url = f"modbus://127.0.0.1:{port}"
    gw = subprocess.Popen([py, "-m", "tools.cli", "gateway", "--listen", f"127.0.0.1:{port}",
                           "--duration", str(seconds + START_TIMEOUT_S + 10)],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    svc = None
    client = None
    err = tempfile.TemporaryFile(mode="w+")  # the service's stderr: its last lines name why it stopped
    try:
        first = gw.stdout.readline() if gw.stdout else ""
        if not first.startswith("pfma gateway:") or "Ctrl-C stops" not in first:
            return {"error": f"the gateway did not start: {first.strip() or gw.stderr.read().strip()}"}
        svc = subprocess.Popen([py, "-m", "tools.cli", "serve", "--bus", url, "--buffer", name,
                                "--duration", str(seconds + START_TIMEOUT_S), "--schedule", "slow"],
                               stdout=subprocess.PIPE, stderr=err, text=True)
        client = wait_for_frames(name, 10, timeout_s=START_TIMEOUT_S, alive=lambda: svc.poll() is None)
        if client is None and svc.poll() is not None:
            err.seek(0)
            said = " | ".join(line.strip() for line in err.read().splitlines()[-3:] if line.strip())
            return {"error": f"pfma serve over {url} exited {svc.returncode} before publishing frames"
                             + (f": {said}" if said else "")}
        if client is None:
            return {"error": f"pfma serve over {url} published no frames within {START_TIMEOUT_S:g} s"}
        return _measure(client, svc, gw, name, url, seconds)
    finally:
        if client is not None:
            client.close()
        stop_all((svc, gw))
        Bit3Buffer.unlink(name)
        err.close()


def _measure(client, svc: subprocess.Popen, gw: subprocess.Popen, name: str, url: str, seconds: float) -> dict:
    """:func:`figures` of a service publishing over the gateway at ``url`` (``client``: a
    reader of its buffer ``name``), measured for ``seconds``."""
    from bench.independent_reader import IndependentReader, measure

    time.sleep(0.5)  # settle
    st0 = client.read_stats()  # the client's preallocated copy: the counters are taken now
    n0 = {k: int(st0[k]) for k in ("frames", "overruns", "dropped_frames")}
    cpu_s0, cpu_g0, t0 = cpu_seconds(svc.pid), cpu_seconds(gw.pid), time.monotonic()
    # meanwhile, the refresh rates as a reader that shares no code with the project sees
    # them (bench/independent_reader.py: stdlib only, layout from the published JSON)
    reader = IndependentReader(client.layout.as_json(), f"/dev/shm/{name}")
    try:
        seen = measure(reader, lambda: time.sleep(0.0002), seconds)
    finally:
        reader.close()
    wall = time.monotonic() - t0
    cpu_s, cpu_g = cpu_seconds(svc.pid) - cpu_s0, cpu_seconds(gw.pid) - cpu_g0
    st = _stats_after(client, n0["frames"], svc)
    lay = client.layout
    rates = {g: float(st.device_rate_hz[lay.slot("device", g)]) for g in ("rtd", "adc", "dac")}
    period = float(st.period_s)
    return {"seconds": round(wall, 2), "url": url,
            "frame_rate_hz": round(1.0 / period, 2) if period > 0 else None,
            "rates_hz": {k: round(v, 2) for k, v in rates.items()},
            "independent_reader_hz": {g: round(seen[f"t_{g}_s"], 2) for g in ("rtd", "adc", "dac")},
            "work_p50_us": float(st.work_p50_us), "work_p99_us": float(st.work_p99_us),
            "frames": int(st.frames) - n0["frames"], "overruns": int(st.overruns) - n0["overruns"],
            "dropped": int(st.dropped_frames) - n0["dropped_frames"],
            "service_cpu_percent": round(100 * cpu_s / wall, 2),
            "gateway_cpu_percent": round(100 * cpu_g / wall, 2),
            "schedule": _schedule_line(svc)}


def _stats_after(client, frames0: int, svc: subprocess.Popen):
    """The service's statistics published after the measurement started (``frames0``: its
    frame count then). It publishes them about once a second: a short run waits (at most
    STATS_WAIT_S) for a publication made after the measurement started."""
    t_stats = time.monotonic() + STATS_WAIT_S
    while int(client.read_stats()["frames"]) == frames0 and time.monotonic() < t_stats \
            and svc.poll() is None:
        time.sleep(0.05)
    return client.read_stats()


def stop_all(procs, timeout_s: float = 10.0) -> None:
    """Terminate the processes still running (all at once), then wait for each
    (``pfma.process.stop_helper``: SIGKILL after ``timeout_s``) and close its pipes."""
    from pfma.process import stop_helper
    for p in procs:
        if p is not None and p.poll() is None:
            p.terminate()
    for p in procs:
        if p is not None:
            stop_helper(p, timeout_s)
            for f in (p.stdout, p.stderr):
                if f is not None:
                    f.close()


def _schedule_line(svc: subprocess.Popen) -> str:
    """What the service said it runs: its 'running ...' line (a slower schedule), or the
    320 Hz default when it kept it. Read once the service has printed its start lines."""
    if svc.stdout is None:
        return "?"
    first = svc.stdout.readline().strip()
    if first.startswith("pfma serve: running "):
        return first.removeprefix("pfma serve: ")
    return "the schedule asked for (320 Hz frames; the bus keeps it)"


def run(seconds: float = 5.0) -> dict:
    f = figures(seconds)
    if "skipped" in f or "error" in f:
        print(f"service over a loopback Modbus gateway: {f.get('skipped') or f.get('error')}")
        return f
    r = f["rates_hz"]
    print(f"service over a loopback Modbus gateway ({f['url']}), {f['seconds']:g} s: {f['schedule']}")
    print(f"  frames {f['frame_rate_hz']} Hz; rates reached rtd {r['rtd']:.1f} / adc {r['adc']:.1f} / dac "
          f"{r['dac']:.1f} Hz; frame work p50 {f['work_p50_us']:.0f} us, p99 {f['work_p99_us']:.0f} us "
          f"(mostly waiting for the gateway); {f['overruns']} overruns, {f['dropped']} dropped in "
          f"{f['frames']} frames; CPU service {f['service_cpu_percent']:.1f} %, gateway "
          f"{f['gateway_cpu_percent']:.1f} %")
    return f
