"""``pfma watch SIGNAL...``: a few values of a running service, one line per sample.

Signals are rack channels (``elbow_pitch_angle``), boards, links, hand controllers
(``cae``) or input-area fields (``ft_force_n``, ``ft_force_n[2]``, ``service_state``).
``--rate`` lines per second (default 30), ``--count`` lines then exit; ``--json`` prints
each sample as one JSON object per line (JSON lines: ``t_s``, ``frame``, ``values``, ``units``). Waits for
the service with a message every few seconds (``--wait``) and reattaches when it
restarts; with no live service on the buffer at start (and no ``--wait``) it says so
and exits 1.
"""

from __future__ import annotations

import argparse
import time
from tools.cli.args import nonneg_float, nonneg_int, positive_float


def add_parser(sub):
    p = sub.add_parser("watch", help="a few values at ~30 Hz, one line each",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("signals", nargs="+", metavar="SIGNAL")
    p.add_argument("--buffer", default="pfma",
                   help="Bit3 shared-memory name (default pfma), or zenoh://HOST:PORT/NAME through a "
                        "pfma bridge (docs/bridge.md)")
    p.add_argument("--rack", default=None, help="rack TOML the service runs (default: the IRSS rack)")
    p.add_argument("--rate", type=positive_float, default=30.0, help="lines per second (default 30)")
    p.add_argument("--count", type=nonneg_int, default=0, help="stop after N lines (default: until Ctrl-C)")
    p.add_argument("--json", action="store_true", help="one JSON object per sample (JSON lines)")
    p.add_argument("--wait", type=nonneg_float, default=None, metavar="S",
                   help="wait this long for the service at start (0 = forever) and after it goes "
                        "away; default: no service at start is an error (exit 1), one that goes "
                        "away is waited for 30 s")
    return p


def run(args) -> int:
    from tools.attach import ServiceLink, no_service
    from tools.checkout.view import resolve_signals, watch_line, watch_record
    from tools.cli.output import print_json
    from bit3.buffer import Bit3Error
    from tools.cli.output import usage_error
    if args.rate <= 0:
        return usage_error("watch", f"--rate must be positive, not {args.rate}")
    from pfma.errors import PfmaError
    if args.wait is None:
        why = no_service(args.buffer)
        if why is not None:
            raise PfmaError(why)  # main prints it on one line, exit 1
    link = ServiceLink(args.buffer, args.rack, wait_s=30.0 if args.wait is None else args.wait)
    try:
        client = link.client()
        signals = resolve_signals(client.layout, args.signals)
        period = 1.0 / args.rate
        t_next = time.monotonic()
        n = 0
        while not args.count or n < args.count:
            client = link.client()
            try:
                snap = client.read_inputs()
                if args.json:
                    print_json(watch_record(snap, signals), line=True)
                else:
                    print(watch_line(snap, signals), flush=True)
            except Bit3Error as err:  # e.g. a service killed in the middle of a write
                link.invalidate(str(err))
                continue
            n += 1
            t_next += period
            delay = t_next - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            else:
                t_next = time.monotonic()  # fell behind: do not burst to catch up
        return 0
    finally:
        link.close()
