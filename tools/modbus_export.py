"""Modbus TCP export of the Bit3 buffer, for HMIs and lab tools.

Issue "data-acquisition service", item 5. A :class:`ModbusExport` is a pymodbus
``ModbusTcpServer`` running in its own background thread (own asyncio loop). It is a
reader of the shared memory like any other tool: it never runs inside the service's
hot loop and the service never waits for it (the areas are sequence-locked, so a
reader never blocks the writer).

Register map (generated from the layout by :func:`register_map`; documented in the
generated ``docs/modbus-map.md``, see :func:`modbus_map_markdown`):

- **input registers (fc 4)**: the ``inputs`` area body at IR ``INPUTS_BASE`` (0) and the
  ``stats`` area body at IR ``STATS_BASE`` (8000), every field at
  ``base + body_byte_offset // 2``, values **big-endian** (the Modbus convention, and
  what pymodbus ``convert_from_registers`` decodes by default: most significant word
  first); then one float32 (2 registers) per rack channel at
  IR ``CHANNELS_BASE + 2 * index`` (20000, layout channel order) holding the channel's
  engineering value; and a small identification block at IR ``IDENT_BASE`` (30000).
- **holding registers (fc 3, 6, 16)**: the ``commands`` area body at HR 0, same
  encoding. Reads are always allowed. Writes are refused (exception 1,
  ILLEGAL_FUNCTION) unless the export was started with ``allow_writes=True``; then the
  export holds the controller writer role and every accepted write is one
  ``Client.write_commands`` (heartbeat + 1).

Every read request copies one consistent, seqlocked snapshot of its area
(``AreaReader.read()``) and answers from that copy, so a multi-register value or a
whole 125-register read is never torn.

pymodbus 3.16.1 facts used here (packages.md section 2): live objects are served with
``SimDevice(action=...)`` (legacy datablock subclasses are deep-copied and ignored);
``SimDevice(id=0)`` answers every unit id; an action returning an ``ExcCodes`` member
becomes that exception response; addresses outside every ``SimData`` answer exception 2.
The server-in-a-thread pattern is the one of ``fakes/modbus_gateway.py`` (the service
must not import fakes; both use :class:`drivers.bus.modbus_server.ModbusServerThread`).
"""

from __future__ import annotations

import inspect
import ipaddress
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pymodbus.constants import ExcCodes
from pymodbus.simulator import DataType, SimData, SimDevice

from bit3.client import PRIMARY_FIELD, Client
from bit3.layout import Layout, default_layout
from ioservice.safety import OutputGuard
from bit3.buffer import Bit3Buffer, Bit3Error
from pfma.errors import ConfigError
from drivers.bus.modbus_server import ModbusServerError, ModbusServerThread

__all__ = [
    "CHANNELS_BASE", "COMMANDS_BASE", "IDENT_BASE", "INPUTS_BASE", "MAP_DOC_PATH", "MAP_VERSION",
    "STATS_BASE", "MapRow", "ModbusExport", "ModbusExportError", "ModbusServerThread",
    "map_row", "modbus_map_markdown", "parse_host_port", "register_map",
    "start_export_from_args", "write_modbus_map_doc",
]

log = logging.getLogger(__name__)

#: input-register base of each exported area body (fixed; documented in docs/modbus-map.md)
INPUTS_BASE = 0
STATS_BASE = 8000
#: float32 engineering value of rack channel ``index`` at IR CHANNELS_BASE + 2 * index
CHANNELS_BASE = 20000
#: identification block: layout hash, map version, channel count
IDENT_BASE = 30000
#: holding-register base of the commands area body
COMMANDS_BASE = 0
#: bump when the addressing rules (not the layout) change
MAP_VERSION = 1
#: the channel kinds that are rack channels (in the inputs area), served in the float32 block
CHANNEL_KINDS = ("rtd", "adc", "dac", "pio")
#: command fields the export sets itself; writing them is accepted as a keep-alive only
KEEPALIVE_FIELDS = ("heartbeat", "t_s", "writer_pid", "writer_token")
#: the service's default command watchdog, taken from ioservice/safety.py OutputGuard (the
#: MVME 104's 15 ms, IRSS report 3.4.2) so that the generated map follows the service
SERVICE_WATCHDOG_S: float = inspect.signature(OutputGuard).parameters["watchdog_s"].default
#: Modbus limit on registers per read (fc 3/4)
MAX_READ_REGISTERS = 125
DEFAULT_PORT = 5020
DEFAULT_OWNER = "modbus-export"

MAP_DOC_PATH = Path(__file__).resolve().parent.parent / "docs" / "modbus-map.md"

#: numpy element dtype -> pymodbus DATATYPE name
_MODBUS_TYPE = {"<f8": "FLOAT64", "<f4": "FLOAT32", "<u8": "UINT64", "<i8": "INT64",
                "<u4": "UINT32", "<i4": "INT32", "<u2": "UINT16", "<i2": "INT16",
                "|u1": "UINT8", "|i1": "INT8"}


class ModbusExportError(ModbusServerError):
    """The Modbus export could not start (port in use, bad address, buffer missing)."""


# ----------------------------------------------------------------------------------------
# the register map


@dataclass(frozen=True)
class MapRow:
    """One row of the Modbus register map.

    ``address``/``count`` cover the whole field (all elements); ``base`` is the register
    of the area body's byte 0 and ``byte_offset`` the field's offset in that body.
    """

    table: str  # "input" (fc 4) or "holding" (fc 3, 6, 16)
    address: int
    count: int
    area: str
    name: str  # the field name, or the channel signal in the float32 block
    field: str  # the buffer field served
    index: int | None  # slot of the channel (channel block), else None
    dtype: str  # pymodbus DATATYPE name of one element (UINT8: a byte inside a register)
    shape: tuple[int, ...]
    units: str
    encoding: str
    writable: bool
    doc: str
    base: int = 0
    byte_offset: int = 0

    @property
    def element_registers(self) -> int:
        """Registers per element (0 for UINT8/INT8: two bytes share a register)."""
        return {"FLOAT64": 4, "UINT64": 4, "INT64": 4, "FLOAT32": 2, "UINT32": 2, "INT32": 2,
                "UINT16": 1, "INT16": 1}.get(self.dtype, 0)

    def element(self, i: int = 0) -> tuple[int, int]:
        """``(register, count)`` of element ``i`` (flat index) of this row.

        For a byte-sized element the register holds it in its high byte when its
        byte offset is even, in its low byte when odd (see :meth:`byte_in_register`).
        """
        n = int(np.prod(self.shape, dtype=np.int64)) if self.shape else 1
        if not 0 <= i < n:
            raise IndexError(f"Modbus map: {self.name} has {n} elements, not index {i}")
        k = self.element_registers
        if k:
            return self.address + i * k, k
        return self.base + (self.byte_offset + i) // 2, 1

    def byte_in_register(self, i: int = 0) -> str:
        """``"high"``/``"low"``: where byte-sized element ``i`` sits in its register."""
        return "high" if (self.byte_offset + i) % 2 == 0 else "low"


def _encoding(dtype: str, shape: tuple[int, ...], byte_offset: int) -> str:
    t = _MODBUS_TYPE[dtype]
    k = {"FLOAT64": 4, "UINT64": 4, "INT64": 4, "UINT32": 2, "INT32": 2, "FLOAT32": 2}.get(t, 1)
    if t in ("UINT8", "INT8"):
        where = "high" if byte_offset % 2 == 0 else "low"
        if shape:
            return f"bytes in buffer order, 2 per register, element 0 in the {where} byte"
        return f"{where} byte of the register"
    if k == 1:
        return "1 register" + ("/element" if shape else "")
    return f"{k} registers{'/element' if shape else ''}, most significant word first"


def _field_rows(layout: Layout, area: str, base: int, table: str) -> list[MapRow]:
    a = layout.area(area)
    rows = []
    for f in layout.fields:
        if f.area != area:
            continue
        off = f.offset - a.body_offset
        first = base + off // 2
        last = base + (off + f.nbytes - 1) // 2
        writable = table == "holding" and f.name not in KEEPALIVE_FIELDS
        doc = f.doc
        if table == "holding" and f.name in KEEPALIVE_FIELDS:
            doc += "; set by the export: a write is accepted as a keep-alive, its value ignored"
        rows.append(MapRow(table, first, last - first + 1, area, f.name, f.name, None,
                           _MODBUS_TYPE[f.dtype], tuple(f.shape), f.units,
                           _encoding(f.dtype, f.shape, off), writable, doc, base, off))
    return rows


def _rack_channels(layout: Layout) -> list:
    return [c for c in layout.channels if c.area == "inputs" and c.kind in CHANNEL_KINDS]


def register_map(layout: Layout | None = None) -> list[MapRow]:
    """Every row of the Modbus map, derived from the Bit3 layout (deterministic).

    Order: inputs fields (IR), stats fields (IR), per-channel float32 block (IR),
    identification block (IR), commands fields (HR).
    """
    lay = layout or default_layout()
    rows = _field_rows(lay, "inputs", INPUTS_BASE, "input")
    rows += _field_rows(lay, "stats", STATS_BASE, "input")
    for i, c in enumerate(_rack_channels(lay)):
        fname = PRIMARY_FIELD[c.kind]
        where = f"{c.board}/{c.channel}" if c.channel >= 0 else c.board
        rows.append(MapRow("input", CHANNELS_BASE + 2 * i, 2, "inputs", c.name, fname, c.slot,
                           "FLOAT32", (), c.units,
                           f"float32 of {fname}[{c.slot}], most significant word first", False,
                           f"{c.label} ({where}){' (spare)' if c.spare else ''}",
                           CHANNELS_BASE, 4 * i))
    rows += [
        MapRow("input", IDENT_BASE, 4, "header", "layout_hash", "layout_hash", None, "UINT8",
               (8,), "", "the 8 hash bytes in buffer order, 2 per register, first in the high byte",
               False, f"Bit3 layout hash ({lay.hash_hex} for this map)", IDENT_BASE, 0),
        MapRow("input", IDENT_BASE + 4, 1, "-", "map_version", "", None, "UINT16", (), "1",
               "1 register", False, f"Modbus addressing rules version ({MAP_VERSION})",
               IDENT_BASE, 8),
        MapRow("input", IDENT_BASE + 5, 1, "-", "channel_count", "", None, "UINT16", (), "1",
               "1 register", False, "entries in the float32 channel block", IDENT_BASE, 10),
    ]
    rows += _field_rows(lay, "commands", COMMANDS_BASE, "holding")
    return rows


def map_row(rows: list[MapRow], name: str, table: str | None = None,
            area: str | None = None) -> MapRow:
    """The first row named ``name`` (a field or a channel signal) in ``rows``.

    A name that is both a field and a channel signal (none in the default rack) is
    found as the field first; give ``table``/``area`` to disambiguate.
    """
    for r in rows:
        if r.name == name and (table is None or r.table == table) and (area is None or r.area == area):
            return r
    raise KeyError(f"no Modbus map row {name!r}"
                   f"{' in ' + table + ' registers' if table else ''}"
                   f"{' of area ' + area if area else ''}")


def _md(s: str) -> str:
    return s.replace("|", "/")


def modbus_map_markdown(layout: Layout | None = None) -> str:
    """The text of ``docs/modbus-map.md`` (generated; a test compares the file with it)."""
    lay = layout or default_layout()
    rows = register_map(lay)
    ins, sts, cmd = (lay.area(n) for n in ("inputs", "stats", "commands"))
    n_ch = len(_rack_channels(lay))
    wd_ms = SERVICE_WATCHDOG_S * 1e3
    out = [
        "# Modbus TCP map of the Bit3 buffer",
        "",
        "<!-- GENERATED by tools.modbus_export.modbus_map_markdown(); do not edit. Regenerate: "
        "python -c \"from tools.modbus_export import write_modbus_map_doc; "
        "write_modbus_map_doc()\" -->",
        "",
        f"Rack `{lay.rack_name}`, Bit3 layout version {lay.version}, layout hash "
        f"`{lay.hash_hex}`, Modbus map version {MAP_VERSION}. The byte layout itself is in "
        "[bit3-layout.md](bit3-layout.md); this map is derived from the same layout "
        "(`tools.modbus_export.register_map()`).",
        "",
        "## Server",
        "",
        f"- `pfma serve --modbus HOST:PORT` (or `tools.modbus_export.ModbusExport`); default "
        f"127.0.0.1:{DEFAULT_PORT}. It listens on loopback only unless another host address "
        "is given.",
        "- Every unit id is answered (pymodbus catch-all device 0).",
        "- The export is a separate thread that reads the shared memory like any other "
        "tool; the I/O service's loop never waits for it.",
        "- Every read request copies **one consistent snapshot** of the area it reads "
        "(sequence lock) and answers from that copy: a multi-register value, or a whole "
        "read of up to 125 registers, is never torn. Registers of one request always "
        "come from one area, because different areas are separated by unmapped "
        "addresses. The identification block is constant.",
        "- Function codes: 4 (read input registers), 3 (read holding registers), 6 and 16 "
        "(write holding registers, only with writes enabled). Any other function code "
        "answers exception 1 (ILLEGAL_FUNCTION).",
        "- Unmapped addresses answer exception 2 (ILLEGAL_ADDRESS). A reader that cannot "
        "get a stable copy within 0.1 s (writer stuck) gets exception 4 (DEVICE_FAILURE).",
        "",
        "## Encoding",
        "",
        "- The buffer is little-endian; Modbus is big-endian. Every field element is served "
        "big-endian, **most significant word first** -- what pymodbus "
        "`client.convert_from_registers(regs, client.DATATYPE.FLOAT64)` decodes with its "
        "default `word_order=\"big\"`.",
        "- An area body's byte `b` is in register `base + b // 2`; so a field at body "
        "offset `o` starts at register `base + o // 2` and element `i` of an array field "
        "at `address + i * registers_per_element`.",
        "- Byte-sized fields (UINT8, e.g. flags) share a register with their neighbour "
        "byte: the byte at an even body offset is the register's high byte, the one at "
        "an odd offset its low byte. Padding bytes read 0.",
        "- No scaling: values are the buffer's own numbers in the units given. The channel "
        "block rounds each float64 engineering value to float32 (about 7 significant "
        "digits).",
        "",
        "## Blocks",
        "",
        "| table | first register | registers | contents |",
        "|---|---:|---:|---|",
        f"| input (fc 4) | {INPUTS_BASE} | {ins.body_size // 2} | `inputs` area body "
        f"({ins.body_size} bytes; fields below) |",
        f"| input (fc 4) | {STATS_BASE} | {sts.body_size // 2} | `stats` area body "
        f"({sts.body_size} bytes; fields below) |",
        f"| input (fc 4) | {CHANNELS_BASE} | {2 * n_ch} | float32 engineering value of each "
        f"of the {n_ch} rack channels, `{CHANNELS_BASE} + 2 * index` |",
        f"| input (fc 4) | {IDENT_BASE} | 6 | identification |",
        f"| holding (fc 3/6/16) | {COMMANDS_BASE} | {cmd.body_size // 2} | `commands` area "
        f"body ({cmd.body_size} bytes; fields below) |",
        "",
        "## Writing commands (holding registers)",
        "",
        "Writes are **refused with exception 1 (ILLEGAL_FUNCTION) unless the export was "
        "started with writes enabled** (`ModbusExport(..., allow_writes=True)`; "
        "`pfma serve` passes its own option through). With writes enabled the export claims the buffer's "
        f"`controller` writer role as `{DEFAULT_OWNER}` (it fails to start, naming the "
        "owner, when a controller already holds it), and every accepted write request is "
        "applied to its command record and published at once, with the command "
        "`heartbeat` incremented by one (`t_s` stamped). Rules:",
        "",
        "- A write must cover whole elements: writing part of a float64 (fewer than its 4 "
        "registers) or a register holding no command field answers exception 2; a "
        "non-finite float answers exception 3 (ILLEGAL_VALUE). Nothing is applied then.",
        "- `heartbeat` and `t_s` are set by the export; writing them (any value) is "
        "accepted as a keep-alive: it publishes the command record again with the "
        "heartbeat incremented.",
        "- Use function code 16 to write a multi-register value in one request.",
        "",
        f"**Watchdog.** When the service is ARMED it trips the outputs to 0 V (FAULT; brakes "
        f"set) if the command heartbeat does not change for longer than its watchdog, "
        f"{wd_ms:.0f} ms by default (the MVME 104's; `ioservice/safety.py`). A Modbus HMI that commands the arm "
        f"must therefore write (for example the heartbeat register) at least every "
        f"{wd_ms:.0f} ms, with every request answered in time, for as long as the arm is "
        "armed. A Modbus/TCP round trip on a plant network does not reliably meet that. "
        "**In practice, Modbus command writes are for `matrix_route` and low-rate lab use "
        "with the arm not armed; drive the arm from a controller process that uses "
        "`bit3.client` directly.**",
        "",
    ]

    def table(title: str, sel: list[MapRow], note: str = "") -> None:
        out.extend([f"## {title}", ""] + ([note, ""] if note else []) + [
            "| register | count | name | type | shape | units | encoding | meaning |",
            "|---:|---:|---|---|---|---|---|---|"])
        for r in sel:
            shape = "" if not r.shape else "[" + ",".join(map(str, r.shape)) + "]"
            out.append(f"| {r.address} | {r.count} | {r.name} | {r.dtype} | {shape} | "
                       f"{_md(r.units)} | {r.encoding} | {_md(r.doc)} |")
        out.append("")

    table(f"Input registers: `inputs` area (IR {INPUTS_BASE}+)",
          [r for r in rows if r.table == "input" and r.area == "inputs" and r.index is None],
          "Array fields hold one element per slot; which slot is which channel is listed in "
          "bit3-layout.md (Channels) and, for rack channels, in the float32 block below.")
    table(f"Input registers: `stats` area (IR {STATS_BASE}+)",
          [r for r in rows if r.table == "input" and r.area == "stats"],
          "Device-group slots (`device_*` arrays) in this order: "
          + ", ".join(c.name for c in lay.channels if c.kind == "device") + ".")
    out += [f"## Input registers: rack channels as float32 (IR {CHANNELS_BASE}+)", "",
            "Each rack channel's engineering value (the same number as "
            "`Client.read_inputs().<signal>`), in layout channel order, 2 registers each.", "",
            "| register | signal | source field[slot] | units | channel |",
            "|---:|---|---|---|---|"]
    for r in rows:
        if r.table == "input" and r.base == CHANNELS_BASE:
            out.append(f"| {r.address} | {r.name} | {r.field}[{r.index}] | {_md(r.units)} | "
                       f"{_md(r.doc)} |")
    out.append("")
    table(f"Input registers: identification (IR {IDENT_BASE}+)",
          [r for r in rows if r.base == IDENT_BASE],
          "Check the layout hash before trusting this map: a different rack file changes "
          "the channel names and slots.")
    table(f"Holding registers: `commands` area (HR {COMMANDS_BASE}+)",
          [r for r in rows if r.table == "holding"],
          "Command channel order (joints, limits) is listed in bit3-layout.md (Channels, "
          "area commands).")
    return "\n".join(out)


def write_modbus_map_doc(path: str | Path = MAP_DOC_PATH, layout: Layout | None = None) -> Path:
    """Write the generated document (default ``docs/modbus-map.md``)."""
    p = Path(path)
    p.write_text(modbus_map_markdown(layout))
    return p


# ----------------------------------------------------------------------------------------
# area encoders


def _swap_permutation(layout: Layout, area: str) -> np.ndarray:
    """Byte index array turning the area body little-endian <-> big-endian (an involution).

    Every element of 2 bytes or more has its bytes reversed; single bytes and padding
    stay in place.
    """
    a = layout.area(area)
    perm = np.arange(a.body_size, dtype=np.intp)
    for f in layout.fields:
        if f.area != area:
            continue
        size = f.np_dtype.itemsize
        if size < 2:
            continue
        off = f.offset - a.body_offset
        n = f.nbytes // size
        starts = off + size * np.arange(n)
        perm[(starts[:, None] + np.arange(size)[None, :]).ravel()] = \
            (starts[:, None] + np.arange(size - 1, -1, -1)[None, :]).ravel()
    return perm


class _AreaView:
    """A reader of one area that hands out big-endian registers of a consistent copy."""

    def __init__(self, buf: Bit3Buffer, area: str) -> None:
        self.reader = buf.reader(area)
        self.perm = _swap_permutation(buf.layout, area)
        self._bytes = np.frombuffer(self.reader.raw, dtype=np.uint8)

    def registers(self) -> np.ndarray:
        """Read one snapshot; return the whole body as big-endian 16-bit words."""
        self.reader.read()
        return self._bytes[self.perm].view(">u2")


# ----------------------------------------------------------------------------------------
# the server thread (same approach as fakes/modbus_gateway.py)


# ----------------------------------------------------------------------------------------
# the export


_READS = {3, 4}
_WRITES = {6, 16}


class ModbusExport:
    """Serve the Bit3 buffer over Modbus TCP (see the module docstring and modbus-map.md).

    :param buffer: shared-memory name (``"pfma"``) or an open :class:`Bit3Buffer`
        (kept open by the caller; the export only reads through it)
    :param host: address to bind; loopback unless told otherwise
    :param port: TCP port (``0``: ephemeral, see :attr:`port` after :meth:`start`)
    :param allow_writes: accept holding-register writes; claims the ``controller`` role
    :param owner: owner name written into the command area's owner slot
    :param device_id: unit id to answer; 0 (default) answers every unit id
    :param layout: layout of a buffer given by name (default: the default rack's)
    """

    def __init__(self, buffer: str | Bit3Buffer = "pfma", host: str = "127.0.0.1",
                 port: int = DEFAULT_PORT, allow_writes: bool = False, *,
                 owner: str = DEFAULT_OWNER, device_id: int = 0,
                 layout: Layout | None = None) -> None:
        if not 0 <= int(port) <= 65535:
            raise ConfigError(f"Modbus export: port {port} out of range 0..65535")
        if not 0 <= int(device_id) <= 255:
            raise ConfigError(f"Modbus export: unit id {device_id} out of range 0..255")
        self._given = buffer if isinstance(buffer, Bit3Buffer) else None
        self.buffer_name = buffer.name if isinstance(buffer, Bit3Buffer) else str(buffer)
        self.layout = buffer.layout if isinstance(buffer, Bit3Buffer) else (layout or default_layout())
        self.host = host
        self.allow_writes = bool(allow_writes)
        self.owner = owner
        self.device_id = int(device_id)
        self.rows = register_map(self.layout)
        self.requests = 0
        self.writes = 0
        self.refused = 0
        self._port = int(port)
        self._buf: Bit3Buffer | None = None
        self._client: Client | None = None
        self._views: dict[str, _AreaView] = {}
        self._server: ModbusServerThread | None = None
        self._build_tables()

    # -- static tables derived from the layout --------------------------------------------
    def _build_tables(self) -> None:
        lay = self.layout
        self._ir_areas = [(INPUTS_BASE, lay.area("inputs").body_size // 2, "inputs"),
                          (STATS_BASE, lay.area("stats").body_size // 2, "stats")]
        chans = _rack_channels(lay)
        self._n_channels = len(chans)
        self._chan_fields: list[tuple[str, np.ndarray, np.ndarray]] = []
        by_field: dict[str, tuple[list[int], list[int]]] = {}
        for i, c in enumerate(chans):
            idx, slots = by_field.setdefault(PRIMARY_FIELD[c.kind], ([], []))
            idx.append(i)
            slots.append(c.slot)
        for f, (idx, slots) in by_field.items():
            self._chan_fields.append((f, np.array(idx, dtype=np.intp), np.array(slots, dtype=np.intp)))
        self._chan_values = np.zeros(self._n_channels, dtype=np.float64)
        ident = np.frombuffer(lay.hash.ljust(8, b"\0")[:8], dtype=">u2").tolist()
        self._ident = ident + [MAP_VERSION, self._n_channels]
        # holding registers: which element (register span) each register belongs to
        cmd = lay.area("commands")
        n = cmd.body_size // 2
        self._hr_count = n
        self._hr_lo = np.full(n, -1, dtype=np.int64)  # -1: no command field in this register
        self._hr_hi = np.full(n, -1, dtype=np.int64)
        self._hr_fields: dict[int, set[str]] = {}
        for f in lay.fields:
            if f.area != "commands":
                continue
            off = f.offset - cmd.body_offset
            size = f.np_dtype.itemsize
            for e in range(f.nbytes // size):
                b0 = off + e * size
                lo, hi = b0 // 2, (b0 + size - 1) // 2
                for r in range(lo, hi + 1):
                    self._hr_lo[r] = lo if self._hr_lo[r] < 0 else min(lo, self._hr_lo[r])
                    self._hr_hi[r] = max(hi, self._hr_hi[r])
                    self._hr_fields.setdefault(r, set()).add(f.name)
        self._cmd_perm = _swap_permutation(lay, "commands")
        self._cmd_dtype = cmd.body_dtype

    def _device(self) -> SimDevice:
        bits = [SimData(address=0, count=1, values=False, datatype=DataType.BITS)]
        ir = [SimData(address=base, count=n, values=0, datatype=DataType.REGISTERS)
              for base, n, _ in self._ir_areas]
        ir.append(SimData(address=CHANNELS_BASE, count=max(2 * self._n_channels, 1), values=0,
                          datatype=DataType.REGISTERS))
        ir.append(SimData(address=IDENT_BASE, count=len(self._ident), values=0,
                          datatype=DataType.REGISTERS))
        hr = [SimData(address=COMMANDS_BASE, count=self._hr_count, values=0,
                      datatype=DataType.REGISTERS)]
        return SimDevice(id=self.device_id, simdata=(bits, list(bits), hr, ir), action=self._action)

    # -- life cycle -------------------------------------------------------------------------
    @property
    def port(self) -> int:
        """The TCP port (the bound one after :meth:`start`)."""
        return self._server.port if self._server is not None else self._port

    @property
    def running(self) -> bool:
        return self._server is not None and self._server.running

    def start(self, timeout_s: float = 5.0) -> "ModbusExport":
        """Attach to the buffer (claim ``controller`` if writes are allowed) and listen.

        :raises OwnershipError: writes allowed and a controller already owns the commands
            (the message names it)
        :raises Bit3Error: no such buffer, or layout mismatch
        :raises ModbusExportError: the port could not be bound
        """
        if self._server is not None:
            raise ModbusExportError("Modbus export already started")
        try:
            if self._given is not None:
                self._buf = self._given
            else:
                self._buf = Bit3Buffer.attach(self.buffer_name, readonly=True, layout=self.layout)
            if self.allow_writes:
                path = self.buffer_name if "/" in self.buffer_name else None  # file window
                self._client = Client.attach(self.buffer_name, writer="commands", owner=self.owner,
                                             layout=self.layout, path=path)
            self._views = {n: _AreaView(self._buf, n) for n in ("inputs", "stats", "commands")}
            server = ModbusServerThread(self._device, self.host, self._port, error=ModbusExportError,
                                        name=f"modbus-export-{self.buffer_name}")
            server.start(timeout_s)
            self._server = server
        except BaseException:
            self._close_buffers()
            raise
        log.info("Modbus export of Bit3 buffer %s on %s:%d (writes %s)", self.buffer_name,
                 self.host, self.port, "allowed" if self.allow_writes else "refused")
        if self.allow_writes and not _is_loopback(self.host):
            log.warning("Modbus export on %s:%d accepts command writes from the network "
                        "(no authentication in Modbus TCP)", self.host, self.port)
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop serving, release the controller role (if held) and detach."""
        server, self._server = self._server, None
        if server is not None:
            self._port = server.port
            server.stop(timeout_s)
        self._close_buffers()

    def _close_buffers(self) -> None:
        self._views = {}
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._buf is not None and self._buf is not self._given:
            self._buf.close()
        self._buf = None

    def __enter__(self) -> "ModbusExport":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def __repr__(self) -> str:
        return (f"<ModbusExport {self.buffer_name} {self.host}:{self.port} "
                f"writes={'on' if self.allow_writes else 'off'} "
                f"{'running' if self.running else 'stopped'}>")

    # -- the action pymodbus calls for every register request -------------------------------
    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      current_registers: list[int], set_values) -> ExcCodes | None:
        self.requests += 1
        if function_code not in _READS | _WRITES:
            self.refused += 1
            return ExcCodes.ILLEGAL_FUNCTION
        if function_code in _WRITES:
            if set_values is None:
                # pymodbus reads the block back to build the fc 6 echo: leave it as written
                return None
            if not self.allow_writes or self._client is None:
                self.refused += 1
                return ExcCodes.ILLEGAL_FUNCTION
            return self._write(address, [int(v) & 0xFFFF for v in set_values])
        off = address - start_address
        try:
            regs = self._read(function_code, address, count)
        except Bit3Error:  # SeqLockTimeout: writer stuck mid-write
            return ExcCodes.DEVICE_FAILURE
        if regs is None:
            return ExcCodes.ILLEGAL_ADDRESS
        current_registers[off:off + count] = regs
        return None

    def _read(self, function_code: int, address: int, count: int) -> list[int] | None:
        """Registers ``address .. address+count-1`` from one snapshot, or None if unmapped."""
        end = address + count
        if function_code == 3:
            if COMMANDS_BASE <= address and end <= COMMANDS_BASE + self._hr_count:
                regs = self._views["commands"].registers()
                return regs[address - COMMANDS_BASE:end - COMMANDS_BASE].tolist()
            return None
        for base, n, area in self._ir_areas:
            if base <= address and end <= base + n:
                return self._views[area].registers()[address - base:end - base].tolist()
        if CHANNELS_BASE <= address and end <= CHANNELS_BASE + 2 * self._n_channels:
            return self._channel_registers()[address - CHANNELS_BASE:end - CHANNELS_BASE].tolist()
        if IDENT_BASE <= address and end <= IDENT_BASE + len(self._ident):
            return self._ident[address - IDENT_BASE:end - IDENT_BASE]
        return None

    def _channel_registers(self) -> np.ndarray:
        view = self._views["inputs"]
        view.reader.read()
        rec = view.reader.record
        vals = self._chan_values
        for fname, idx, slots in self._chan_fields:
            vals[idx] = rec[fname][slots]
        with np.errstate(over="ignore"):
            return vals.astype(">f4").view(">u2")

    def _write(self, address: int, values: list[int]) -> ExcCodes | None:
        """Apply one write request to the command record and publish it (heartbeat + 1)."""
        lo = address - COMMANDS_BASE
        hi = lo + len(values)  # exclusive
        if lo < 0 or hi > self._hr_count:
            self.refused += 1
            return ExcCodes.ILLEGAL_ADDRESS
        span_lo = self._hr_lo[lo:hi]
        span_hi = self._hr_hi[lo:hi]
        if (span_lo < 0).any() or (span_lo < lo).any() or (span_hi >= hi).any():
            self.refused += 1  # a register with no command field, or part of an element
            return ExcCodes.ILLEGAL_ADDRESS
        client = self._client
        rec = client.command
        le = np.frombuffer(rec.tobytes(), dtype=np.uint8)
        be = le[self._cmd_perm]
        be[2 * lo:2 * hi] = np.array(values, dtype=">u2").view(np.uint8)
        new = np.ndarray((), self._cmd_dtype, buffer=be[self._cmd_perm].tobytes())
        names: set[str] = set()
        for r in range(lo, hi):
            names |= self._hr_fields[r]
        fields = {n: (new[n].item() if new[n].ndim == 0 else new[n].copy())
                  for n in sorted(names) if n not in KEEPALIVE_FIELDS}
        try:
            if fields:
                client.write_commands(**fields)
            else:
                client.publish_commands()
        except Bit3Error as err:  # not finite, out of range: nothing applied
            self.refused += 1
            log.warning("Modbus write HR %d..%d refused: %s", address, address + len(values) - 1, err)
            return ExcCodes.ILLEGAL_VALUE
        self.writes += 1
        return None


# ----------------------------------------------------------------------------------------
# command-line helper


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def parse_host_port(host_port: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``"HOST:PORT"``, ``":PORT"``, ``"PORT"`` or ``"[v6addr]:PORT"`` -> (host, port)."""
    s = host_port.strip()
    host, port_s = default_host, s
    if s.startswith("["):
        end = s.find("]")
        if end < 0 or not s[end + 1:].startswith(":"):
            raise ConfigError(f"--modbus {host_port!r}: expected [IPv6]:PORT")
        host, port_s = s[1:end], s[end + 2:]
    elif ":" in s:
        h, _, port_s = s.rpartition(":")
        host = h or default_host
    try:
        port = int(port_s)
    except ValueError:
        raise ConfigError(f"--modbus {host_port!r}: expected HOST:PORT with a numeric port, "
                          f"e.g. 127.0.0.1:{DEFAULT_PORT}") from None
    if not 0 <= port <= 65535:
        raise ConfigError(f"--modbus {host_port!r}: port {port} out of range 0..65535")
    return host, port


def start_export_from_args(buffer_name: str, host_port: str, allow_writes: bool) -> ModbusExport:
    """Parse ``HOST:PORT`` and start a :class:`ModbusExport` (for ``pfma serve --modbus``).

    The caller stops it (``export.stop()``) when the service stops.
    """
    host, port = parse_host_port(host_port)
    return ModbusExport(buffer_name, host=host, port=port, allow_writes=allow_writes).start()
