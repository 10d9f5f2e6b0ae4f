"""``pfma regs [KIND] [--assumptions]``: the boards' register tables and every assumption.

Printed from the ``BoardDescription`` tables that the drivers and fakes share, so
this is what the code believes about each board. ``--assumptions`` lists only what
is not backed by a source (the board's assumptions and every register whose
provenance says "assumed"), for checking against the real boards in the lab.
"""

from __future__ import annotations

import argparse
import sys

from drivers.registers import BoardDescription
from tools.cli import add_bus_arguments
from pfma.errors import PfmaError
from drivers.catalog import CATALOG as KINDS
from pfma.rack import board_description, load_rack


def add_parser(sub):
    p = sub.add_parser("regs", help="print register tables and modelling assumptions",
                       description=__doc__.split("\n\n")[1],
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("kind", nargs="?", metavar="KIND",
                   help=f"board kind ({', '.join(KINDS)}), device class (rtd, adc, dac, serial, pio) "
                        f"or board name from the rack; default: all")
    p.add_argument("--assumptions", action="store_true", help="only the assumptions")
    add_bus_arguments(p)  # --rack names the boards of each kind; --bus is not used
    return p


def _kinds(selector: str | None, rack) -> list[str]:
    if selector is None:
        return list(KINDS)
    if selector in KINDS:
        return [selector]
    by_device = [k for k, b in KINDS.items() if b.device == selector]
    if by_device:
        return by_device
    for b in rack.boards:
        if b.name == selector:
            return [b.kind]
    raise KeyError(selector)


def _table(desc: BoardDescription, boards: str) -> list[str]:
    lines = [f"{desc.kind}: {desc.title}",
             f"  window 0x{desc.window:X} bytes, {desc.byte_lanes} byte lanes; in this rack: {boards}"]
    if desc.constants:
        lines.append("  constants: " + ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
                                                   for k, v in desc.constants.items()))
    lines.append(f"  {'offset':<10} {'register':<12} {'w':>2} {'acc':<3} {'reset':<6}  source / meaning")
    for r in desc.registers:
        span = f"+0x{r.offset:02X}" + (f"..+0x{r.addr(r.count - 1):02X}" if r.count > 1 else "")
        name = f"{r.name}[{r.count}]" if r.count > 1 else r.name
        lines.append(f"  {span:<10} {name:<12} {r.width:>2} {r.access:<3} 0x{r.reset:04X}  {r.source}")
        if r.doc:
            lines.append(f"  {'':<10} {'':<12} {'':>2} {'':<3} {'':<6}  {r.doc}")
        for f in r.fields:
            bits = f"b{f.lsb}" if f.bits == 1 else f"b{f.lsb + f.bits - 1}..{f.lsb}"
            lines.append(f"  {'':<10}   {bits:<8} {f.name}" + (f": {f.doc}" if f.doc else ""))
    return lines


def _assumptions(desc: BoardDescription) -> list[str]:
    lines = [f"{desc.kind}: {desc.title}"]
    for text in desc.assumptions:
        lines.append(f"  - {text}")
    for r in desc.registers:
        if r.source.startswith("assumed"):
            lines.append(f"  - register {r.name} (+0x{r.offset:02X}): {r.source}")
    if len(lines) == 1:
        lines.append("  (none)")
    return lines


def run(args) -> int:
    rack = load_rack(args.rack)
    try:
        kinds = _kinds(args.kind, rack)
    except KeyError:
        print(f"pfma regs: {args.kind!r} is not a board kind, device class or board name; "
              f"kinds: {', '.join(KINDS)}", file=sys.stderr)
        return 2
    failures = 0
    blocks = []
    for kind in kinds:
        try:
            desc = board_description(kind)
        except (PfmaError, ImportError, AttributeError) as err:
            failures += 1
            blocks.append([f"{kind}: register table not available ({err})"])
            continue
        boards = ", ".join(f"{b.name}@0x{b.base:04X}" for b in rack.boards if b.kind == kind) or "none"
        blocks.append(_assumptions(desc) if args.assumptions else _table(desc, boards))
    print("\n\n".join("\n".join(b) for b in blocks))
    return 1 if failures else 0
