"""Register peek and poke for rack bring-up: the logic of ``pfma reg`` (and the bus opening
``pfma read`` and ``pfma hand`` share): open ``--bus``, name the board and register at an
A16 address, read, write and dump, and each result's text and JSON document. The verb
(:mod:`tools.cli.reg`) parses the options and prints."""

from __future__ import annotations

from dataclasses import dataclass

from drivers.bus import open_bus
from drivers.registers import BoardDescription, Register
from pfma.errors import BusError
from pfma.rack import BoardConfig, RackConfig, board_description

#: what a read or dump of the fake rack adds to its line (``pfma read --bus fake`` says
#: "(simulated rack)" the same way)
SIMULATED_READ = "(simulated rack, power-up state)"
#: the line under a write to the fake rack
SIMULATED_WRITE = ("simulated rack: a fake in this process: nothing real was written, and the value is "
                   "gone when the command ends")


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


def fields_text(reg: Register | None, value: int) -> str:
    if reg is None or not reg.fields:
        return ""
    return "  [" + " ".join(f"{f.name}={f.get(value)}" for f in reg.fields) + "]"


def default_width(reg: Register | None, addr: int) -> int:
    if reg is not None:
        return reg.width
    return 8 if addr % 2 else 16


def value_text(value: int, width: int) -> str:
    return f"0x{value:0{width // 4}X} ({value})"


def check_a16(addr: int) -> None:
    if not 0 <= addr <= 0xFFFF:
        raise UsageError(f"address 0x{addr:X} is outside the A16 space 0x0000-0xFFFF")


# -- read -----------------------------------------------------------------------------------------
def read_register(rack: RackConfig, url: str, addr: int, width: int | None) -> tuple[dict, str]:
    """Read one register: its JSON document (addr, width, where, value, fields, and "source"
    on the simulated rack) and its line.

    :raises UsageError: outside A16, a malformed bus URL
    :raises BusError: the read failed (named by board and register)
    """
    check_a16(addr)
    where, reg = describe_addr(rack, addr, "read")
    width = width or default_width(reg, addr)
    bus = open_cli_bus(url, rack)
    try:
        value = bus.read8(addr) if width == 8 else bus.read16(addr)
    except BusError as err:
        raise with_rack_context(err, rack) from err
    finally:
        close_bus(bus)
    doc = {"addr": addr, "width": width, "where": where, "value": value,
           "fields": {f.name: f.get(value) for f in reg.fields} if reg is not None and reg.fields else {}}
    simulated = is_fake_bus(url)
    if simulated:
        doc["source"] = "simulated rack"
    sim = f"  {SIMULATED_READ}" if simulated else ""
    return doc, f"read{width} 0x{addr:04X} {where}: {value_text(value, width)}{fields_text(reg, value)}{sim}"


# -- write ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Write:
    """One register write, checked (:func:`plan_write`) before it is done."""

    addr: int
    value: int
    width: int
    where: str
    reg: Register | None

    def refusal(self) -> str:
        """Why it is not done without ``--yes-i-know``."""
        return (f"refusing to write {value_text(self.value, self.width)} to 0x{self.addr:04X} "
                f"{self.where} without --yes-i-know (a register write can drive real outputs: "
                f"DAC voltages, brakes, the matrix switcher)")

    def read_only(self) -> bool:
        """Whether the register table says the register is read-only."""
        return self.reg is not None and "w" not in self.reg.access


def plan_write(rack: RackConfig, addr: int, value: int, width: int | None) -> Write:
    """:raises UsageError: outside A16, a value wider than the register"""
    check_a16(addr)
    where, reg = describe_addr(rack, addr, "write")
    width = width or default_width(reg, addr)
    if not 0 <= value < (1 << width):
        raise UsageError(f"value {value:#x} does not fit {width} bits (0x{addr:04X} {where})")
    return Write(addr, value, width, where, reg)


def write_register(rack: RackConfig, url: str, w: Write) -> list[str]:
    """Do the write; the lines that say so.

    :raises UsageError: a malformed bus URL
    :raises BusError: the write failed (named by board and register)
    """
    bus = open_cli_bus(url, rack)
    try:
        if w.width == 8:
            bus.write8(w.addr, w.value)
        else:
            bus.write16(w.addr, w.value)
    except BusError as err:
        raise with_rack_context(err, rack) from err
    finally:
        close_bus(bus)
    simulated = is_fake_bus(url)
    lines = [f"write{w.width} 0x{w.addr:04X} {w.where}: {value_text(w.value, w.width)} written"
             + (" (simulated rack)" if simulated else "")]
    if simulated:
        lines.append(f"  {SIMULATED_WRITE}")
    return lines


# -- dump -----------------------------------------------------------------------------------------
def dump_board_config(rack: RackConfig, name: str) -> BoardConfig:
    """:raises UsageError: no board of that name (the closest named)"""
    try:
        return rack.board(name)
    except KeyError:
        from pfma.errors import did_you_mean
        names = [x.name for x in rack.boards]
        raise UsageError(f"no board named {name!r} in rack {rack.name}"
                         + (did_you_mean(name, names) or f"; known: {', '.join(names)}")) from None


def dump_header(b: BoardConfig, simulated: bool) -> str:
    desc = board_description(b.kind)
    return (f"{b.name}: {desc.title} at A16 0x{b.base:04X} (window 0x{desc.window:X}, {desc.byte_lanes} lanes)"
            + (f"  {SIMULATED_READ}" if simulated else ""))


def dump_rows(rack: RackConfig, url: str, b: BoardConfig):
    """Read every readable register of board ``b``: one row (a dict) and its line each,
    yielded as read; a read that failed has "error" instead of "fields".

    :raises UsageError: a malformed bus URL
    """
    desc = board_description(b.kind)
    bus = open_cli_bus(url, rack)
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
                    yield ({"addr": addr, "register": name, "width": reg.width, "value": None,
                            "error": err.reason}, f"  0x{addr:04X} {name:<12} read{reg.width:<2} --  {err.reason}")
                    continue
                yield ({"addr": addr, "register": name, "width": reg.width, "value": value,
                        "fields": {f.name: f.get(value) for f in reg.fields}},
                       f"  0x{addr:04X} {name:<12} read{reg.width:<2} {value_text(value, reg.width)}"
                       f"{fields_text(reg, value)}")
    finally:
        close_bus(bus)


def dump_doc(b: BoardConfig, rows: list[dict], simulated: bool) -> dict:
    desc = board_description(b.kind)
    doc = {"board": b.name, "kind": b.kind, "base": b.base, "title": desc.title, "registers": rows,
           "failures": sum(1 for r in rows if r["value"] is None)}
    if simulated:
        doc["source"] = "simulated rack"
    return doc
