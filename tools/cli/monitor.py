"""``pfma monitor``: live view of every channel of a running service (halmeter for all).

Each rack channel, board, link and hand controller with its engineering value and
units, measured rate, status bits and detail (where it is, raw value), plus the
service state, frame rate, device rates and the latest messages. Every line fits 80
columns. The live view redraws twice a second and fits the terminal: the header and
the column names stay at the top, the channel rows are shown a page at a time (space
or n: next page, p: previous, q: quit; the page also advances by itself every
``--page-s`` seconds). ``--filter`` keeps channels whose name, label, kind or board
contains the text (or matches a shell pattern such as ``wrist_*``); ``--once`` prints
one plain snapshot and exits (scripts, tests); ``--once --json`` prints it as one JSON
document. Waits for the service with a message every few seconds (``--wait``) and
reattaches when it restarts; with no live service on the buffer at start (and no
``--wait``) it says so at once and exits 1, as ``pfma stats`` does.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import select
import shutil
import sys
import time
from tools.cli.args import nonneg_float, positive_float

CLEAR = "\x1b[H\x1b[2J"
#: the line under the header when the service's rack is simulated (its SIMULATED flag in the
#: Bit3 header, ``HeaderInfo.rack_kind``); ``--json`` has ``rack_kind``
SIMULATED_LINE = "SIMULATED RACK: the service's boards are the register-level fakes"


def add_parser(sub):
    p = sub.add_parser("monitor", help="live view of every channel (units, rates, status, links)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--buffer", default="pfma", help="Bit3 shared-memory name (default pfma)")
    p.add_argument("--rack", default=None, help="rack TOML the service runs (default: the IRSS rack)")
    p.add_argument("--filter", default=None, metavar="TEXT", help="only channels matching TEXT")
    p.add_argument("--once", action="store_true", help="print one snapshot and exit")
    p.add_argument("--json", action="store_true", help="with --once: the snapshot as one JSON document")
    p.add_argument("--interval", type=positive_float, default=0.5, help="redraw period, s (default 0.5)")
    p.add_argument("--page-s", type=positive_float, default=5.0, metavar="S",
                   help="live view: turn to the next page of channels every S seconds (0 = only by key)")
    p.add_argument("--wait", type=nonneg_float, default=None, metavar="S",
                   help="wait this long for the service at start (0 = forever) and after it goes "
                        "away; default: no service at start is an error (exit 1), one that goes "
                        "away is waited for 30 s")
    return p


@contextlib.contextmanager
def _keys():
    """Single key presses from a terminal's stdin (a function returning one key or "");
    on a pipe, a function that never has a key."""
    if not sys.stdin.isatty():
        yield lambda: ""
        return
    import termios
    import tty
    fd = sys.stdin.fileno()
    old = termios.tcgetattr(fd)
    tty.setcbreak(fd)

    def key() -> str:
        ready, _, _ = select.select([fd], [], [], 0)
        return os.read(fd, 1).decode(errors="replace") if ready else ""
    try:
        yield key
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, old)


def run(args) -> int:
    from tools.attach import ServiceLink, no_service
    from tools.checkout.view import monitor_data, monitor_lines, monitor_screen
    from tools.cli.output import print_json, usage_error
    from bit3.access import Bit3AccessError
    from bit3.buffer import Bit3Error
    from pfma.errors import PfmaError
    if args.json and not args.once:
        return usage_error("monitor", "--json prints one snapshot: give it with --once")
    if args.interval <= 0:
        return usage_error("monitor", f"--interval must be positive, not {args.interval}")
    if args.wait is None:
        why = no_service(args.buffer)
        if why is not None:
            raise PfmaError(why)  # main prints it on one line, exit 1
    link = ServiceLink(args.buffer, args.rack, wait_s=30.0 if args.wait is None else args.wait)
    try:
        if args.once:
            kind = link.client().header().rack_kind
            if args.json:
                print_json({**monitor_data(link.client(), args.filter), "rack_kind": kind})
            else:
                print("\n".join(_with_rack(monitor_lines(link.client(), args.filter), kind)))
            return 0
        page, pages, t_page = 0, 1, time.monotonic()
        with _keys() as key:
            while True:
                k = key()
                if k in ("q", "Q"):
                    return 0
                now = time.monotonic()
                if k in (" ", "n") or (args.page_s > 0 and now - t_page >= args.page_s):
                    page, t_page = (page + 1) % pages, now
                elif k == "p":
                    page, t_page = (page - 1) % pages, now
                size = shutil.get_terminal_size((80, 24))
                try:
                    d = monitor_data(link.client(), args.filter)
                    kind = link.client().header().rack_kind
                except Bit3AccessError:
                    raise  # no permission: one message now, not a reattach loop
                except Bit3Error as err:  # e.g. a service killed in the middle of a write
                    link.invalidate(str(err))
                    continue
                extra = len(_with_rack([""], kind)) - 1
                lines, pages = monitor_screen(d, page, size.lines - extra,
                                              min(size.columns, 80) if size.columns else 80)
                lines = _with_rack(lines, kind)
                sys.stdout.write(CLEAR + "\n".join(lines))
                sys.stdout.flush()
                time.sleep(args.interval)
    finally:
        link.close()


def _with_rack(lines: list[str], rack_kind: str) -> list[str]:
    """The monitor's lines with :data:`SIMULATED_LINE` under the first when the rack is
    simulated (nothing is added for a hardware bus or an unknown rack: no claim is made)."""
    return lines[:1] + [SIMULATED_LINE] + lines[1:] if rack_kind == "simulated" else lines
