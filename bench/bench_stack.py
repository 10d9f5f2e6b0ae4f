"""The whole stack in real time: ``pfma serve --rack fake`` + ``pfma controller --power-up``
+ ``pfma record``, each a subprocess with this venv's python, for M minutes (issue 14).

Reported (text or ``--json``): watchdog/safety trips and every WARNING/ERROR message of the
service's and the controller's queues (read every 20 ms, so none of their 50 and 127 entries is
overwritten unread; a gap in the sequence numbers is counted as lost), the controller layers
that went to ERROR and why, the service's frame counters (``stats`` area), the controller's
(``controller_stats`` area, "n/a" without an owner), the F/T link (records, bad, resyncs, the
largest age seen, time flagged stale), the recorder's summary, CPU % per process (utime +
stime from /proc over the run), the host stalls the service named. A process that dies is
reported with its exit code and the tail of its output, never a traceback.

``pfma bench stack --minutes 10 [--json]``; ``--minutes 0.05`` is the short variant a test runs.
``--clock own --profile overview`` runs the controller on its own frame clock at 268 Hz (the
service keeps its 320 Hz; issue 33 item 5); every run reports the age of the command each
armed service frame applied (``command_age``: frames, from the recording, so every frame).
``--hog`` runs one CPU hog beside the stack (a busy Python loop at nice 0, as issue 29's
"done when" asks: an ordinary host's other work), reported with its CPU %; the report's
``held`` says whether no layer went to ERROR.
"""

from __future__ import annotations

import json
import math
import re
import signal
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

from pfma.process import Child, cpu_seconds_or_none
from tools.attach import wait_for_frames

POLL_S = 0.02  #: reading period of the buffer (messages, F/T link, host stalls)
START_TIMEOUT_S = 30.0  #: the service must publish frames within this
STOP_TIMEOUT_S = 15.0  #: each process must exit this long after SIGINT (then SIGKILL)
LINK_STALE = 8  #: link_status bit (ioservice.service.LINK_STALE)


def _r(x, nd: int = 1):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return None
    return round(float(x), nd)


class _Proc(Child):
    """One process of the stack (:class:`pfma.process.Child`: its output in a file, no pipe
    to fill), its CPU over the run and how it ended."""

    def __init__(self, name: str, argv: list[str], workdir: Path) -> None:
        super().__init__(name, argv, workdir)
        self.name = name
        self.cpu0 = cpu_seconds_or_none(self.p.pid)
        self.cpu_percent: float | None = None
        self.died: dict | None = None  # exited before we stopped it
        self.stop_how = "not stopped"
        self.returncode: int | None = None

    def measure_cpu(self) -> None:
        c = cpu_seconds_or_none(self.p.pid)
        wall = time.monotonic() - self.t0
        if c is not None and self.cpu0 is not None and wall > 0:
            self.cpu_percent = 100.0 * (c - self.cpu0) / wall

    def note_death(self, t_run: float) -> None:
        if self.died is None and not self.alive():
            self.died = {"at_s": round(t_run, 2), "returncode": self.p.returncode, "output_tail": self.lines(12)}

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = STOP_TIMEOUT_S) -> str:
        """SIGINT, then wait; SIGKILL if it does not exit in time (:attr:`stop_how` says which)."""
        if not self.alive():
            self.returncode = self.p.returncode
            self.stop_how = "had exited"
            return self.stop_how
        self.measure_cpu()
        how = super().stop(sig, timeout_s)
        self.returncode = self.p.returncode
        self.stop_how = f"SIGKILL (no exit {timeout_s:g} s after SIGINT)" if how.startswith("needed SIGKILL") \
            else "SIGINT"
        return self.stop_how

    def report(self) -> dict:
        return {"pid": self.p.pid, "argv": self.argv[1:], "cpu_percent": _r(self.cpu_percent),
                "stopped": self.stop_how, "returncode": self.returncode, "died": self.died}


class MessageCursor:
    """The service's and the controller's message queues read on: each :meth:`read` gives
    the messages of a queue not read before; a gap in the sequence numbers (a message
    overwritten unread) is counted in :attr:`lost`, per queue."""

    QUEUES = ("service", "controller")

    def __init__(self) -> None:
        self.cursor = dict.fromkeys(self.QUEUES, 0)
        self.lost = dict.fromkeys(self.QUEUES, 0)

    def read(self, client, q: str) -> list[tuple[Any, str]]:
        """Queue ``q``'s new messages, each with its severity's name (raises on a torn read)."""
        out = []
        for m in client.messages(self.cursor[q], queue=q):
            if self.cursor[q] and m.first_seq > self.cursor[q] + 1:  # a long message takes several
                self.lost[q] += m.first_seq - self.cursor[q] - 1
            self.cursor[q] = max(self.cursor[q], m.seq)
            out.append((m, m.severity.name if hasattr(m.severity, "name") else str(m.severity)))
        return out


def recorder_summary(path: Path, keys: tuple[str, ...], *, digits: int = 2, missing: dict | None = None) -> dict:
    """The ``keys`` of the recorder's summary of the recording at ``path`` (its MCAP
    metadata) and the file's size (``file_mb``, rounded to ``digits``); ``missing`` (or {})
    when there is no file, ``{"error": ...}`` for a file cut short."""
    if not path.exists():
        return dict(missing or {})
    from tools.recording.reader import read_metadata
    try:
        meta = read_metadata(path).get("pfma.recorder.summary", {})
    except Exception as err:  # noqa: BLE001 - a cut file: say so
        return {"error": f"{type(err).__name__}: {err}"}
    out = {k: meta.get(k) for k in keys}
    out["file_mb"] = round(path.stat().st_size / 1e6, digits)
    return out


class _Watch:
    """Everything read from the buffer while the stack runs."""

    def __init__(self, client, t0: float) -> None:
        self.c = client
        self.t0 = t0
        self.queues = MessageCursor()
        self.messages: list[dict] = []
        self.counts = {"service": {}, "controller": {}}
        self.stalls: dict[float, float] = {}  # host_stall_t_s -> length
        self.ft_max_age_s = 0.0
        self.ft_stale_reads = 0
        self.reads = 0
        self.link = client.layout.slot("link", "ft_sensor")
        self.last_inputs = None

    def poll(self) -> None:
        c = self.c
        for q in MessageCursor.QUEUES:
            try:
                got = self.queues.read(c, q)
            except Exception:  # noqa: BLE001 - a torn read: try again next time
                self.counts[q]["read_errors"] = self.counts[q].get("read_errors", 0) + 1
                continue
            for m, sev in got:
                self.counts[q][sev] = self.counts[q].get(sev, 0) + 1
                if sev in ("WARNING", "ERROR", "FATAL"):
                    self.messages.append({"queue": q, "seq": m.seq, "t_s": round(m.t_s, 3),
                                          "at_s": round(time.monotonic() - self.t0, 2), "severity": sev,
                                          "code": m.code, "text": m.text})
        try:
            s = c.read_inputs()
        except Exception:  # noqa: BLE001
            return
        self.reads += 1
        age = float(s.link_age_s[self.link])
        self.ft_max_age_s = max(self.ft_max_age_s, age)
        if int(s.link_status[self.link]) & LINK_STALE:
            self.ft_stale_reads += 1
        try:
            st, st_t = float(s.host_stall_s), float(s.host_stall_t_s)
            if st > 0:
                self.stalls[st_t] = st
        except (AttributeError, KeyError, ValueError):
            pass
        self.last_inputs = {"link_records": int(s.link_records[self.link]), "link_bad": int(s.link_bad[self.link]),
                            "link_resyncs": int(s.link_resyncs[self.link]),
                            "link_rate_hz": _r(float(s.link_rate_hz[self.link])),
                            "link_age_ms": _r(age * 1e3), "watchdog_tripped": int(s.watchdog_tripped),
                            "fault_code": int(s.fault_code), "frame": int(s.frame)}


def _area(client, name: str, fields: tuple[str, ...]) -> dict | str:
    """A stats area as a dict, or "n/a" when the layout has no such area or nobody owns it."""
    try:
        owner = client.owners().get(name)
        if owner is None or owner.pid <= 0:
            return "n/a"
        s = client.read(name)
        out = {}
        for f in fields:
            v = s[f]
            v = v.item() if hasattr(v, "item") else v
            out[f] = _r(v, 2) if isinstance(v, float) else int(v)
        if not out.get("frames"):
            return "n/a (owned, never published)"
        return out
    except Exception:  # noqa: BLE001 - an area this layout does not have
        return "n/a"


_LAYER_ERR = re.compile(r"^(\w[\w ]*?): .*", re.S)


def _layers_in_error(messages: list[dict]) -> list[dict]:
    """The controller's ERROR messages ("<layer>: <why>"), first per layer."""
    seen: dict[str, dict] = {}
    for m in messages:
        if m["queue"] != "controller" or m["severity"] != "ERROR":
            continue
        mm = _LAYER_ERR.match(m["text"])
        layer = mm.group(1) if mm else "?"
        seen.setdefault(layer, {"layer": layer, "at_s": m["at_s"], "why": m["text"], "count": 0})
        seen[layer]["count"] += 1
    return list(seen.values())


def _trips(messages: list[dict]) -> list[dict]:
    """Service messages that name a watchdog/safety trip or a fault (not the orderly stop's
    "outputs safe: service stopped" notice, which every run ends with)."""
    from ioservice.safety import STOP_CODE
    words = ("watchdog", "trip", "safe", "fault", "refused", "stale")
    return [m for m in messages if m["queue"] == "service" and m["code"] != STOP_CODE
            and any(w in m["text"].lower() for w in words)]


#: the CPU hog of ``--hog``: one busy process at nice 0 (assumed representative of an ordinary
#: host's other work: a compile, a browser tab spinning)
HOG = "import signal, sys\nsignal.signal(signal.SIGINT, lambda *a: sys.exit(0))\nwhile True:\n    pass"


def _start(procs: dict[str, _Proc], name: str, workdir: Path, rt_flag: list[str], hog: bool, rep: dict):
    """The hog (with ``--hog``) and the service; a client once it publishes frames, else
    None (said in ``rep``)."""
    py = sys.executable
    if hog:
        procs["hog"] = _Proc("hog", [py, "-c", HOG], workdir)
        rep["started"].append("hog")
    svc = procs["service"] = _Proc("service", [py, "-m", "tools.cli", "serve", "--rack", "fake", "--buffer", name,
                                               *rt_flag], workdir)
    rep["started"].append("service")
    t_start = time.monotonic()
    client = wait_for_frames(name, 10, timeout_s=START_TIMEOUT_S, alive=svc.alive)
    if client is None:
        rep["errors"].append("service exited during start-up" if not svc.alive() else
                             f"service published no frames within {START_TIMEOUT_S:g} s")
    rep["service_start_s"] = _r(time.monotonic() - t_start, 2)
    return client


def _run(client, procs: dict[str, _Proc], seconds: float, progress, rep: dict) -> _Watch:
    """The run proper: the buffer read every :data:`POLL_S` for ``seconds``, then the final
    counters while everything still runs."""
    t0 = time.monotonic()
    watch = _Watch(client, t0)
    next_report = t0 + 60.0
    while (now := time.monotonic()) - t0 < seconds:
        watch.poll()
        for p in procs.values():
            p.note_death(now - t0)
        if progress and now >= next_report:
            next_report += 60.0
            progress(f"{(now - t0) / 60:.0f} min: {len(watch.messages)} warnings/errors, "
                     f"F/T max age {watch.ft_max_age_s * 1e3:.0f} ms")
        time.sleep(POLL_S)
    watch.poll()
    rep["run_s"] = _r(time.monotonic() - t0, 2)
    for p in procs.values():
        p.note_death(time.monotonic() - t0)
        p.measure_cpu()
    rep["service_stats"] = _area(client, "stats", ("frames", "dropped_frames", "overruns", "stall_events",
                                                   "wake_latency_p99_us", "wake_latency_max_us",
                                                   "work_p99_us", "cpu_percent"))
    rep["controller_stats"] = _area(client, "controller_stats",
                                    ("frames", "missed_frames", "missed_events", "longest_missed_run",
                                     "missed_task_slots", "overruns", "rate_hz", "cpu_percent",
                                     "work_p50_us", "work_p99_us"))
    return watch


def _stop(procs: dict[str, _Proc], watch: _Watch | None, client, name: str, rep: dict) -> None:
    """Stop the stack, the service last (the others end cleanly), read what the shutdown
    posted, and remove the run's segments."""
    for key in ("controller", "recorder", "service", "hog"):
        p = procs.get(key)
        if p is not None:
            try:
                p.stop()
            except Exception as err:  # noqa: BLE001
                rep["errors"].append(f"stopping {key}: {err}")
    if watch is not None:
        try:
            watch.poll()  # the messages the shutdown posted
        except Exception:  # noqa: BLE001
            pass
    if client is not None:
        client.close()
    for p in procs.values():
        p.close()
    # a stopped service and controller leave their segments for tools to read; a
    # benchmark's are its own (a new name per run): remove them
    from bit3.buffer import Bit3Buffer
    from controller.worldmodel import WorldModel
    Bit3Buffer.unlink(name)
    WorldModel.remove_segment(name + "-wm")


def _watch_report(watch: _Watch, rep: dict) -> None:
    rep["messages"] = watch.messages
    rep["message_counts"] = watch.counts
    rep["messages_lost"] = watch.queues.lost
    rep["trips"] = _trips(watch.messages)
    rep["layers_in_error"] = _layers_in_error(watch.messages)
    rep["host_stalls"] = {"named": len(watch.stalls),
                          "longest_ms": _r(max(watch.stalls.values(), default=0.0) * 1e3),
                          "over_20ms": sum(1 for v in watch.stalls.values() if v > 0.02),
                          "over_60ms": sum(1 for v in watch.stalls.values() if v > 0.06),
                          "over_100ms": sum(1 for v in watch.stalls.values() if v > 0.1)}
    li = watch.last_inputs or {}
    rep["ft_link"] = {"records": li.get("link_records"), "bad": li.get("link_bad"),
                      "resyncs": li.get("link_resyncs"), "rate_hz": li.get("link_rate_hz"),
                      "max_age_ms": _r(watch.ft_max_age_s * 1e3),
                      "stale_fraction": _r(watch.ft_stale_reads / watch.reads, 4) if watch.reads else None,
                      "reads": watch.reads}
    rep["inputs"] = li
    rep["held"] = not rep["layers_in_error"] and not rep["errors"]


def command_ages(path: Path, limit: int = 4) -> dict | None:
    """The age of the command each ARMED service frame of the recording applied (its frame
    minus the inputs frame the command was computed from: the service's freshness rule's
    figure, ``command_input_age_frames``): count, p50, p99, max and how many were over
    ``limit`` (the service's default age limit, frames). None without a readable recording."""
    import numpy as np

    from bit3.layout import ServiceState
    from tools.recording.reader import read_frames
    try:
        ages = [int(r["command_input_age_frames"]) for _, _, r in read_frames(path)
                if int(r["service_state"]) == ServiceState.ARMED]
    except Exception:  # noqa: BLE001 - no recording (it is reported as such): no figure
        return None
    if not ages:
        return {"frames": 0}
    a = np.array(ages)
    return {"frames": len(a), "p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)),
            "max": int(a.max()), f"over_{limit}": int((a > limit).sum())}


def measure(minutes: float, workdir: Path, *, progress=None, realtime: bool = False, hog: bool = False,
            clock: str = "locked", profile: str = "layers") -> dict:
    py = sys.executable
    name = "pfma-stack-" + uuid.uuid4().hex[:6]
    rec_path = workdir / "stack.mcap"
    procs: dict[str, _Proc] = {}
    rep: dict = {"minutes": minutes, "buffer": name, "started": [], "errors": [], "realtime": realtime, "hog": hog,
                 "clock": clock, "profile": profile}
    rt_flag = ["--realtime"] if realtime else []  # service SCHED_FIFO on the last CPU, controller on CPU 0
    client = None
    watch = None
    try:
        client = _start(procs, name, workdir, rt_flag, hog, rep)
        if client is not None and not rep["errors"]:
            procs["controller"] = _Proc("controller", [py, "-m", "tools.cli", "controller", "--buffer", name,
                                                       "--wm", name + "-wm", "--power-up", "--clock", clock,
                                                       "--profile", profile, *rt_flag], workdir)
            procs["recorder"] = _Proc("recorder", [py, "-m", "tools.cli", "record", str(rec_path), "--buffer", name,
                                                   "--quiet"], workdir)
            rep["started"] += ["controller", "recorder"]
            watch = _run(client, procs, max(0.0, minutes * 60.0), progress, rep)
    except Exception as err:  # noqa: BLE001 - the report, never a traceback
        rep["errors"].append(f"{type(err).__name__}: {err}")
    finally:
        _stop(procs, watch, client, name, rep)
    rep["processes"] = {k: p.report() for k, p in procs.items()}
    for k, p in procs.items():
        if k == "hog":
            continue
        if p.died is not None:
            rep["errors"].append(f"{k} died after {p.died['at_s']} s (exit {p.died['returncode']})")
        elif p.stop_how.startswith("SIGKILL"):
            rep["errors"].append(f"{k} needed SIGKILL")
    rep["tails"] = {k: p.lines(8) for k, p in procs.items()}
    if watch is not None:
        _watch_report(watch, rep)
    rep["recorder"] = recorder_summary(rec_path, ("frames_recorded", "recorder_missed", "service_skipped",
                                                  "messages_missed", "lossless", "sessions"))
    rep["command_age"] = command_ages(rec_path)
    return rep


def _pairs_text(d) -> str:
    """A dict as readable words, ``frames recorded 1200, lossless yes`` (never a Python dict);
    anything else as it is."""
    if not isinstance(d, dict):
        return str(d)

    def one(v) -> str:
        if isinstance(v, bool):
            return "yes" if v else "no"
        return "-" if v is None else _pairs_text(v) if isinstance(v, dict) else str(v)
    return ", ".join(f"{str(k).replace('_', ' ')} {one(v)}" for k, v in d.items())


def _print(rep: dict) -> None:
    print(f"stack on buffer {rep['buffer']}: {rep.get('run_s', 0):g} s measured "
          f"(service up in {rep.get('service_start_s')} s){', beside a CPU hog' if rep.get('hog') else ''}")
    if (rep.get("clock") or "locked") != "locked" or (rep.get("profile") or "layers") != "layers":
        print(f"  controller --clock {rep.get('clock')} --profile {rep.get('profile')}")
    if "held" in rep:
        print(f"  {'HELD: no layer went to ERROR' if rep['held'] else 'NOT HELD: see the problems and layers below'}")
    _print_processes(rep)
    _print_service(rep.get("service_stats"))
    _print_controller(rep.get("controller_stats"))
    _print_ft_link(rep.get("ft_link"))
    h = rep.get("host_stalls")
    if h:
        print(f"  host stalls named by the service: {h['named']} (longest {h['longest_ms']} ms; >20 ms "
              f"{h['over_20ms']}, >60 ms {h['over_60ms']}, >100 ms {h['over_100ms']})")
    r = rep.get("recorder")
    if r:
        print(f"  recorder: {_pairs_text(r)}")
    a = rep.get("command_age")
    if a:
        print(f"  command age at the service (armed frames, service frames): {_pairs_text(a)}")
    if "trips" in rep:
        _print_messages(rep)


def _print_processes(rep: dict) -> None:
    """Each process (its CPU, how it stopped, whether it died), then the problems."""
    for k, p in rep.get("processes", {}).items():
        died = f", DIED at {p['died']['at_s']} s (exit {p['died']['returncode']})" if p["died"] else ""
        print(f"  {k:<10} pid {p['pid']:<7} CPU {p['cpu_percent']} % of a core, stopped by {p['stopped']} "
              f"(exit {p['returncode']}){died}")
    for e in rep["errors"]:
        print(f"  PROBLEM: {e}")


def _print_service(s) -> None:
    if isinstance(s, dict):
        print(f"  service: frames {s['frames']}, dropped {s['dropped_frames']}, overruns {s['overruns']}, "
              f"stall events {s['stall_events']}, wake p99/max {s['wake_latency_p99_us']:.0f}/"
              f"{s['wake_latency_max_us']:.0f} us, work p99 {s['work_p99_us']:.0f} us")


def _print_controller(c) -> None:
    if isinstance(c, dict):
        print(f"  controller: frames {c['frames']}, missed {c['missed_frames']} in {c['missed_events']} events "
              f"(longest run {c['longest_missed_run']}), missed task slots {c['missed_task_slots']}, "
              f"overruns {c['overruns']}")
    else:
        print(f"  controller: no statistics ({c})")


def _print_ft_link(f) -> None:
    if f:
        print(f"  F/T link: records {f['records']}, bad {f['bad']}, resyncs {f['resyncs']}, rate {f['rate_hz']} Hz, "
              f"max age {f['max_age_ms']} ms (read every {POLL_S * 1e3:.0f} ms), stale in "
              f"{100 * (f['stale_fraction'] or 0):.2f} % of reads")


def _print_messages(rep: dict) -> None:
    """The trips, the layers that went to ERROR and the warnings/errors (the first 40)."""
    print(f"  trips (service): {len(rep['trips'])}")
    for m in rep["trips"][:20]:
        print(f"    {m['at_s']:8.2f} s {m['severity']:<7} {m['text']}")
    print(f"  layers that went to ERROR: {len(rep['layers_in_error'])}")
    for m in rep["layers_in_error"]:
        print(f"    {m['layer']} at {m['at_s']} s ({m['count']}x): {m['why']}")
    counts = "; ".join(f"{q} {_pairs_text(c) or 'none'}" for q, c in rep["message_counts"].items())
    print(f"  warnings/errors: {counts} (lost unread: {_pairs_text(rep['messages_lost']) or 'none'})")
    for m in rep["messages"][:40]:
        print(f"    {m['at_s']:8.2f} s {m['queue']:<10} {m['severity']:<7} {m['code']:>4} {m['text']}")
    if len(rep["messages"]) > 40:
        print(f"    ... {len(rep['messages']) - 40} more (--json has them all)")


def figures(minutes: float = 0.5, realtime: bool = False, hog: bool = False, clock: str = "locked",
            profile: str = "layers") -> dict:
    """The whole stack for ``minutes`` (real time): its headline figures (the full report is
    ``run(as_json=True)``). ``minutes`` and ``run_s`` name the duration."""
    with tempfile.TemporaryDirectory(prefix="pfma-bench-stack-") as d:
        rep = measure(minutes, Path(d), realtime=realtime, hog=hog, clock=clock, profile=profile)
    procs = rep.get("processes", {})
    return {"minutes": minutes, "run_s": rep.get("run_s"), "realtime": realtime, "hog": hog, "held": rep.get("held"),
            "service_start_s": rep.get("service_start_s"),
            "cpu_percent": {k: p.get("cpu_percent") for k, p in procs.items()},
            "service_stats": rep.get("service_stats"), "controller_stats": rep.get("controller_stats"),
            "ft_link": rep.get("ft_link"), "host_stalls": rep.get("host_stalls"), "recorder": rep.get("recorder"),
            "clock": clock, "profile": profile, "command_age": rep.get("command_age"),
            "trips": len(rep.get("trips", [])), "layers_in_error": rep.get("layers_in_error", []),
            "warnings_errors": len(rep.get("messages", [])), "errors": rep["errors"]}


def run(seconds: float | None = None, minutes: float = 10.0, as_json: bool = False, realtime: bool = False,
        hog: bool = False, clock: str = "locked", profile: str = "layers") -> dict:
    """Run the stack; ``seconds`` (``pfma bench --seconds``) overrides ``minutes`` when given."""
    if seconds is not None:
        minutes = seconds / 60.0
    progress = None if as_json else (lambda s: print("  ..." + s, flush=True))
    if not as_json:
        print(f"pfma serve --rack fake + pfma controller --power-up + pfma record, {minutes:g} min"
              f"{' (service and controller --realtime)' if realtime else ''}"
              f"{', beside one CPU hog at nice 0' if hog else ''}"
              f"{'' if (clock, profile) == ('locked', 'layers') else f'; controller --clock {clock} --profile {profile}'}",
              flush=True)
    with tempfile.TemporaryDirectory(prefix="pfma-bench-stack-") as d:
        rep = measure(minutes, Path(d), progress=progress, realtime=realtime, hog=hog, clock=clock, profile=profile)
    if as_json:
        print(json.dumps(rep, indent=1))
    else:
        _print(rep)
    return rep
