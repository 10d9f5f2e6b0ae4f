"""``pfma scope``: capture signals at the native frame rate, with a trigger and a pre-trigger.

    pfma scope SIGNAL... [--trigger 'SIGNAL>VALUE' | 'SIGNAL<VALUE'] [--pre S] [--post S]
               [-o capture.mcap] [--buffer NAME | zenoh://HOST:PORT/NAME] [--timeout S]
    pfma scope --open capture.mcap

A SIGNAL is a rack channel (``elbow_pitch_angle``, ``elbow_pitch_rate``: its engineering
value), an inputs-area field (``frame``, ``ft_status``) or one element of one
(``ft_force_n[2]``, ``adc_volts[3]``). Every published frame is looked at; the last
``--pre`` seconds are kept in a ring, and when the trigger condition becomes true (an
edge: false on the previous frame, true now) ``--post`` more seconds are captured. No
trigger: capture ``--post`` seconds at once. The capture is an MCAP file with one JSON
channel ``/pfma/scope`` ({t_s, frame, <signal>: value}) that Foxglove plots and
``pfma scope --open`` prints as a table and a text plot.
"""


from __future__ import annotations

from pathlib import Path

import argparse
import signal
import sys
import time

from tools.scope import ScopeCapture, capture_live, load, render, save, save_png
from tools.cli.args import nonneg_float, positive_float, positive_int


def add_parser(sub):
    p = sub.add_parser("scope", help="capture signals at the native rate with a trigger; saved as MCAP",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("signals", nargs="*", help="rack channels or inputs fields (field[i])")
    p.add_argument("--trigger", default=None, help="'SIGNAL>VALUE' or 'SIGNAL<VALUE' (rising into the condition)")
    p.add_argument("--pre", type=nonneg_float, default=0.1, help="seconds kept before the trigger (0.1)")
    p.add_argument("--post", type=positive_float, default=0.5, help="seconds captured after the trigger (0.5)")
    p.add_argument("-o", "--output", default="capture.mcap", help="capture file (capture.mcap)")
    p.add_argument("--buffer", default="pfma",
                   help="Bit3 shared-memory name (default pfma), or zenoh://HOST:PORT/NAME through a "
                        "pfma bridge (docs/bridge.md)")
    p.add_argument("--rack", default="fake", help="rack TOML the service runs")
    p.add_argument("--timeout", type=positive_float, default=None, help="give up when no trigger within S seconds")
    p.add_argument("--open", metavar="CAPTURE.mcap", default=None, help="print a saved capture")
    p.add_argument("--rows", type=positive_int, default=20, help="--open: table rows (decimated)")
    p.add_argument("--json", action="store_true",
                   help="--open: the whole capture (every sample) as one JSON document")
    return p



def run(args) -> int:
    if args.open:
        from tools.cli import check_mcap, mcap_errors
        check_mcap(args.open)
        with mcap_errors(args.open):
            cap = load(args.open)
        if args.json:
            from tools.cli.output import print_json
            print_json({"file": args.open, "signals": cap.signals, "units": cap.units, "trigger": cap.trigger,
                        "trigger_t_s": cap.trigger_t_s, "trigger_frame": cap.trigger_frame,
                        "pre_s": cap.pre_s, "post_s": cap.post_s, "samples": len(cap.t_s),
                        "t_s": cap.t_s, "frames": cap.frames,
                        "values": {sig: [row[j] for row in cap.values] for j, sig in enumerate(cap.signals)}})
            return 0
        print(render(cap, rows=args.rows))
        return 0
    if args.json:
        print("pfma scope: --json prints a saved capture: give it with --open CAPTURE.mcap", file=sys.stderr)
        return 2
    if not args.signals:
        print("pfma scope: name at least one signal (or --open CAPTURE.mcap)", file=sys.stderr)
        return 2
    from bit3.layout import build_layout, default_layout
    from tools.attach import attach_reader, remote_target, wait_for_service
    from tools.recording.schema import epoch_offset_ns
    from pfma.rack import load_rack
    layout = default_layout() if args.rack in ("fake", "default") else build_layout(load_rack(args.rack))
    try:
        sc = ScopeCapture(layout, args.signals, args.trigger, args.pre, args.post)
    except KeyError as err:  # an unknown signal: exit 1, as read and watch
        print(f"pfma scope: {err.args[0] if err.args else err}", file=sys.stderr)
        return 1
    except ValueError as err:  # a malformed trigger
        print(f"pfma scope: {err.args[0] if err.args else err}", file=sys.stderr)
        return 2
    stop = {"flag": False}
    old = signal.signal(signal.SIGINT, lambda *_: stop.__setitem__("flag", True))
    say = lambda s: print(f"pfma scope: {s}", file=sys.stderr, flush=True)  # noqa: E731
    t_start = time.monotonic()
    client = None
    try:
        if remote_target(args.buffer) is not None:  # through a bridge: every frame queued
            client = attach_reader(args.buffer, args.rack, every_frame=True,
                                   timeout_s=min(args.timeout or 5.0, 5.0))
        else:
            client = wait_for_service(args.buffer, layout, timeout_s=args.timeout, say=say,
                                      stop=lambda: stop["flag"])
        if client is None:
            say("no service; nothing captured")
            return 1
        say(f"armed: {', '.join(args.signals)}; trigger {args.trigger or 'immediate'}; "
            f"pre {args.pre:g} s, post {args.post:g} s (Ctrl-C cancels)")
        how = capture_live(client, sc, trigger=args.trigger, timeout_s=args.timeout, t_start=t_start,
                           stop=lambda: stop["flag"], say=say)
        if how == "timeout":
            say(f"no trigger within {args.timeout:g} s; nothing saved")
            return 1
        if how == "stopped":
            say("cancelled before the capture completed; nothing saved")
            return 130
        n = save(sc.capture, args.output, epoch_offset_ns=epoch_offset_ns(),
                 meta={"buffer": args.buffer, "layout_hash": layout.hash_hex})
        png = save_png(sc.capture, Path(args.output).with_suffix(".png"))
        print(render(sc.capture, rows=args.rows))
        print(f"pfma scope: {n} samples saved to {args.output}, plot {png} "
              f"(reopen: pfma scope --open {args.output})")
        return 0
    finally:
        signal.signal(signal.SIGINT, old)
        if client is not None:
            client.close()
