"""Loop wake-up latency at 320 Hz and 1 kHz, beside the machine's own floor.

The Python figure is the real ``ioservice.loop.FrameLoop`` with an empty frame
body; the floor is a C loop doing the same absolute-deadline sleep
(``bench/periodic_floor.c``, built with the system's ``cc``), or ``cyclictest``
from Debian's rt-tests when installed. Both run in the same invocation, one after
the other, and the p99 ratio is reported (goal: at most 1.5; perf-limits.md s.8).
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from ioservice.loop import FrameLoop, realtime_setup
from pfma.clock import MonotonicClock

SRC = Path(__file__).with_name("periodic_floor.c")


def _pct(a_s: np.ndarray) -> dict:
    p50, p99, p999 = np.percentile(a_s, [50, 99, 99.9])
    return {"p50_us": p50 * 1e6, "p99_us": p99 * 1e6, "p999_us": p999 * 1e6, "max_us": a_s.max() * 1e6}


def python_loop_latency(rate_hz: float, seconds: float) -> dict:
    loop = FrameLoop(MonotonicClock(), 1.0 / rate_hz, lambda info: None)
    n = int(rate_hz * seconds)
    loop.stats = type(loop.stats)(window=n)
    stats = loop.run(frames=n)
    lat = stats.wake_latency_s[: min(stats.n, n)]
    out = _pct(lat)
    out.update(dropped=stats.dropped, frames=stats.n)
    return out


def c_floor_latency(rate_hz: float, seconds: float) -> dict | None:
    cc = shutil.which("cc") or shutil.which("gcc")
    if not cc:
        return None
    with tempfile.TemporaryDirectory() as d:
        exe = Path(d) / "periodic_floor"
        subprocess.run([cc, "-O2", "-o", str(exe), str(SRC)], check=True)
        out = subprocess.run([str(exe), str(rate_hz), str(seconds)], check=True,
                             capture_output=True, text=True).stdout
    lat = np.array([int(x) for x in out.split()], dtype=float) * 1e-9
    return _pct(lat)


def run(seconds: float = 5.0) -> dict:
    """Print and return the figures. ``seconds`` per rate and per loop kind."""
    warnings = realtime_setup(cpu=None, fifo_priority=None)
    results = {}
    print(f"loop wake-up latency, {seconds:g} s per run (absolute deadlines){' ; ' + '; '.join(warnings) if warnings else ''}")
    print(f"{'rate':>6} {'loop':8} {'p50 us':>8} {'p99 us':>8} {'p99.9 us':>9} {'max us':>9}  notes")
    for rate in (320.0, 1000.0):
        py = python_loop_latency(rate, seconds)
        floor = c_floor_latency(rate, seconds)
        results[rate] = {"python": py, "floor": floor}
        print(f"{rate:6g} {'python':8} {py['p50_us']:8.1f} {py['p99_us']:8.1f} {py['p999_us']:9.1f} "
              f"{py['max_us']:9.1f}  dropped {py['dropped']} of {py['frames'] + py['dropped']} frames")
        if floor:
            ratio = py["p99_us"] / floor["p99_us"] if floor["p99_us"] > 0 else float("nan")
            results[rate]["p99_ratio"] = ratio
            print(f"{rate:6g} {'C floor':8} {floor['p50_us']:8.1f} {floor['p99_us']:8.1f} "
                  f"{floor['p999_us']:9.1f} {floor['max_us']:9.1f}  python/C p99 ratio {ratio:.2f} (goal <= 1.5)")
        else:
            print(f"{rate:6g} {'C floor':8} no C compiler found; floor not measured")
    return results
