"""``pfma read SIGNAL...``: read channels by signal name, in engineering units.

Signal names, scales and units come from the rack file (``pfma channels``). RTD
angles are radians; analog inputs are ``scale * volts + offset``; the DAC is
write-only, so its value is the driver's shadow (what this process last wrote,
the board's reset value when nothing was); PIO ports are the port byte.
"""

from __future__ import annotations

import argparse
import json
import sys

from pfma.cli import add_bus_arguments
from pfma.cli.reg import FAKE_NOTE, UsageError, close_bus, open_cli_bus
from pfma.errors import PfmaError
from pfma.rack import load_rack
from pfma.rackio import RackIO


def add_parser(sub):
    p = sub.add_parser("read", help="read channels by signal name (engineering units)",
                       description=__doc__.split("\n\n")[1] + "\n\n" + FAKE_NOTE,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("signals", nargs="+", metavar="SIGNAL", help="signal name(s), see `pfma channels`")
    p.add_argument("--json", action="store_true", help="one JSON list with an object per signal")
    add_bus_arguments(p)
    return p


def run(args) -> int:
    rack = load_rack(args.rack)
    try:
        bus = open_cli_bus(args.bus, rack)
    except UsageError as err:
        print(f"pfma read: {err}", file=sys.stderr)
        return 2
    io = RackIO(bus, rack)
    rows: list[dict] = []
    failures = 0
    try:
        for signal in args.signals:
            row: dict = {"signal": signal}
            try:
                ch = io.channel(signal)
                row.update(board=ch.board, channel=ch.channel, address=ch.address)
                r = io.read_signal(signal)
                row.update(value=r.value, units=r.units, raw=r.raw, note=r.note)
            except PfmaError as err:
                failures += 1
                row["error"] = str(err)
                if not args.json:
                    print(f"pfma read: {signal}: {err}", file=sys.stderr)
            rows.append(row)
    finally:
        close_bus(bus)
    if args.json:
        print(json.dumps(rows, indent=1))
    else:
        for row in rows:
            if "error" in row:
                continue
            value = row["value"]
            shown = f"{value:.6g}" if isinstance(value, float) else f"{value} (0x{value:02X})"
            print(f"{row['signal']:32} {shown:>14} {row['units']:6} raw {row['raw']:<6} "
                  f"{row['board']} ch {row['channel']}  {row['note']}".rstrip())
    return 1 if failures else 0
