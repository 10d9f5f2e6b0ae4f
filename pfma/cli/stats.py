"""``pfma stats``: measured rates per device, loop latency percentiles, overruns and
error counters of a running service, read from its Bit3 buffer."""

from __future__ import annotations

import json
import sys

from ioservice.layout import DEVICE_GROUPS, ServiceState


def add_parser(sub):
    p = sub.add_parser("stats", help="service statistics from the Bit3 buffer")
    p.add_argument("--buffer", default="pfma", help="Bit3 shared-memory name (default pfma)")
    p.add_argument("--json", action="store_true", help="one JSON object")
    return p


def collect(client) -> dict:
    st = client.read_stats()
    s = client.read_inputs()
    lay = client.layout
    out = {
        "service_state": ServiceState(s.service_state).name,
        "frame": st.frame, "frames": st.frames, "dropped_frames": st.dropped_frames,
        "overruns": st.overruns, "stall_events": st.stall_events,
        "frame_rate_hz": st.rate_hz, "period_s": st.period_s,
        "wake_latency_us": {n: getattr(st, f"wake_latency_{n}_us") for n in ("p50", "p99", "p999", "max")},
        "work_us": {n: getattr(st, f"work_{n}_us") for n in ("p50", "p99", "max")},
        "cpu_percent": st.cpu_percent, "gc_gen2": st.gc_gen2,
        "devices": {g: {"rate_hz": float(st.device_rate_hz[lay.slot("device", g)]),
                        "samples": int(st.device_samples[lay.slot("device", g)]),
                        "errors": int(st.device_errors[lay.slot("device", g)])} for g in DEVICE_GROUPS},
        "boards": {c.name: {"status": int(s.board_status[c.slot]), "errors": int(s.board_errors[c.slot])}
                   for c in lay.channels if c.kind == "board"},
        "links": {c.name: {"records": int(s.link_records[c.slot]), "bad": int(s.link_bad[c.slot]),
                           "resyncs": int(s.link_resyncs[c.slot]), "rate_hz": float(s.link_rate_hz[c.slot])}
                  for c in lay.channels if c.kind == "link"},
    }
    return out


def run(args) -> int:
    from ioservice.client import Client
    from ioservice.shm import Bit3Error
    try:
        c = Client.attach(args.buffer)
    except (Bit3Error, FileNotFoundError) as err:
        print(f"pfma stats: no service buffer {args.buffer!r}: {err}", file=sys.stderr)
        return 1
    try:
        d = collect(c)
    finally:
        c.close()
    if args.json:
        print(json.dumps(d, indent=1))
        return 0
    print(f"state {d['service_state']}  frame {d['frame']}  {d['frame_rate_hz']:.1f} Hz  "
          f"dropped {d['dropped_frames']}  overruns {d['overruns']}  stalls {d['stall_events']}  "
          f"cpu {d['cpu_percent']:.1f} %  gen2 GCs {d['gc_gen2']}")
    w, k = d["wake_latency_us"], d["work_us"]
    print(f"wake latency us: p50 {w['p50']:.0f}  p99 {w['p99']:.0f}  p99.9 {w['p999']:.0f}  max {w['max']:.0f}")
    print(f"frame work us:   p50 {k['p50']:.0f}  p99 {k['p99']:.0f}  max {k['max']:.0f}")
    print("devices: " + ", ".join(f"{g} {v['rate_hz']:.1f} Hz ({v['errors']} errors)"
                                  for g, v in d["devices"].items() if v["samples"]))
    print("boards:  " + ", ".join(f"{b} status {v['status']} errors {v['errors']}" for b, v in d["boards"].items()))
    print("links:   " + ", ".join(f"{n} {v['records']} records {v['bad']} bad {v['resyncs']} resyncs "
                                  f"{v['rate_hz']:.1f}/s" for n, v in d["links"].items()))
    return 0
