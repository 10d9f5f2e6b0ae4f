"""``pfma ft``: live forces and torques from the Lord/ATI F/T controller, plus bias commands.

Examples::

    pfma ft --port fake                      # fake controller on a real pty, binary, polled
    pfma ft --port fake --stream --count 20  # QS streaming through the reader thread
    pfma ft --port /dev/ttyS1 --ascii        # a real controller on a serial port
    pfma ft bias --port fake                 # SB, then show one reading
    pfma ft --port fake --count 5 --json     # JSON lines: one object per reading, then a summary

``--port`` here is the F/T controller's serial line (a pyserial URL), not a register bus.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from contextlib import ExitStack

from drivers.serial_ft.ftsensor import FtReader, FtReading, FtSensor, open_ft
from drivers.serial_ft.protocol import NOMINAL
from tools.cli.output import print_json
from tools.cli.args import positive_float, positive_int

ACTIONS = {"read": None, "bias": "bias", "unbias": "unbias", "clear-bias": "clear_bias"}


def add_parser(sub):
    p = sub.add_parser("ft", help="read the F/T sensor (live N, N.m and link statistics); bias it",
                       description="Read the Lord/ATI F/T controller over a serial port URL "
                                   "(device, pty, socket://, rfc2217://) or a fake on a real pty.")
    p.add_argument("action", nargs="?", choices=sorted(ACTIONS), default="read",
                   help="read (default), bias (SB), unbias (SU) or clear-bias (SZ)")
    p.add_argument("--port", default="fake", help="pyserial URL or 'fake' (default: fake)")
    p.add_argument("--baud", type=positive_int, default=19200, help="line rate, 8N1 (default 19200)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--binary", dest="mode", action="store_const", const="binary", help="binary records (default)")
    mode.add_argument("--ascii", dest="mode", action="store_const", const="ascii", help="ASCII records")
    p.set_defaults(mode="binary")
    p.add_argument("--checksum", action="store_true", help="binary records with checksum (CD E; algorithm assumed)")
    p.add_argument("--stream", action="store_true", help="stream (QS) through the reader thread instead of Ctrl-T polls")
    p.add_argument("--rate", type=positive_float, default=80.0, help="rate the rack needs, checked against the line (Hz)")
    p.add_argument("--average", type=positive_int, default=None, help="SA n: controller moving average over n samples")
    p.add_argument("--count", type=positive_int, default=None, help="stop after N printed readings")
    p.add_argument("--duration", type=positive_float, default=None, help="stop after S seconds")
    p.add_argument("--interval", type=positive_float, default=0.1, help="print period in seconds (default 0.1)")
    p.add_argument("--json", action="store_true",
                   help="JSON lines: one object per reading (type reading), then one summary (type summary); "
                        "notes go to stderr")
    p.add_argument("--cpf", type=float, default=NOMINAL.cpf, help=f"counts per N (default {NOMINAL.cpf:g}, assumed)")
    p.add_argument("--cpt", type=float, default=NOMINAL.cpt,
                   help=f"counts per N.m (default {NOMINAL.cpt:g}, assumed)")
    return p


def _line(r: FtReading, sensor: FtSensor) -> str:
    s = sensor.stats()
    f = " ".join(f"{v:+8.2f}" for v in r.force_n)
    t = " ".join(f"{v:+7.3f}" for v in r.torque_nm)
    age = "-" if s.age_s is None else f"{s.age_s * 1e3:.0f} ms"
    return (f"#{r.seq:<6d} F[N] {f}   T[N.m] {t}   st {r.status} | {s.rate_hz:6.1f} Hz  "
            f"bad {s.bad_records} resync {s.resyncs} age {age} in {s.bytes_in} B")


def _note(args: argparse.Namespace, text: str) -> None:
    """An informational line: stdout for people, stderr under --json (stdout is the JSON)."""
    print(text, file=sys.stderr if args.json else sys.stdout)


def run(args: argparse.Namespace) -> int:
    with ExitStack() as stack:
        url = args.port
        if url == "fake":
            from fakes.ft_sensor import FakeFtController, gentle_load
            from fakes.pty import PtyDevice

            dev = stack.enter_context(PtyDevice(FakeFtController(load_fn=gentle_load), baud=args.baud))
            url = dev.port_name
            _note(args, f"fake F/T controller on {url} ({args.baud} baud 8N1, gentle varying load)")
        sensor = open_ft(url, args.baud, cpf=args.cpf, cpt=args.cpt)
        stack.callback(sensor.close)
        sensor.set_mode(args.mode)
        if args.mode == "binary":
            sensor.set_checksum(args.checksum)
        if args.average is not None:
            sensor.set_average(args.average)
        limit = FtSensor.max_rate_hz(args.mode, args.baud, sensor.checksum_on)
        _note(args, f"{args.mode} records, line limit {limit:.1f} records/s; cpf {sensor.cpf:g}/N, cpt {sensor.cpt:g}/N.m")
        if ACTIONS[args.action]:
            getattr(sensor, ACTIONS[args.action])()
            _note(args, f"{args.action}: done")
            if args.count is None and args.duration is None:
                args.count = 1
        return _show(args, sensor, stack)
    return 0


def _show(args: argparse.Namespace, sensor: FtSensor, stack: ExitStack) -> int:
    reader = None
    if args.stream:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            reader = FtReader(sensor, rate_hz=args.rate, on_slow="warn").start()
        for w in caught:
            print(f"warning: {w.message}", file=sys.stderr)
        stack.callback(reader.stop)
    elif sensor.check_rate(args.rate, on_slow="ignore") < args.rate:
        print(f"note: {args.mode.upper()} at {args.baud} baud cannot carry {args.rate:g} Hz", file=sys.stderr)
    t_end = None if args.duration is None else time.monotonic() + args.duration
    printed = 0
    try:
        while (args.count is None or printed < args.count) and (t_end is None or time.monotonic() < t_end):
            t_next = time.monotonic() + args.interval
            if reader is not None:
                if reader.error is not None:
                    print(f"pfma ft: link lost: {reader.error}", file=sys.stderr)
                    return 1
                r = reader.latest()
            else:
                r = sensor.poll()
            if r is not None:
                if args.json:
                    print_json({"type": "reading", "seq": r.seq, "t_s": r.t_s, "status": r.status,
                                "force_n": r.force_n, "torque_nm": r.torque_nm, "counts": r.counts,
                                "link": sensor.stats()}, line=True)
                else:
                    print(_line(r, sensor), flush=True)
                printed += 1
            time.sleep(max(0.0, t_next - time.monotonic()))  # a CLI print period, not a test wait
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
    s = sensor.stats()
    if args.json:
        print_json({"type": "summary", "records": s.records, "bad_records": s.bad_records, "resyncs": s.resyncs,
                    "bytes_in": s.bytes_in, "bytes_discarded": s.bytes_discarded}, line=True)
        return 0
    print(f"records {s.records}  bad {s.bad_records}  resyncs {s.resyncs}  bytes in {s.bytes_in}  "
          f"discarded {s.bytes_discarded}")
    return 0
