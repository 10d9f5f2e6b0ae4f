"""``pfma record``: lossless MCAP recording of a running service's Bit3 buffer.

    pfma record FILE.mcap [--buffer NAME] [--duration S] [--json-every N]
                          [--wm NAME --var PATTERN[@RATE] [--var ...]]
    pfma record recover BROKEN.mcap [-o FIXED.mcap]
    pfma record info FILE.mcap

Every inputs frame is written raw (``/pfma/inputs_raw``, lossless) and as JSON channels
Foxglove plots (``/pfma/joints``, ``/pfma/adc``, ...); see docs/recording.md. The
recorder waits with a message while no service is up, and when the service stops or
is restarted it goes back to waiting and continues the same file as a new session
(frame numbers start again; counters stay per recording). A buffer with another
layout (another rack file) ends the recording with an error: that is a different
recording. Ctrl-C, SIGTERM or ``--duration`` end it cleanly with the counters and the
MCAP summary written. A killed recorder loses at most ``--flush-s`` (0.25 s); ``pfma
record recover`` makes such a file whole.

With ``--wm NAME --var PATTERN[@RATE]`` the chosen variables of the controller's world
model (glob patterns over variable names: ``servo.*``, ``*.status``; RATE in Hz, default
every controller frame) go into the same file as ``/pfma/wm/<area>`` JSON topics on the
same time axis (tools/recording/wm.py). The world model is attached read-only. While it
is not there the recorder waits for it (``--wait`` bounds this too); a pattern that
matches nothing or a bad rate is a usage mistake (exit 2, nothing recorded). A controller
that stops mid-recording is said once; the Bit3 topics go on, and the world-model topics
continue when it comes back.

With ``--buffer zenoh://HOST:PORT/NAME`` it records a remote rack through its ``pfma
bridge`` (docs/bridge.md): the same file, lossless when the link keeps up; frames lost
on the way are named (the ``pfma.link`` metadata and the last line: "LOST 5 frames:
frames 1220-1224"), apart from frames the service itself skipped.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import signal
import sys
import time
from pathlib import Path

from pfma.rack import load_rack
from tools.cli.args import nonneg_float, positive_float, positive_int

#: no new frame for this long: look whether the service is still there
STALE_S = 1.0
#: sleep between polls when nothing changed, without a frame ring (a 1 kHz frame is 1 ms)
POLL_SLEEP_S = 0.0004
#: with a frame ring the inputs cannot be missed (the capture thread polls the ring every
#: ``RING_POLL_S``); this loop then only looks for commands, stats and messages: every 2 ms
#: catches each command publish of a 320 Hz controller (3.125 ms apart) unless two land
#: within one poll, and costs ~500 wake-ups a second instead of ~2500
COMMANDS_POLL_S = 0.002


def _ring(buffer: str, client):
    """The service's frame ring of this buffer and layout, or None (then the inputs area
    itself is polled, and a reader descheduled for a frame period misses that frame)."""
    from bit3.ring import FrameRing, RingError
    try:
        return FrameRing.attach(buffer, client.layout.hash)
    except RingError:
        return None


def add_parser(sub):
    p = sub.add_parser("record", help="record every frame of the buffer to MCAP (also: recover, info)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("target", nargs="+", metavar="FILE.mcap | recover BROKEN.mcap | info FILE.mcap")
    p.add_argument("-o", "--output", default=None, help="recover: output file (default BROKEN-recovered.mcap)")
    p.add_argument("--buffer", default="pfma",
                   help="Bit3 shared-memory name (default pfma), or zenoh://HOST:PORT/NAME through a "
                        "pfma bridge (docs/bridge.md)")
    p.add_argument("--rack", default="fake", help="rack TOML the service runs (default: the IRSS rack)")
    p.add_argument("--duration", type=positive_float, default=None, help="seconds to record (default: until Ctrl-C)")
    p.add_argument("--json-every", type=positive_int, default=1,
                   help="JSON channels for every Nth frame (1 = native rate; the raw stream is always complete)")
    p.add_argument("--flush-s", type=positive_float, default=0.25, help="close a chunk at least this often (s)")
    p.add_argument("--wait", type=nonneg_float, default=None, help="give up when no service comes within S seconds")
    p.add_argument("--quiet", action="store_true", help="only the final summary")
    p.add_argument("--json", action="store_true", help="info: one JSON document (topics, counts, recorder summary)")
    p.add_argument("--wm", default=None, metavar="NAME",
                   help="also record variables of this world model (the controller's --wm; read-only)")
    p.add_argument("--var", action="append", default=[], metavar="PATTERN[@RATE]",
                   help="world-model variables to record: a glob over names (servo.*, ui.state, "
                        "*.status), optionally @RATE in Hz (default: every controller frame); repeatable")
    return p


def run(args) -> int:
    verb = args.target[0]
    if verb == "recover":
        return _recover(args)
    if verb == "info":
        return _info(args)
    if len(args.target) != 1:
        print("pfma record: one output file, or 'recover FILE' / 'info FILE'", file=sys.stderr)
        return 2
    from tools.recording.wm import WmUsageError, parse_var
    try:
        if args.var and not args.wm:
            raise WmUsageError("--var needs --wm NAME (the world model the controller runs: "
                               "`pfma controller --wm NAME`)")
        if args.wm is not None and not args.var:
            raise WmUsageError(f"--wm {args.wm} needs at least one --var PATTERN[@RATE] "
                               f"(e.g. --var 'servo.*'; `pfma wm list --wm {args.wm}` lists the variables)")
        if args.wm is not None and not args.wm.strip():
            raise WmUsageError("--wm needs a world-model name (e.g. --wm pfma_wm)")
        patterns = [parse_var(v) for v in args.var]
    except WmUsageError as err:
        print(f"pfma record: {err}", file=sys.stderr)
        return 2
    why = _unwritable(args.target[0])
    if why:  # said now, not after waiting for a service and recording into nowhere
        print(f"pfma record: cannot write {args.target[0]}: {why}; nothing recorded", file=sys.stderr)
        return 1
    from tools.attach import remote_target
    if remote_target(args.buffer) is not None:
        if args.wm is not None:
            print("pfma record: --wm records a world model on this host; with a remote --buffer "
                  "(zenoh://...) record the world model where the controller runs", file=sys.stderr)
            return 2
        return _record_remote(args)
    return record(args.target[0], buffer=args.buffer, rack_arg=args.rack, duration_s=args.duration,
                  json_every=args.json_every, flush_s=args.flush_s, wait_s=args.wait, quiet=args.quiet,
                  wm_name=args.wm, patterns=patterns)


def _unwritable(path: str) -> str:
    """Why a recording cannot be made at ``path`` ("" when it can, as far as one can tell
    before trying: the directory exists and this user may write in it; not a directory)."""
    p = Path(path)
    d = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        return "it is a directory"
    if not d.is_dir():
        return f"no directory {d}"
    if not os.access(d, os.W_OK | os.X_OK):
        return f"this user may not write in {d}"
    if p.exists() and not os.access(p, os.W_OK):
        return "this user may not write it"
    return ""


def _record_remote(args) -> int:
    """``--buffer zenoh://HOST:PORT/NAME``: the recording through a bridge (tools/recording/remote.py)."""
    from tools.recording.remote import record_remote
    sys.setswitchinterval(0.0005)  # as locally: the Zenoh threads get in while this one writes
    stop = {"flag": False}

    def handler(signum, _frame):
        stop["flag"] = True
    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    t_end = None if args.duration is None else time.monotonic() + args.duration
    try:
        return record_remote(args.target[0], args.buffer, rack_arg=args.rack, json_every=args.json_every,
                             flush_s=args.flush_s, wait_s=args.wait, say=_say(args.quiet),
                             done=lambda: stop["flag"] or (t_end is not None and time.monotonic() >= t_end),
                             summary=_summary_line)
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _recover(args) -> int:
    from tools.recording.recover import recover
    from tools.cli import check_mcap
    from pfma.errors import PfmaError
    if len(args.target) != 2:
        print("pfma record: usage: pfma record recover BROKEN.mcap [-o FIXED.mcap]", file=sys.stderr)
        return 2
    check_mcap(args.target[1], summary=False)  # missing / empty / not an MCAP: nothing written
    try:
        rep = recover(args.target[1], args.output)
    except ValueError as err:  # the output is the input
        raise PfmaError(str(err)) from err
    print(rep.describe())
    if not rep.messages:
        raise PfmaError(f"{args.target[1]}: no message recoverable"
                        f"{' (' + rep.stopped_by + ')' if rep.stopped_by else ''}")
    return 0


def _info(args) -> int:
    from tools.recording.reader import read_metadata
    from tools.cli import check_mcap, mcap_errors
    if len(args.target) != 2:
        print("pfma record: usage: pfma record info FILE.mcap", file=sys.stderr)
        return 2
    path = args.target[1]
    s = check_mcap(path)  # raises naming the file: missing, not an MCAP, damaged, unfinished
    st = s.statistics
    dur = (st.message_end_time - st.message_start_time) / 1e9
    topics = []
    for cid, n in sorted(st.channel_message_counts.items()):
        ch = s.channels[cid]
        topics.append({"topic": ch.topic, "messages": n, "rate_hz": n / dur if dur > 0 else 0.0,
                       "encoding": ch.message_encoding})
    with mcap_errors(path):
        meta = read_metadata(path)
    summ = meta.get("pfma.recorder.summary")
    keys = ("frames_recorded", "recorder_missed", "service_skipped", "frame_gaps",
            "window_service_frames", "window_recorded", "window_service_dropped",
            "messages_missed", "sessions", "lossless")
    if args.json:
        from tools.cli.output import print_json
        wm, wsum = meta.get("pfma.wm"), meta.get("pfma.wm.summary")
        print_json({"file": path, "messages": st.message_count, "chunks": st.chunk_count, "duration_s": dur,
                    "attachments": st.attachment_count, "metadata": st.metadata_count, "topics": topics,
                    "recorder": {k: summ.get(k) for k in keys} if summ else None,
                    "world_model": None if not wm else {
                        "name": wm.get("name"), "patterns": json.loads(wm.get("patterns", "[]")),
                        "variables": json.loads(wm.get("variables", "[]")),
                        "summary": {k: wsum.get(k) for k in _WM_KEYS} if wsum else None},
                    "link": _link(meta.get("pfma.link"))})
        return 0
    print(f"{path}: {st.message_count} messages, {st.chunk_count} chunks, {dur:.3f} s, "
          f"{st.attachment_count} attachments, {st.metadata_count} metadata")
    width = max([22] + [len(t["topic"]) for t in topics])
    for t in topics:
        print(f"  {t['topic']:{width}} {t['messages']:9d}  {t['rate_hz']:8.1f}/s  {t['encoding']}")
    if summ:
        print("  recorder: " + ", ".join(f"{k}={summ.get(k)}" for k in keys))
    wm, wsum = meta.get("pfma.wm"), meta.get("pfma.wm.summary")
    if wm:
        nvars = len(json.loads(wm.get("variables", "[]")))
        print(f"  world model {wm.get('name')!r}: {nvars} variables from "
              f"{', '.join(json.loads(wm.get('patterns', '[]')))}"
              + (": " + ", ".join(f"{k}={wsum.get(k)}" for k in _WM_KEYS) if wsum else ""))
    link = _link(meta.get("pfma.link"))
    if link:
        ranges = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in link["lost_ranges"]) or "none"
        print(f"  remote source {link['source']}: {link['inputs_received']} inputs bodies, frames lost "
              f"{link['frames_lost']} ({ranges}), service skipped {link['service_skipped']}")
    return 0


def _link(meta: dict | None) -> dict | None:
    """A remote recording's ``pfma.link`` metadata (tools/recording/remote.py), typed."""
    if not meta:
        return None
    return {"source": meta.get("source"), "inputs_received": int(meta.get("inputs_received", 0)),
            "frames_lost": int(meta.get("frames_lost", 0)), "lost_ranges": json.loads(meta.get("lost_ranges", "[]")),
            "service_skipped": int(meta.get("service_skipped", 0)), "counted_from": meta.get("counted_from")}


#: the ``pfma.wm.summary`` counters ``info`` prints
_WM_KEYS = ("samples", "frames_seen", "frames_unseen", "torn_reads", "sessions", "went_away")


def _say(quiet: bool):
    def say(text: str) -> None:
        if not quiet:
            print(f"pfma record: {text}", file=sys.stderr, flush=True)
    return say


def _frame_rate_hz(client) -> tuple[float, str]:
    """The service's frame rate (the cap of every-frame world-model samples) and where it
    came from: its statistics area's nominal period, else the schedule's default."""
    try:
        period = float(client.read_stats().as_dict().get("period_s") or 0.0)
    except Exception:  # noqa: BLE001 - no statistics published yet
        period = 0.0
    if period > 0:
        return 1.0 / period, "the service's statistics (period_s)"
    from ioservice.schedule import Schedule
    return Schedule().frame_rate_hz, "the schedule's default (no statistics published yet)"


def _open_wm(wm_name: str, patterns, *, wait_s, t_end, say, done):
    """(the sampler's world model and its first selection, exit code): waits for the world
    model like for the service; a pattern that matches nothing is a usage mistake (2)."""
    from tools.recording.wm import WmUsageError, select, wait_for_wm
    remaining = None if t_end is None else max(0.0, t_end - time.monotonic())
    if wait_s is not None:
        remaining = wait_s if remaining is None else min(wait_s, remaining)
    try:
        wm, why = wait_for_wm(wm_name, timeout_s=remaining, say=say, stop=done)
    except WmUsageError as err:
        print(f"pfma record: {err}; nothing recorded", file=sys.stderr)
        return None, 2
    if wm is None:
        limit = f" within {remaining:g} s" if remaining is not None else ""
        print(f"pfma record: no running world model /dev/shm/{wm_name}{limit} ({why}); "
              f"nothing recorded", file=sys.stderr)
        return None, 1
    try:
        select(wm.specs, patterns, wm_name=wm_name)
    except WmUsageError as err:
        wm.close()
        print(f"pfma record: {err}; nothing recorded", file=sys.stderr)
        return None, 2
    return wm, 0


def record(path: str, *, buffer: str = "pfma", rack_arg: str = "fake", duration_s: float | None = None,
           json_every: int = 1, flush_s: float = 0.25, wait_s: float | None = None,
           quiet: bool = False, wm_name: str | None = None, patterns=()) -> int:
    """The recording loop (see the module docstring); returns the exit code."""
    from bit3.layout import ServiceState, build_layout, default_layout
    from tools.attach import buffer_replaced, wait_for_service
    from tools.recording import InputsCapture, Recorder
    from bit3.buffer import LayoutMismatchError, SeqLockTimeout
    # the capture thread must get the GIL within a fraction of a frame while this one
    # compresses or encodes (the default switch interval is 5 ms, longer than a frame)
    sys.setswitchinterval(0.0005)
    rack = load_rack(rack_arg)
    layout = default_layout() if rack_arg in ("fake", "default") else build_layout(rack)
    say = _say(quiet)
    stop = {"flag": False}

    def handler(signum, _frame):
        stop["flag"] = True
    old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    t_end = None if duration_s is None else time.monotonic() + duration_s

    def done() -> bool:
        return stop["flag"] or (t_end is not None and time.monotonic() >= t_end)

    def wait(remaining):
        """(the service's client or None, True when its layout is another recording's)."""
        try:
            return wait_for_service(buffer, layout, timeout_s=remaining, say=say, stop=done), False
        except LayoutMismatchError as err:
            print(f"pfma record: {err}; this recording ends here (a different rack or "
                  f"layout is a different recording)", file=sys.stderr)
            return None, True

    rec = None
    err_code = 0
    wm = None
    write_error: OSError | None = None
    if wm_name is not None:
        wm, code = _open_wm(wm_name, patterns, wait_s=wait_s, t_end=t_end, say=say, done=done)
        if wm is None:
            for s, h in old.items():
                signal.signal(s, h)
            return code
    try:
        while not done():
            remaining = None if t_end is None else max(0.0, t_end - time.monotonic())
            if wait_s is not None and rec is None:
                remaining = wait_s if remaining is None else min(wait_s, remaining)
            client, mismatch = wait(remaining)
            if mismatch:
                err_code = 1
                break
            if client is None:
                if rec is None and not stop["flag"] and wait_s is not None:
                    print(f"pfma record: no service on /dev/shm/{buffer} within {wait_s:g} s; "
                          "nothing recorded", file=sys.stderr)
                    err_code = 1
                break
            if rec is None:
                sampler = None
                if wm is not None:
                    from tools.recording.wm import WmSampler, select
                    rate, source = _frame_rate_hz(client)
                    chosen = select(wm.specs, patterns, wm_name=wm_name or "", frame_rate_hz=rate)
                    sampler = WmSampler(wm, chosen, patterns=patterns, frame_rate_hz=rate, say=say)
                    wm = None  # the sampler (and then the recorder) owns it
                    say(f"world model /dev/shm/{wm_name}: {len(chosen)} variables in "
                        f"{len(sampler.topics())} topics (every-frame samples capped at {rate:g} Hz, "
                        f"from {source})")
                rec = Recorder(client, path, rack=rack, json_every=json_every, flush_every_s=flush_s,
                               meta={"command": " ".join(sys.argv)}, wm=sampler)
                say(f"recording /dev/shm/{buffer} to {path} (Ctrl-C ends it)")
            else:
                rec.attach(client)
                say(f"service back: recording continues as session {rec.counters.sessions}")
            gc.collect()
            gc.freeze()  # long-lived objects out of the collector's way: short GC pauses
            idle_since = time.monotonic()
            warned = False
            capture = InputsCapture(client, ring=_ring(buffer, client)).start()  # every publish
            while not done():
                try:
                    n = capture.drain(rec)
                    rec.poll(inputs=False)
                except SeqLockTimeout as e:  # the service died mid-write
                    say(f"{e}")
                    n = 0
                if capture.replaced_note is not None:
                    # a restarted service made a new frame ring and the capture moved to it:
                    # the new service's frames follow in the queue; start their session first
                    say(capture.replaced_note)
                    capture.replaced_note = None
                    if not buffer_replaced(client) and client.buffer.owner("inputs").alive:
                        continue  # this session's client already is the new service's (it made
                        # its buffer before its ring, and we attached in between)
                    rec.flush()
                    remaining = None if t_end is None else max(0.0, t_end - time.monotonic())
                    new, mismatch = wait(remaining)
                    if mismatch:
                        err_code = 1
                        stop["flag"] = True
                        break
                    if new is None:
                        break
                    rec.client = None
                    client.close()
                    client = capture.client = new
                    rec.attach(client)
                    say(f"service restarted: recording continues as session {rec.counters.sessions}")
                    idle_since = time.monotonic()
                    continue
                if capture.error is not None:
                    if isinstance(capture.error, SeqLockTimeout):
                        say(f"{capture.error}")
                    else:
                        raise capture.error
                    capture.stop()  # the thread has ended; this closes its ring
                    capture.drain(rec)
                    capture = InputsCapture(client, ring=_ring(buffer, client)).start()
                now = time.monotonic()
                if n:
                    idle_since = now
                    warned = False
                    continue
                if now - idle_since > STALE_S:
                    gone = buffer_replaced(client) or not client.buffer.owner("inputs").alive \
                        or client.service_state == ServiceState.STOPPED
                    if gone:
                        say(f"service on /dev/shm/{buffer} stopped after frame "
                            f"{rec.counters.last_frame}; waiting for it to come back")
                        rec.flush()
                        break
                    if not warned:
                        say(f"service pid {client.buffer.owner('inputs').pid} is alive but has "
                            f"published no frame for {now - idle_since:.1f} s")
                        warned = True
                time.sleep(POLL_SLEEP_S if capture.ring is None else COMMANDS_POLL_S)
            capture.stop()
            capture.drain(rec)
            rec.poll(inputs=False)
            rec.client = None
            client.close()
    except OSError as err:  # writing: the disk full, a file-size limit, the file system gone
        if rec is None:
            err_code = 1  # not a recording yet (main() names the file): not "no service came up"
            raise
        write_error = err
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        gc.unfreeze()
        if wm is not None:  # never handed to a recorder
            wm.close()
        if rec is not None:
            try:
                c = rec.close()
            except OSError as err:
                write_error = write_error or err
                c = None
            if c is not None:
                print(_summary_line(path, c), flush=True)
                if rec.wm is not None:
                    print(_wm_line(rec.wm), flush=True)
            if write_error is not None:
                from tools.cli import _os_error_text
                print(f"pfma record: cannot write {path}: {_os_error_text(write_error)}; the recording "
                      f"ends here and the file keeps what was written before: `pfma record recover "
                      f"{path}` makes a whole file of it", file=sys.stderr, flush=True)
                err_code = 1
        elif not err_code:
            print(f"pfma record: no service came up on /dev/shm/{buffer}; nothing recorded", file=sys.stderr)
            err_code = 1
    return err_code


def _wm_line(sampler) -> str:
    c = sampler.counters
    return (f"pfma record: world model {sampler.name!r}: {c.samples} samples of "
            f"{len(sampler.variables)} variables on {len(c.messages)} topics; controller frames not "
            f"seen {c.frames_unseen}, went away {c.went_away}, sessions {c.sessions}")


def _summary_line(path: str, c) -> str:
    tc = json.loads(c.topic_counts)
    return (f"pfma record: {path}: {c.frames_recorded} frames (frames {c.first_frame}..{c.last_frame}), "
            f"{c.messages_total} messages in {len(tc)} topics, {c.wall_s:.1f} s; recorder missed "
            f"{c.recorder_missed}, service skipped {c.service_skipped} (stats window: service ran "
            f"{c.window_service_frames}, recorded {c.window_recorded}, service dropped "
            f"{c.window_service_dropped}); messages missed {c.messages_missed}; sessions "
            f"{c.sessions}; {'LOSSLESS' if c.lossless else 'NOT LOSSLESS'}")
