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
import json
import os
import sys
from pathlib import Path

from pfma.log import add_argument as add_log_level
from pfma.log import for_process as process_logging
from tools.cli.args import nonneg_float, positive_float, positive_int

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
    p.add_argument("--realtime", action=argparse.BooleanOptionalAction, default=None,
                   help="the capture thread (every frame, every message) at SCHED_FIFO priority 10, below "
                        "the service and controller: taken by default where this user may, said in one "
                        "line; --no-realtime opts out")
    add_log_level(p)
    return p


def run(args) -> int:
    with process_logging("pfma record", args.log_level):
        return _run(args)


def _run(args) -> int:
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
    if remote_target(args.buffer) is not None and args.wm is not None:
        print("pfma record: --wm records a world model on this host; with a remote --buffer "
              "(zenoh://...) record the world model where the controller runs", file=sys.stderr)
        return 2
    from tools.stacks.recorder import RecorderConfig, record
    return record(RecorderConfig(args.target[0], buffer=args.buffer, rack=args.rack, duration_s=args.duration,
                                 json_every=args.json_every, flush_s=args.flush_s, wait_s=args.wait,
                                 quiet=args.quiet, wm_name=args.wm, patterns=patterns,
                                 realtime=args.realtime))


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


#: the ``pfma.recorder.summary`` counters ``info`` prints
_RECORDER_KEYS = ("frames_recorded", "recorder_missed", "service_skipped", "frame_gaps",
                  "window_service_frames", "window_recorded", "window_service_dropped",
                  "messages_missed", "sessions", "lossless")


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
    topics = _topics(s, dur)
    with mcap_errors(path):
        meta = read_metadata(path)
    if args.json:
        _print_info_json(path, st, dur, topics, meta)
        return 0
    print(f"{path}: {st.message_count} messages, {st.chunk_count} chunks, {dur:.3f} s, "
          f"{st.attachment_count} attachments, {st.metadata_count} metadata")
    width = max([22] + [len(t["topic"]) for t in topics])
    for t in topics:
        print(f"  {t['topic']:{width}} {t['messages']:9d}  {t['rate_hz']:8.1f}/s  {t['encoding']}")
    summ = meta.get("pfma.recorder.summary")
    if summ:
        print("  recorder: " + ", ".join(f"{k}={summ.get(k)}" for k in _RECORDER_KEYS))
    _print_wm(meta.get("pfma.wm"), meta.get("pfma.wm.summary"))
    _print_link(_link(meta.get("pfma.link")))
    return 0


def _topics(s, dur: float) -> list[dict]:
    """Per channel of the summary ``s``: topic, messages, rate and encoding."""
    topics = []
    for cid, n in sorted(s.statistics.channel_message_counts.items()):
        ch = s.channels[cid]
        topics.append({"topic": ch.topic, "messages": n, "rate_hz": n / dur if dur > 0 else 0.0,
                       "encoding": ch.message_encoding})
    return topics


def _print_info_json(path: str, st, dur: float, topics: list[dict], meta: dict) -> None:
    """``pfma record info --json``."""
    from tools.cli.output import print_json
    summ = meta.get("pfma.recorder.summary")
    wm, wsum = meta.get("pfma.wm"), meta.get("pfma.wm.summary")
    print_json({"file": path, "messages": st.message_count, "chunks": st.chunk_count, "duration_s": dur,
                "attachments": st.attachment_count, "metadata": st.metadata_count, "topics": topics,
                "recorder": {k: summ.get(k) for k in _RECORDER_KEYS} if summ else None,
                "world_model": None if not wm else {
                    "name": wm.get("name"), "patterns": json.loads(wm.get("patterns", "[]")),
                    "variables": json.loads(wm.get("variables", "[]")),
                    "summary": {k: wsum.get(k) for k in _WM_KEYS} if wsum else None},
                "link": _link(meta.get("pfma.link"))})


def _print_wm(wm: dict | None, wsum: dict | None) -> None:
    """The world model line of ``pfma record info`` (nothing without ``pfma.wm`` metadata)."""
    if not wm:
        return
    nvars = len(json.loads(wm.get("variables", "[]")))
    print(f"  world model {wm.get('name')!r}: {nvars} variables from "
          f"{', '.join(json.loads(wm.get('patterns', '[]')))}"
          + (": " + ", ".join(f"{k}={wsum.get(k)}" for k in _WM_KEYS) if wsum else ""))


def _print_link(link: dict | None) -> None:
    """The remote source line of ``pfma record info`` (nothing for a local recording)."""
    if not link:
        return
    ranges = ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in link["lost_ranges"]) or "none"
    print(f"  remote source {link['source']}: {link['inputs_received']} inputs bodies, frames lost "
          f"{link['frames_lost']} ({ranges}), service skipped {link['service_skipped']}")


def _link(meta: dict | None) -> dict | None:
    """A remote recording's ``pfma.link`` metadata (tools/recording/remote.py), typed."""
    if not meta:
        return None
    return {"source": meta.get("source"), "inputs_received": int(meta.get("inputs_received", 0)),
            "frames_lost": int(meta.get("frames_lost", 0)), "lost_ranges": json.loads(meta.get("lost_ranges", "[]")),
            "service_skipped": int(meta.get("service_skipped", 0)), "counted_from": meta.get("counted_from")}


#: the ``pfma.wm.summary`` counters ``info`` prints
_WM_KEYS = ("samples", "frames_seen", "frames_unseen", "torn_reads", "sessions", "went_away")
