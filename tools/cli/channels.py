"""``pfma channels``: the rack's channel map (from the rack TOML)."""

from __future__ import annotations

import json

from pfma.rack import load_rack


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
    print(f"{'device':6} {'addr':6} {'ch':>2}  {'signal':32} {'dir':3} {'rate':>5}  {'units':6} label")
    for c in chans:
        print(f"{c.device:6} 0x{c.address:04X} {c.channel:2d}  {c.signal:32} {c.direction:3} "
              f"{c.rate_hz:5g}  {c.units:6} {c.label}{'  (spare)' if c.spare else ''}")
    return 0
