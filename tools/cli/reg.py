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

from drivers.bus import open_bus
from drivers.registers import BoardDescription, Register
from tools.cli import add_bus_arguments
from tools.cli.output import add_json_flag, print_json
from pfma.errors import BusError
from pfma.rack import BoardConfig, RackConfig, board_description, load_rack

FAKE_NOTE = ("With --bus fake (the default) every command starts a fresh fake rack in its "
             "power-up state, so a write is not seen by the next command.")
#: what a read or dump of the fake rack adds to its line (``pfma read --bus fake`` says
#: "(simulated rack)" the same way)
SIMULATED_READ = "(simulated rack, power-up state)"
#: the line under a write to the fake rack
SIMULATED_WRITE = ("simulated rack: a fake in this process: nothing real was written, and the value is "
                   "gone when the command ends")


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


class UsageError(Exception):
    """Bad command-line input found after parsing (exit code 2, message on stderr)."""


#: Reply time-out of a Modbus gateway for the interactive tools (reg, read, hand): a person
#: is waiting, not a 320 Hz frame, so a loaded host's slow reply is not an error. The
#: service keeps the bus's default, one minor frame. ``?timeout=S`` in the URL wins.
INTERACTIVE_MODBUS_TIMEOUT_S = 0.5


def is_fake_bus(url: str) -> bool:
    """Whether ``--bus URL`` is the simulated rack: a fake built in this process (also behind
    ``spy+``). A Modbus gateway is a real bus even when a simulator answers at its far end
    (this process cannot see that)."""
    return url.removeprefix("spy+") in ("fake", "fake://", "")


def open_cli_bus(url: str, rack: RackConfig):
    """Open ``--bus``; the fake rack (also behind ``spy+``) is built from ``--rack``.

    :raises UsageError: for a malformed bus URL
    """
    inner = url[4:] if url.startswith("spy+") else url
    kwargs: dict = {"rack": rack} if is_fake_bus(url) else {}
    if inner.startswith("modbus://") and "timeout=" not in inner:
        kwargs["timeout"] = INTERACTIVE_MODBUS_TIMEOUT_S
    try:
        return open_bus(url, **kwargs)
    except ValueError as err:
        raise UsageError(f"--bus {url}: {err}") from None


def with_rack_context(err: BusError, rack: RackConfig) -> BusError:
    """Name board and register in a bus error that does not (a Modbus gateway's)."""
    if err.board is not None:
        return err
    b = board_at(rack, err.addr)
    if b is None:
        return err
    names = _names(board_description(b.kind), err.addr - b.base, err.op)
    return err.with_context(b.name, "/".join(n for n, _ in names) or None)


def close_bus(bus) -> None:
    close = getattr(bus, "close", None)
    if close is not None:
        close()


# -- naming an address ------------------------------------------------------------------------
def board_at(rack: RackConfig, addr: int) -> BoardConfig | None:
    for b in rack.boards:
        if b.base <= addr < b.base + b.window:
            return b
    return None


def _names(desc: BoardDescription, offset: int, op: str | None) -> list[tuple[str, Register]]:
    found = []
    for r in desc.registers:
        span = r.count * (r.width // 8)
        if r.offset <= offset < r.offset + span:
            name = f"{r.name}[{(offset - r.offset) // (r.width // 8)}]" if r.count > 1 else r.name
            found.append((name, r))
    if op is not None:  # the registers this kind of access reaches, if the table says
        wanted = [(n, r) for n, r in found if op[0] in r.access]
        found = wanted or found
    return found


def describe_addr(rack: RackConfig, addr: int, op: str | None = None) -> tuple[str, Register | None]:
    """``"dac CTRL (vmivme4100 at 0xD000+0x00)"`` and the register, for an A16 address."""
    b = board_at(rack, addr)
    if b is None:
        return "no board in the rack", None
    off = addr - b.base
    names = _names(board_description(b.kind), off, op)
    reg_text = "/".join(n for n, _ in names) if names else f"+0x{off:02X} (no register)"
    return f"{b.name} {reg_text} ({b.kind} at 0x{b.base:04X}+0x{off:02X})", (names[0][1] if names else None)


def _fields(reg: Register | None, value: int) -> str:
    if reg is None or not reg.fields:
        return ""
    return "  [" + " ".join(f"{f.name}={f.get(value)}" for f in reg.fields) + "]"


def _default_width(reg: Register | None, addr: int) -> int:
    if reg is not None:
        return reg.width
    return 8 if addr % 2 else 16


def _fmt(value: int, width: int) -> str:
    return f"0x{value:0{width // 4}X} ({value})"


# -- verbs ----------------------------------------------------------------------------------------
def _check_a16(addr: int) -> None:
    if not 0 <= addr <= 0xFFFF:
        raise UsageError(f"address 0x{addr:X} is outside the A16 space 0x0000-0xFFFF")


def cmd_read(args, rack: RackConfig) -> int:
    _check_a16(args.addr)
    where, reg = describe_addr(rack, args.addr, "read")
    width = args.width or _default_width(reg, args.addr)
    bus = open_cli_bus(args.bus, rack)
    try:
        value = bus.read8(args.addr) if width == 8 else bus.read16(args.addr)
    except BusError as err:
        raise with_rack_context(err, rack) from err
    finally:
        close_bus(bus)
    simulated = is_fake_bus(args.bus)
    if args.json:
        doc = {"addr": args.addr, "width": width, "where": where, "value": value,
               "fields": {f.name: f.get(value) for f in reg.fields} if reg is not None and reg.fields else {}}
        if simulated:
            doc["source"] = "simulated rack"
        print_json(doc)
        return 0
    sim = f"  {SIMULATED_READ}" if simulated else ""
    print(f"read{width} 0x{args.addr:04X} {where}: {_fmt(value, width)}{_fields(reg, value)}{sim}")
    return 0


def cmd_write(args, rack: RackConfig) -> int:
    _check_a16(args.addr)
    where, reg = describe_addr(rack, args.addr, "write")
    width = args.width or _default_width(reg, args.addr)
    if not 0 <= args.value < (1 << width):
        raise UsageError(f"value {args.value:#x} does not fit {width} bits (0x{args.addr:04X} {where})")
    if not args.yes_i_know:
        print(f"pfma reg write: refusing to write {_fmt(args.value, width)} to 0x{args.addr:04X} "
              f"{where} without --yes-i-know (a register write can drive real outputs: "
              f"DAC voltages, brakes, the matrix switcher)", file=sys.stderr)
        return 2
    if reg is not None and "w" not in reg.access:
        print(f"note: the register table says {where} is read-only", file=sys.stderr)
    bus = open_cli_bus(args.bus, rack)
    try:
        if width == 8:
            bus.write8(args.addr, args.value)
        else:
            bus.write16(args.addr, args.value)
    except BusError as err:
        raise with_rack_context(err, rack) from err
    finally:
        close_bus(bus)
    simulated = is_fake_bus(args.bus)
    print(f"write{width} 0x{args.addr:04X} {where}: {_fmt(args.value, width)} written"
          + (" (simulated rack)" if simulated else ""))
    if simulated:
        print(f"  {SIMULATED_WRITE}")
    return 0


def cmd_dump(args, rack: RackConfig) -> int:
    try:
        b = rack.board(args.board)
    except KeyError:
        from pfma.errors import did_you_mean
        names = [x.name for x in rack.boards]
        raise UsageError(f"no board named {args.board!r} in rack {rack.name}"
                         + (did_you_mean(args.board, names) or f"; known: {', '.join(names)}")) from None
    desc = board_description(b.kind)
    rows: list[dict] = []
    simulated = is_fake_bus(args.bus)
    if not args.json:
        print(f"{b.name}: {desc.title} at A16 0x{b.base:04X} (window 0x{desc.window:X}, {desc.byte_lanes} lanes)"
              + (f"  {SIMULATED_READ}" if simulated else ""))
    failures = 0
    bus = open_cli_bus(args.bus, rack)
    try:
        for reg in desc.registers:
            if "r" not in reg.access:
                continue
            for i in range(reg.count):
                addr = b.base + reg.addr(i)
                name = f"{reg.name}[{i}]" if reg.count > 1 else reg.name
                try:
                    value = bus.read8(addr) if reg.width == 8 else bus.read16(addr)
                except BusError as err:
                    failures += 1
                    rows.append({"addr": addr, "register": name, "width": reg.width, "value": None,
                                 "error": err.reason})
                    if not args.json:
                        print(f"  0x{addr:04X} {name:<12} read{reg.width:<2} --  {err.reason}")
                    continue
                rows.append({"addr": addr, "register": name, "width": reg.width, "value": value,
                             "fields": {f.name: f.get(value) for f in reg.fields}})
                if not args.json:
                    print(f"  0x{addr:04X} {name:<12} read{reg.width:<2} {_fmt(value, reg.width)}"
                      f"{_fields(reg, value)}")
    finally:
        close_bus(bus)
    if args.json:
        doc = {"board": b.name, "kind": b.kind, "base": b.base, "title": desc.title, "registers": rows,
               "failures": failures}
        if simulated:
            doc["source"] = "simulated rack"
        print_json(doc)
    return 1 if failures else 0


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
