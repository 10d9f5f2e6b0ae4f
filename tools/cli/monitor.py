"""``pfma monitor``: live view of every channel of a running service (halmeter for all).

Each rack channel, board, link and hand controller with its engineering value and
units, raw value, status bits and measured rate, plus the service state, frame
rate, link counters and the latest messages. Redrawn twice a second with plain ANSI
codes; ``--filter`` keeps channels whose name, label, kind or board contains the
text (or matches a shell pattern such as ``wrist_*``); ``--once`` prints one
snapshot and exits (scripts, tests). Waits for the service with a message every few
seconds (``--wait``) and reattaches when it restarts; with no live service on the
buffer at start (and no ``--wait``) it says so and exits 1.
"""

from __future__ import annotations

import argparse
import sys
import time

CLEAR = "\x1b[H\x1b[2J"


def add_parser(sub):
    p = sub.add_parser("monitor", help="live view of every channel (units, rates, status, links)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--buffer", default="pfma", help="Bit3 shared-memory name (default pfma)")
    p.add_argument("--rack", default=None, help="rack TOML the service runs (default: the IRSS rack)")
    p.add_argument("--filter", default=None, metavar="TEXT", help="only channels matching TEXT")
    p.add_argument("--once", action="store_true", help="print one snapshot and exit")
    p.add_argument("--interval", type=float, default=0.5, help="redraw period, s (default 0.5)")
    p.add_argument("--wait", type=float, default=None, metavar="S",
                   help="wait this long for the service at start (0 = forever) and after it goes "
                        "away; default: no service at start is an error (exit 1), one that goes "
                        "away is waited for 30 s")
    return p


def run(args) -> int:
    from tools.attach import ServiceLink, no_service
    from tools.checkout.view import monitor_lines
    from bit3.buffer import Bit3Error
    from pfma.errors import PfmaError
    if args.wait is None:
        why = no_service(args.buffer)
        if why is not None:
            raise PfmaError(why)  # main prints it on one line, exit 1
    link = ServiceLink(args.buffer, args.rack, wait_s=30.0 if args.wait is None else args.wait)
    try:
        if args.once:
            print("\n".join(monitor_lines(link.client(), args.filter)))
            return 0
        while True:
            try:
                lines = monitor_lines(link.client(), args.filter)
            except Bit3Error as err:  # e.g. a service killed in the middle of a write
                link.invalidate(str(err))
                continue
            sys.stdout.write(CLEAR + "\n".join(lines) + "\n")
            sys.stdout.flush()
            time.sleep(args.interval)
    finally:
        link.close()
