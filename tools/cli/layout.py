"""``pfma layout``: the Bit3 buffer layout (every field: name, area, offset, dtype, shape, units)."""

from __future__ import annotations

import json

from bit3.layout import build_layout, layout_markdown
from pfma.rack import load_rack


def add_parser(sub):
    p = sub.add_parser("layout", help="print the Bit3 buffer layout (areas, fields, channels)")
    p.add_argument("--rack", default="fake", help="rack TOML (default: the IRSS report's tables)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--json", action="store_true", help="the whole layout as JSON")
    g.add_argument("--markdown", action="store_true",
                   help="the generated document (docs/bit3-layout.md)")
    p.add_argument("--channels", action="store_true", help="also list every channel's offsets")
    return p


def run(args) -> int:
    lay = build_layout(load_rack(args.rack))
    if args.json:
        print(json.dumps(lay.as_json(), indent=1))
        return 0
    if args.markdown:
        print(layout_markdown(lay), end="")
        return 0
    print(f"Bit3 buffer: {lay.size} bytes, layout version {lay.version}, hash {lay.hash_hex}, "
          f"rack {lay.rack_name}")
    print(f"{'area':20} {'offset':>6} {'size':>6}  writer")
    for a in lay.areas:
        print(f"{a.name:20} {a.offset:6d} {a.size:6d}  {a.writer or '-'}")
    print()
    print(f"{'field':26} {'area':20} {'offset':>6} {'dtype':10} {'shape':8} units")
    for f in lay.fields:
        shape = "x".join(map(str, f.shape)) if f.shape else "-"
        print(f"{f.name:26} {f.area:20} {f.offset:6d} {f.dtype:10} {shape:8} {f.units}")
    if args.channels:
        print()
        print(f"{'channel':32} {'area':9} {'kind':7} {'slot':>4}  {'units':6} offsets")
        for c in lay.channels:
            offs = " ".join(f"{f}@{o}" for f, _, o in c.fields)
            print(f"{c.name:32} {c.area:9} {c.kind:7} {c.slot:4d}  {c.units:6} {offs}")
    return 0
