"""The recorder in real time against ``pfma serve`` (both subprocesses), measured from outside.

For 320 Hz and 1 kHz minor frames: frames recorded vs the service's own frame count,
the recorder's drop counters, recorder CPU % (from /proc), file size and MB/min, and
the time ``pfma record recover`` takes on the file cut in the middle. The 10-minute soak
of issue 8 is ``pfma bench record --seconds 600``.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

from pfma.process import cpu_seconds
from tools.recording.reader import read_metadata
from tools.recording.recover import recover


def one(rate: float, seconds: float, workdir: Path) -> dict:
    name = "pfma-benchrec-" + uuid.uuid4().hex[:6]
    path = workdir / f"rec-{int(rate)}.mcap"
    py = sys.executable
    # the recorder starts first and waits for the service (start-up robustness on the way)
    rec = subprocess.Popen([py, "-m", "tools.cli", "record", str(path), "--buffer", name, "--quiet"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    srv = subprocess.Popen([py, "-m", "tools.cli", "serve", "--buffer", name, "--duration", str(seconds),
                            "--frame-rate", str(rate)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True)
    cpu0, t0 = cpu_seconds(rec.pid), time.monotonic()
    srv_out, _ = srv.communicate(timeout=seconds + 60)
    cpu = cpu_seconds(rec.pid) - cpu0
    wall = time.monotonic() - t0
    rec.send_signal(signal.SIGINT)  # Ctrl-C: the summary is written
    rec_out, rec_err = rec.communicate(timeout=60)
    meta = read_metadata(path).get("pfma.recorder.summary", {})
    size = path.stat().st_size
    # recover time on the same file cut in half (as if the recorder had been killed)
    cut = workdir / f"cut-{int(rate)}.mcap"
    cut.write_bytes(path.read_bytes()[: size // 2])
    t = time.perf_counter()
    rep = recover(cut, workdir / f"fixed-{int(rate)}.mcap")
    t_recover = time.perf_counter() - t
    served = next((ln for ln in srv_out.splitlines() if "stopped after" in ln), "")
    return {"rate": rate, "seconds": seconds, "meta": meta, "size_b": size, "cpu_percent": 100 * cpu / wall,
            "mb_per_min": size / 1e6 / (seconds / 60), "recover_s": t_recover, "recover_msgs": rep.messages,
            "recover_frames": rep.frames, "served": served, "rec_out": rec_out.strip(),
            "rec_err": rec_err.strip()[-500:]}


def run(seconds: float = 10.0) -> dict:
    out = {}
    print(f"recorder vs pfma serve (simulated rack), real time, {seconds:g} s per rate")
    with tempfile.TemporaryDirectory(prefix="pfma-bench-rec-") as d:
        for rate in (320.0, 1000.0):
            r = one(rate, seconds, Path(d))
            out[rate] = r
            m = r["meta"]
            if not m:
                print(f"{rate:g} Hz: no summary in the recording; recorder said: {r['rec_out']} {r['rec_err']}")
                continue
            tc = json.loads(m.get("topic_counts", "{}"))
            print(f"{rate:6g} Hz: frames recorded {m['frames_recorded']} (frames {m['first_frame']}..{m['last_frame']}); "
                  f"service ran {m['window_service_frames']} / recorded {m['window_recorded']} in the stats window; "
                  f"recorder missed {m['recorder_missed']}, service skipped {m['service_skipped']} "
                  f"(service dropped {m['window_service_dropped']}); lossless {m['lossless']}")
            print(f"         recorder CPU {r['cpu_percent']:.1f} % of one core, file {r['size_b'] / 1e6:.2f} MB, "
                  f"{r['mb_per_min']:.1f} MB/min, {sum(tc.values())} messages; recover of the half-cut file "
                  f"{r['recover_s']:.2f} s ({r['recover_frames']} frames)")
            print(f"         {r['served']}")
    return out
