"""``pfma stats``: measured rates per device, loop latency percentiles, overruns and
error counters of a running service, read from its Bit3 buffer; and the controller's
frame timing and missed frames (Bit3 ``controller_stats``) when a controller is attached.

States, fault codes and status words are shown by name (pfma/show.py); ``--json`` keeps each
number beside its name (``service_state`` / ``service_state_code``, ``fault_code`` /
``fault_name``, a board's ``status`` / ``status_name``)."""

from __future__ import annotations

import json
import sys

from bit3.layout import (
    CMD_STATUS_NAMES, DEVICE_GROUPS, FAULT_CODE_NAMES, FAULT_DAC_UNREACHABLE, ServiceState, status_text,
)
from pfma.show import name_of


def add_parser(sub):
    p = sub.add_parser("stats", help="service statistics from the Bit3 buffer")
    p.add_argument("--buffer", default="pfma", help="Bit3 shared-memory name (default pfma)")
    p.add_argument("--json", action="store_true", help="one JSON object")
    p.add_argument("--wm", default="pfma_wm", metavar="NAME",
                   help="the controller's world model, for its ERROR episode's first cause (default pfma_wm; "
                        "'none': not read)")
    return p


def collect(client) -> dict:
    st = client.read_stats()
    s = client.read_inputs()
    lay = client.layout
    out = {
        "service_state": name_of(s.service_state, ServiceState), "service_state_code": int(s.service_state),
        "frame": st.frame, "frames": st.frames, "dropped_frames": st.dropped_frames,
        "overruns": st.overruns, "stall_events": st.stall_events,
        "frame_rate_hz": st.rate_hz, "period_s": st.period_s,
        "wake_latency_us": {n: getattr(st, f"wake_latency_{n}_us") for n in ("p50", "p99", "p999", "max")},
        "work_us": {n: getattr(st, f"work_{n}_us") for n in ("p50", "p99", "max")},
        "cpu_percent": st.cpu_percent, "gc_gen2": st.gc_gen2,
        "devices": {g: {"rate_hz": float(st.device_rate_hz[lay.slot("device", g)]),
                        "samples": int(st.device_samples[lay.slot("device", g)]),
                        "errors": int(st.device_errors[lay.slot("device", g)])} for g in DEVICE_GROUPS},
        "boards": {c.name: {"status": int(s.board_status[c.slot]),
                            "status_name": status_text("board", int(s.board_status[c.slot])),
                            "errors": int(s.board_errors[c.slot])}
                   for c in lay.channels if c.kind == "board"},
        "links": {c.name: {"status": int(s.link_status[c.slot]),
                           "status_name": status_text("link", int(s.link_status[c.slot])),
                           "records": int(s.link_records[c.slot]), "bad": int(s.link_bad[c.slot]),
                           "resyncs": int(s.link_resyncs[c.slot]), "rate_hz": float(s.link_rate_hz[c.slot])}
                  for c in lay.channels if c.kind == "link"},
    }
    status = int(s.command_status)
    writer = client.owners().get("commands")
    out["commands"] = {  # what the service made of the command area (docs/safety.md)
        "writer": writer.name if writer is not None and writer.alive else None,
        "fault_code": int(s.fault_code), "fault_name": name_of(s.fault_code, FAULT_CODE_NAMES),
        "watchdog_tripped": bool(s.watchdog_tripped),
        # False while the DAC board does not answer: its outputs may hold their last values
        # (docs/safety.md "Honest outputs")
        "outputs_known_safe": int(s.fault_code) != FAULT_DAC_UNREACHABLE,
        "inputs_frame": int(s.command_inputs_frame), "input_age_frames": int(s.command_input_age_frames),
        "status": [n for b, n in CMD_STATUS_NAMES.items() if status & b], "status_bits": status,
        "stale_frames": int(s.stale_commands), "absent_frames": int(s.absent_commands),
        "refused": int(s.refused_commands), "foreign_writes": int(s.foreign_writes),
        "last_host_stall_s": float(s.host_stall_s), "last_host_stall_t_s": float(s.host_stall_t_s),
    }
    # the first trip or refusal since the last arm (the root of the episode, not the notices after it)
    out["first_trip"] = ({"code": int(s.first_trip_code), "t_s": float(s.first_trip_t_s),
                          "text": s.text("first_trip_text")} if int(s.first_trip_code) else None)
    out["controller"] = collect_controller(client)
    return out


#: controller_stats fields shown by ``pfma stats`` (all of them go into ``--json``)
CONTROLLER_FIELDS = ("frame", "frames", "missed_frames", "missed_events", "missed_run", "longest_missed_run",
                     "max_missed_run", "missed_task_slots", "overruns", "period_s", "rate_hz",
                     "wake_latency_p50_us", "wake_latency_p99_us", "wake_latency_max_us",
                     "work_p50_us", "work_p99_us", "work_max_us", "cpu_percent", "gc_gen2")


def collect_controller(client) -> dict | None:
    """The controller's own statistics (Bit3 ``controller_stats``), or None when no live
    controller holds the area or it has not published yet."""
    try:
        owner = client.owners().get("controller_stats")
        if owner is None or not owner.alive:
            return None
        cs = client.read("controller_stats")
    except Exception:  # noqa: BLE001 - an older buffer without the area
        return None
    if not cs.frames:
        return None
    out = {"owner": owner.name, "pid": owner.pid}
    out.update({f: cs[f] for f in CONTROLLER_FIELDS})
    return out


def format_controller(c: dict | None) -> str:
    if c is None:
        return "controller: no controller attached"
    return "\n".join([
        f"controller {c['owner']} (pid {c['pid']}): frame {c['frame']}  {c['rate_hz']:.1f} Hz  "
        f"frames {c['frames']}  overruns {c['overruns']}  cpu {c['cpu_percent']:.1f} %  gen2 GCs {c['gc_gen2']}",
        f"  missed frames {c['missed_frames']} in {c['missed_events']} events  last run {c['missed_run']}  "
        f"longest run {c['longest_missed_run']} (fault above {c['max_missed_run']})  "
        f"task slots caught up {c['missed_task_slots']}",
        f"  wake latency us: p50 {c['wake_latency_p50_us']:.0f}  p99 {c['wake_latency_p99_us']:.0f}  "
        f"max {c['wake_latency_max_us']:.0f}",
        f"  frame work us:   p50 {c['work_p50_us']:.0f}  p99 {c['work_p99_us']:.0f}  max {c['work_max_us']:.0f}",
    ])


def controller_first_cause(wm_name: str) -> str | None:
    """The controller's current ERROR episode's first cause from its world model ("" none;
    None: no world model of that name, or it is not read)."""
    if wm_name in ("", "none"):
        return None
    from controller.runtime import first_cause_text
    from controller.worldmodel import WorldModel
    try:
        wm = WorldModel.attach(wm_name)
    except Exception:  # noqa: BLE001 - no controller's world model: nothing to show
        return None
    try:
        if not wm.info().owner_alive:  # a stopped controller's episode is not the running system's
            return None
        return first_cause_text(wm)
    finally:
        wm.close()


def format_first_causes(d: dict) -> list[str]:
    ft = d.get("first_trip")
    out = [f"service first trip since the last arm: {ft['text']} (code {ft['code']}, t={ft['t_s']:.1f} s)"
           if ft else "service first trip since the last arm: none"]
    fc = d.get("controller_first_cause")
    if fc is not None:
        out.append(f"controller first cause of the ERROR: {fc}" if fc else
                   "controller first cause of the ERROR: none (no ERROR episode)")
    return out


def run(args) -> int:
    from bit3.buffer import Bit3Error
    from pfma.errors import PfmaError
    from tools.attach import attach_reader
    try:  # a dead service's last statistics are not a live service's: refused, saying why
        c = attach_reader(args.buffer)  # shared memory, or zenoh://HOST:PORT/NAME via a bridge
    except PfmaError as err:
        print(f"pfma stats: {err}", file=sys.stderr)
        return 1
    except (Bit3Error, FileNotFoundError) as err:
        print(f"pfma stats: no service buffer {args.buffer!r}: {err}", file=sys.stderr)
        return 1
    try:
        d = collect(c)
    finally:
        c.close()
    d["controller_first_cause"] = controller_first_cause(getattr(args, "wm", "none"))
    if args.json:
        print(json.dumps(d, indent=1))
        return 0
    print(f"state {d['service_state']}  frame {d['frame']}  {d['frame_rate_hz']:.1f} Hz  "
          f"dropped {d['dropped_frames']}  overruns {d['overruns']}  stalls {d['stall_events']}  "
          f"cpu {d['cpu_percent']:.1f} %  gen2 GCs {d['gc_gen2']}")
    w, k = d["wake_latency_us"], d["work_us"]
    print(f"wake latency us: p50 {w['p50']:.0f}  p99 {w['p99']:.0f}  p99.9 {w['p999']:.0f}  max {w['max']:.0f}")
    print(f"frame work us:   p50 {k['p50']:.0f}  p99 {k['p99']:.0f}  max {k['max']:.0f}")
    from tools.cli.output import print_table, table
    t = table("device", "rate Hz>", "samples>", "errors>", title="devices")
    for g, v in d["devices"].items():
        if v["samples"]:
            t.add_row(g, f"{v['rate_hz']:.1f}", str(v["samples"]), str(v["errors"]))
    print_table(t)
    t = table("board", "status", "errors>", title="boards")
    for b, v in d["boards"].items():
        t.add_row(b, v["status_name"], str(v["errors"]))
    print_table(t)
    t = table("link", "status", "records>", "bad>", "resyncs>", "rate /s>", title="links")
    for n, v in d["links"].items():
        t.add_row(n, v["status_name"], str(v["records"]), str(v["bad"]), str(v["resyncs"]), f"{v['rate_hz']:.1f}")
    print_table(t)
    cm = d["commands"]
    stall = (f"  last host stall {cm['last_host_stall_s'] * 1e3:.0f} ms at t={cm['last_host_stall_t_s']:.1f} s"
             if cm["last_host_stall_s"] > 0 else "")
    age = f"age {cm['input_age_frames']} frames" if cm["writer"] else "no command writer attached"
    fault = f"  service fault {cm['fault_name']}" if cm["fault_code"] else ""
    print(f"commands: {age}  status {'+'.join(cm['status']) or 'ok'}  "
          f"stale {cm['stale_frames']} frames  absent {cm['absent_frames']}  refused {cm['refused']}  "
          f"foreign writes {cm['foreign_writes']}{'  WATCHDOG TRIPPED' if cm['watchdog_tripped'] else ''}{stall}"
          f"{fault}")
    if not cm["outputs_known_safe"]:
        print("OUTPUTS NOT KNOWN SAFE: the DAC board does not answer; its outputs may hold their last values: "
              "press the hardware E-stop if the arm moves (docs/safety.md \"Honest outputs\")")
    print("\n".join(format_first_causes(d)))
    print(format_controller(d["controller"]))
    return 0
