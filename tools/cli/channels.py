"""``pfma channels``: the rack's channel map (from the rack TOML): a table, or ``--json``."""

from __future__ import annotations

import json

from pfma.rack import load_rack
from tools.cli.output import print_table, table


def add_parser(sub):
    p = sub.add_parser("channels", help="print the rack's channel map")
    p.add_argument("--rack", default="fake", help="rack TOML (default: the IRSS report's tables)")
    p.add_argument("--json", action="store_true", help="JSON list, one object per channel")
    return p


def run(args) -> int:
    rack = load_rack(args.rack)
    chans = rack.channels()
    if args.json:
        print(json.dumps([c.as_dict() for c in chans], indent=1))
        return 0
    t = table("device", "addr", "ch>", "signal", "dir", "Hz>", "units", "label")
    for c in chans:
        t.add_row(c.device, f"0x{c.address:04X}", str(c.channel), c.signal, c.direction, f"{c.rate_hz:g}",
                  c.units, c.label + ("  (spare)" if c.spare else ""))
    print_table(t)
    return 0
