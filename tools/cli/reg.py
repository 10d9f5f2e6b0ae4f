"""``pfma reg``: register peek and poke for rack bring-up.

    pfma reg read ADDR [--width 8|16]
    pfma reg write ADDR VALUE [--width 8|16] --yes-i-know
    pfma reg dump BOARD

ADDR and VALUE are hex (0xD000) or decimal. Every line names the board and the
register at the address, from the rack configuration and the board's register
table. Reads can have side effects (a 6821 data read clears its IRQ flags; an ADC
DATA read clears EOC); writes drive real outputs, hence ``--yes-i-know``.
"""

from __future__ import annotations

import argparse
import sys

from tools.cli import add_bus_arguments
from tools.cli.output import add_json_flag, print_json
from tools.regs import (
    UsageError, dump_board_config, dump_doc, dump_header, dump_rows,
    is_fake_bus, plan_write, read_register, write_register)
from pfma.rack import RackConfig, load_rack

FAKE_NOTE = ("With --bus fake (the default) every command starts a fresh fake rack in its "
             "power-up state, so a write is not seen by the next command.")


def parse_int(text: str) -> int:
    """Hex (0xD000) or decimal; an argparse type."""
    try:
        return int(text, 0)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number (use 0xD000 or 53248)") from None


def parse_width(text: str) -> int:
    if text not in ("8", "16"):
        raise argparse.ArgumentTypeError(f"width must be 8 or 16, not {text!r}")
    return int(text)


# -- verbs ----------------------------------------------------------------------------------------
def cmd_read(args, rack: RackConfig) -> int:
    doc, line = read_register(rack, args.bus, args.addr, args.width)
    if args.json:
        print_json(doc)
    else:
        print(line)
    return 0


def cmd_write(args, rack: RackConfig) -> int:
    w = plan_write(rack, args.addr, args.value, args.width)
    if not args.yes_i_know:
        print(f"pfma reg write: {w.refusal()}", file=sys.stderr)
        return 2
    if w.read_only():
        print(f"note: the register table says {w.where} is read-only", file=sys.stderr)
    for line in write_register(rack, args.bus, w):
        print(line)
    return 0


def cmd_dump(args, rack: RackConfig) -> int:
    b = dump_board_config(rack, args.board)
    simulated = is_fake_bus(args.bus)
    if not args.json:
        print(dump_header(b, simulated))
    rows = []
    for row, line in dump_rows(rack, args.bus, b):
        rows.append(row)
        if not args.json:
            print(line)
    doc = dump_doc(b, rows, simulated)
    if args.json:
        print_json(doc)
    return 1 if doc["failures"] else 0


def add_parser(sub):
    p = sub.add_parser("reg", help="read, write or dump registers (A16 addresses)",
                       description=__doc__.split("\n\n")[1] + "\n\n" + FAKE_NOTE,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    verbs = p.add_subparsers(dest="reg_verb", metavar="ACTION", required=True)

    r = verbs.add_parser("read", help="read one register", epilog=FAKE_NOTE)
    r.add_argument("addr", type=parse_int, metavar="ADDR", help="A16 address, e.g. 0xD000")
    r.add_argument("--width", type=parse_width, default=None,
                   help="8 or 16 (default: the register table's width, else 16 even / 8 odd)")
    add_bus_arguments(r)
    add_json_flag(r)
    r.set_defaults(_reg=cmd_read)

    w = verbs.add_parser("write", help="write one register (needs --yes-i-know)", epilog=FAKE_NOTE)
    w.add_argument("addr", type=parse_int, metavar="ADDR", help="A16 address, e.g. 0xD000")
    w.add_argument("value", type=parse_int, metavar="VALUE", help="value, e.g. 0xC100")
    w.add_argument("--width", type=parse_width, default=None,
                   help="8 or 16 (default: the register table's width, else 16 even / 8 odd)")
    w.add_argument("--yes-i-know", action="store_true",
                   help="confirm: register writes can drive real outputs")
    add_bus_arguments(w)
    w.set_defaults(_reg=cmd_write)

    d = verbs.add_parser("dump", help="read every readable register of one board", epilog=FAKE_NOTE)
    d.add_argument("board", metavar="BOARD", help="board name from the rack file, e.g. rtd1")
    add_bus_arguments(d)
    add_json_flag(d)
    d.set_defaults(_reg=cmd_dump)
    return p


def run(args) -> int:
    rack = load_rack(args.rack)
    try:
        return args._reg(args, rack)
    except UsageError as err:
        print(f"pfma reg {args.reg_verb}: {err}", file=sys.stderr)
        return 2
