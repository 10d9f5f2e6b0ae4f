"""Modbus TCP export of the Bit3 buffer, for HMIs and lab tools.

Issue "data-acquisition service", item 5; hardened in issue 20 item 2. A
:class:`ModbusExport` serves the buffer from an asyncio loop in its own thread; ``pfma
serve --modbus`` runs it in **its own process** (:class:`ExportProcess`, ``python -m
tools.modbus_export``), so Modbus clients never compete with the acquisition loop for
the service's interpreter. It is a reader of the shared memory like any other tool: the
service never waits for it (the areas are sequence-locked, so a reader never blocks the
writer).

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
  export holds the controller writer role and accepts writes of :data:`REQUEST_FIELDS`
  only (the camera route, checked against the route table) and keep-alives, each one
  ``Client.write_commands`` (heartbeat + 1). It **never arms or drives motion** (issue 28
  item 6): its command record holds the safe command (no arm request, rates 0, current
  limits 0: brakes set, gripper 0), and a write touching any other field answers
  exception 2 (ILLEGAL_ADDRESS), counted and logged like every refusal.
- **every other function code** (0..255) answers exception 1.

Every read request copies one consistent, seqlocked snapshot of its area
(``AreaReader.read()``) and answers from that copy, so a multi-register value or a
whole 125-register read is never torn.

**The server is this module's own Modbus TCP framing** (function codes 3, 4, 6, 16 need
little), not pymodbus's ``ModbusTcpServer``: pymodbus 3.16.1's server answers function
codes 7, 8, 11, 12, 17, 20, 21, 24 and 43 itself (its built-in diagnostics; the
``SimDevice`` action never sees them), logs a ~14-line traceback for every request of
function code 0x81-0xFF, and answers only the first of two requests that arrive in one
TCP segment (issue 20 measured all three). Here every request is framed by its MBAP
length, answered in order (pipelined requests too), and bounded by
:class:`ExportLimits` (connections, per-connection buffers, idle time-out); refused
requests are counted and said in one log line per minute at most (:class:`RefusalLog`),
never a traceback. Frame sizes are the Modbus application protocol's: a PDU of at most
253 bytes (MBAP length field <= 254), reads of 1..125 registers, writes of 1..123.
Tests and the HMI side use the pymodbus client.
"""

from __future__ import annotations

import asyncio
import inspect
import ipaddress
import logging
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any
from pathlib import Path

import numpy as np

from bit3.client import PRIMARY_FIELD, Client
from bit3.layout import Layout, default_layout
from controller.routes import ALL_ROUTES
from ioservice.safety import OutputGuard
from bit3.buffer import Bit3Buffer, Bit3Error
from pfma.errors import ConfigError, PfmaError
from pfma.process import NO_WORD, bring_up, set_parent_death_signal, spawn_helper, stop_helper
from pfma.refusals import RefusalLog

__all__ = [
    "CHANNELS_BASE", "COMMANDS_BASE", "IDENT_BASE", "INPUTS_BASE", "MAP_DOC_PATH", "MAP_VERSION",
    "STATS_BASE", "ExportLimits", "ExportProcess", "MapRow", "ModbusExport", "ModbusExportError",
    "refusal_log", "main", "map_row", "modbus_map_markdown", "parse_host_port", "register_map",
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
#: the requests a Modbus master may write (writes enabled): the camera route, a value of the
#: route table (controller/routes.py ALL_ROUTES), which the service's PIO task applies. No
#: field that arms or moves the arm is here: Modbus TCP has no authentication and its port
#: is reachable by every local user (issue 28 item 6)
REQUEST_FIELDS = ("matrix_route",)
#: holding registers of the requests to a running controller (``requests_wm``): HR 9000 the
#: request (``controller.layers.Request``), 9001 its argument; read back: 9000-9001 the last
#: request written and its argument, 9002 the number it was posted under (low 16 bits),
#: 9003 the controller's answer to the newest request (``Response``: 0 none, 1 IN PROGRESS,
#: 2 COMPLETE, 3 REFUSED, 4 FAILED, 5 QUEUED, 6 CANCELLED), 9004 the number that answer is
#: for (low 16 bits)
REQUESTS_BASE = 9000
REQUEST_REGISTERS = 5
#: the requests a Modbus master may post to the controller: HALT (outputs 0 V, brakes set)
#: and CAMERA ROUTE (argument monitor * 16 + camera). Not POWER UP, SINGLE STEP, RESUME
#: (they arm or move the arm), ERROR RESET or POWER DOWN (they start sequences of the
#: controller's): issue 28 item 6, the export never arms or drives motion
MODBUS_REQUESTS = {4: "HALT", 7: "CAMERA ROUTE"}
#: what the export's command record holds apart from the requests: the safe command (no arm
#: request, every rate 0, every current limit 0 = brakes set, gripper 0), so the service
#: stays SAFE while the export holds the command area
SAFE_COMMAND = {"arm_request": 0, "joint_rate_rad_s": 0.0, "current_limit_a": 0.0, "gripper": 0.0,
                "mode": 0, "crl_reflect_enable": 0, "crl_reflect_force_n": 0.0, "crl_reflect_torque_nm": 0.0}
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


class ModbusExportError(PfmaError):
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
        writable = table == "holding" and f.name in REQUEST_FIELDS
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
        "- Every unit id is answered (the export's default device id 0 answers any).",
        "- `pfma serve --modbus` runs the export in its own process (`python -m "
        "tools.modbus_export`, at a lower priority than the service), a reader of the shared "
        "memory like any other tool; the I/O service's loop never waits for it.",
        "- Limits (defaults; flags of `python -m tools.modbus_export`): "
        f"{ExportLimits().max_connections} connections at once (one more is closed at once), "
        f"{ExportLimits().in_buffer_bytes} bytes of unanswered requests and "
        f"{ExportLimits().out_buffer_bytes} bytes of untaken answers per connection (a client "
        "that does not read its answers is not read either), a connection silent (or not "
        f"reading) for {ExportLimits().idle_timeout_s:g} s is closed. Requests sent back to "
        "back without waiting (pipelined) are all answered, in order.",
        "- Every read request copies **one consistent snapshot** of the area it reads "
        "(sequence lock) and answers from that copy: a multi-register value, or a whole "
        "read of up to 125 registers, is never torn. Registers of one request always "
        "come from one area, because different areas are separated by unmapped "
        "addresses. The identification block is constant.",
        "- Function codes: 4 (read input registers), 3 (read holding registers), 6 and 16 "
        "(write holding registers, only with writes enabled). Any other function code "
        "(0-255, diagnostics such as 8 and 43 included) answers exception 1 (ILLEGAL_FUNCTION). "
        "A request of one of these codes with a wrong length, a count of 0 or more than 125 "
        "(123 for writes) answers exception 3 (ILLEGAL_DATA_VALUE). A malformed MBAP header "
        "(length field below 2 or above 254) closes the connection; a protocol id other "
        "than 0 is not answered. Refused requests are counted and logged in one line per "
        "minute at most.",
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
        f"| holding (fc 3/6/16) | {REQUESTS_BASE} | {REQUEST_REGISTERS} | requests to the controller "
        "(only with `--modbus-requests WM`; below) |",
        "",
        "## Requests to the controller (holding registers 9000-9004)",
        "",
        "With `pfma serve --modbus --modbus-requests WM` (`ModbusExport(..., allow_writes=True, "
        "requests_wm=WM)`, WM the running controller's world model) a Modbus master posts "
        "**requests** to the controller, which validates and answers them as it does the "
        "console's (System Up/Down, docs/console.md); the export does not claim the command "
        "area (the controller holds it), and every write to it answers exception 2.",
        "",
        "| register | UINT16 | write | read |",
        "|---:|---|---|---|",
        f"| {REQUESTS_BASE} | request | posts the request (fc 6 alone, with the argument written "
        f"before; or fc 16 with the argument in {REQUESTS_BASE + 1}) | the last request posted |",
        f"| {REQUESTS_BASE + 1} | argument | kept for the next request | its argument |",
        f"| {REQUESTS_BASE + 2} | number | | the number it was posted under (low 16 bits) |",
        f"| {REQUESTS_BASE + 3} | answer | | the controller's answer to its newest request: 0 none "
        "yet, 1 IN PROGRESS, 2 COMPLETE, 3 REFUSED, 4 FAILED, 5 QUEUED, 6 CANCELLED |",
        f"| {REQUESTS_BASE + 4} | answered | | the number that answer is for (low 16 bits) |",
        "",
        "Requests taken: " + ", ".join(f"**{k} {n}**" for k, n in MODBUS_REQUESTS.items()) + " "
        "(argument monitor x 16 + camera, 0 = blank; docs/cameras.md). Any other request, "
        "among them 1 POWER UP, 5 SINGLE STEP and 6 RESUME (they arm or move the arm), 3 ERROR "
        "RESET and 2 POWER DOWN, answers exception 3 and is not posted. No running controller "
        "(no world model, or its owner gone): exception 4, one log line. The world model's "
        "access key is `$PFMA_WM_KEY` or the default one, as for `pfma controller halt`.",
        "",
        "## Camera-route writes without a controller (`--modbus-writes`)",
        "",
        "Writes are **refused with exception 1 (ILLEGAL_FUNCTION) unless the export was "
        "started with writes enabled** (`ModbusExport(..., allow_writes=True)`; "
        "`pfma serve --modbus-writes`). With writes enabled the export claims the buffer's "
        f"`controller` writer role as `{DEFAULT_OWNER}` (it fails to start, naming the "
        "owner, when a controller already holds it), and every accepted write request is "
        "applied to its command record and published at once, with the command "
        "`heartbeat` incremented by one (`t_s` stamped).",
        "",
        "**The export never arms the arm or drives motion** (a Modbus TCP port has no "
        "authentication; on loopback every local user reaches it). Its command record holds "
        "the safe command: `arm_request` 0, every rate 0, every current limit 0 (brakes "
        "set), gripper 0, mode 0, no CRL force display; so the service stays SAFE while the "
        "export holds the command area. Rules:",
        "",
        f"- Writable: {', '.join(f'`{n}`' for n in REQUEST_FIELDS)} only: "
        "a camera route, which must be one of the route table's 16 values "
        "(`controller/routes.py` `ALL_ROUTES`, docs/cameras.md), else exception 3; the "
        "service's PIO task applies it and reads it back (`inputs.matrix_route`).",
        "- A write that touches any other command field (`arm_request`, `rearm_counter`, "
        "rates, current limits, gripper, mode, ...) answers **exception 2 "
        "(ILLEGAL_ADDRESS)**, is counted (`refused`) and said in the export's refusal log "
        "line; nothing is applied.",
        "- A write must cover whole elements: writing part of a float64 (fewer than its 4 "
        "registers) or a register holding no command field answers exception 2; a "
        "non-finite float answers exception 3 (ILLEGAL_VALUE). Nothing is applied then.",
        "- `heartbeat` and `t_s` are set by the export; writing them (any value) is "
        "accepted as a keep-alive: it publishes the command record again with the "
        "heartbeat incremented (the safe command stays the safe command).",
        "- Use function code 16 to write a multi-register value in one request.",
        "",
        "The arm is driven by a controller process through `bit3.client` (docs/safety.md, "
        "\"Trust boundary\"); a Modbus master observes it (input registers, holding-register "
        "reads), posts HALT and CAMERA ROUTE requests to a running controller "
        "(`--modbus-requests`), or, with `--modbus-writes` and no controller running, sets the "
        "camera route.",
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
# Modbus TCP framing and the limits of one export


#: Modbus exception codes the export answers (Modbus application protocol, section 7)
ILLEGAL_FUNCTION = 1
ILLEGAL_ADDRESS = 2
ILLEGAL_VALUE = 3
DEVICE_FAILURE = 4
#: MBAP length field: unit id + PDU; a PDU is at most 253 bytes (an ADU at most 260)
MBAP_MAX_LENGTH = 254
#: Modbus limit on registers per write (fc 16)
MAX_WRITE_REGISTERS = 123
#: kernel send and receive buffer asked for each connection (Linux doubles it for its
#: bookkeeping); without it a loopback connection autotunes to ~4 MB each way
SOCKET_BUFFER_BYTES = 65536
_MBAP = struct.Struct(">HHHB")
_READS = {3, 4}
_WRITES = {6, 16}


@dataclass(frozen=True)
class ExportLimits:
    """What one export lets its clients use (flags of ``python -m tools.modbus_export``).

    Memory per connection is bounded by ``in_buffer_bytes`` (requests received, not yet
    answered) plus ``out_buffer_bytes`` (answers the client has not taken yet) plus one
    answer: when the answers pile up the export stops reading that connection (the
    client's sends then block in its own kernel buffers), and a connection that moves no
    byte either way for ``idle_timeout_s`` is closed.
    """

    max_connections: int = 16  #: clients at once; one more is accepted and closed at once
    in_buffer_bytes: int = 4096  #: per connection: received bytes not yet answered (>= 260)
    out_buffer_bytes: int = 16384  #: per connection: answers not yet taken by a slow reader
    idle_timeout_s: float = 60.0  #: a connection with no traffic (or a stalled reader) closed after
    summary_interval_s: float = 60.0  #: at most one line about refused requests per interval

    def __post_init__(self) -> None:
        if self.max_connections < 1:
            raise ConfigError(f"Modbus export: max_connections {self.max_connections}: at least 1")
        if self.in_buffer_bytes < 7 + MBAP_MAX_LENGTH - 1:
            raise ConfigError(f"Modbus export: in_buffer_bytes {self.in_buffer_bytes}: at least 260 "
                              f"(one whole Modbus TCP request)")
        if self.out_buffer_bytes < 260:
            raise ConfigError(f"Modbus export: out_buffer_bytes {self.out_buffer_bytes}: at least 260")
        if not self.idle_timeout_s > 0 or not self.summary_interval_s > 0:
            raise ConfigError("Modbus export: idle_timeout_s and summary_interval_s must be > 0")


def refusal_log(where: str, interval_s: float = 60.0, clock=time.monotonic,
                logger: logging.Logger | None = None) -> RefusalLog:
    """The export's :class:`pfma.refusals.RefusalLog`: refused requests and dropped
    connections counted, one warning line per ``interval_s`` at most, never a traceback."""
    lg = logger or log
    return RefusalLog(f"Modbus export {where}", lambda line: lg.warning("%s", line), interval_s, clock)


class _Connection(asyncio.BufferedProtocol):
    """One client: whole ADUs cut from a fixed receive buffer, answered in order
    (pipelined requests too), with the limits of :class:`ExportLimits`."""

    def __init__(self, server: "_Server") -> None:
        self.server = server
        self.transport: asyncio.Transport | None = None
        self._in = bytearray(server.limits.in_buffer_bytes)
        self._view = memoryview(self._in)
        self._n = 0  # bytes held in self._in
        self._paused = False  # answers piled up: not reading, not answering
        self._closing = False
        self.last_activity = server.loop.time()

    # -- asyncio callbacks -------------------------------------------------------------------
    def connection_made(self, transport) -> None:  # type: ignore[override]
        self.transport = transport
        srv = self.server
        if len(srv.connections) >= srv.limits.max_connections:
            srv.export.note(f"connections over the limit of {srv.limits.max_connections} (closed)")
            self._closing = True
            transport.abort()
            return
        srv.connections.add(self)
        srv.export.connections_total += 1
        transport.set_write_buffer_limits(high=srv.limits.out_buffer_bytes)
        sock = transport.get_extra_info("socket")
        if sock is not None:
            try:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                # the kernel's buffers for this client bounded too (Linux autotunes them to MBs)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER_BYTES)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER_BYTES)
            except OSError:
                pass

    def connection_lost(self, exc) -> None:
        self.server.connections.discard(self)
        self.transport = None

    def get_buffer(self, sizehint: int) -> memoryview:
        if self._n >= len(self._in):  # never while reading: a full buffer pauses reading
            return self._view[:1]  # pragma: no cover - defensive; asyncio needs a non-empty buffer
        return self._view[self._n:]

    def buffer_updated(self, nbytes: int) -> None:
        self._n += nbytes
        self.last_activity = self.server.loop.time()
        self._process()

    def pause_writing(self) -> None:
        self._paused = True
        if self.transport is not None and not self._closing:
            self.transport.pause_reading()

    def resume_writing(self) -> None:
        self._paused = False
        self.last_activity = self.server.loop.time()
        self._process()
        if self.transport is not None and not self._closing and not self._paused:
            self.transport.resume_reading()

    def eof_received(self) -> bool:
        return False  # close when the client half-closes (answers already written are sent)

    # -- framing ---------------------------------------------------------------------------
    def _process(self) -> None:
        buf, n, at = self._in, self._n, 0
        export = self.server.export
        while not self._paused and not self._closing and n - at >= 7:
            tid, proto, length, unit = _MBAP.unpack_from(buf, at)
            if length < 2 or length > MBAP_MAX_LENGTH:
                # the stream cannot be framed any further: nothing to answer, close
                export.note(f"malformed MBAP header (length {'< 2' if length < 2 else '> 254'}; "
                            f"connection closed)")
                self._close()
                break
            end = at + 6 + length
            if end > n:
                break  # the rest of this request has not arrived yet
            pdu = bytes(buf[at + 7:end])
            at = end
            export.requests += 1
            if proto != 0:
                export.note("requests with a protocol id other than 0 (not Modbus; not answered)")
                continue
            if export.device_id and unit != export.device_id:
                export.note("requests for another unit id (not answered)")
                continue
            answer = export.handle_pdu(pdu)
            if self.transport is not None:
                self.transport.write(_MBAP.pack(tid, 0, len(answer) + 1, unit) + answer)
        if at:
            rest = n - at
            buf[:rest] = buf[at:n]
            n = rest
        self._n = n
        if n >= len(buf) and self.transport is not None and not self._closing:
            self.transport.pause_reading()  # only while paused: resume_writing reads on

    def _close(self) -> None:
        self._closing = True
        if self.transport is not None:
            self.transport.close()

    def check_idle(self, now: float, timeout_s: float) -> None:
        """Close a connection that moved nothing for ``timeout_s`` (idle, or a reader that
        takes no answers: its write buffer then stays above the limit)."""
        if self._closing or now - self.last_activity < timeout_s:
            return
        why = "reader stalled" if self._paused else "idle"
        self.server.export.note(f"connections closed after {timeout_s:g} s {why}")
        self._closing = True
        if self.transport is not None:
            self.transport.abort()


class _Server:
    """The listening socket and its connections, on one asyncio loop."""

    def __init__(self, export: "ModbusExport", loop: asyncio.AbstractEventLoop, limits: ExportLimits) -> None:
        self.export = export
        self.loop = loop
        self.limits = limits
        self.connections: set[_Connection] = set()
        self.listener: asyncio.base_events.Server | None = None
        self._ticker: asyncio.Task | None = None

    async def start(self, host: str, port: int) -> int:
        self.listener = await self.loop.create_server(lambda: _Connection(self), host, port,
                                                      reuse_address=True, backlog=64)
        self._ticker = self.loop.create_task(self._tick())
        return self.listener.sockets[0].getsockname()[1]

    async def _tick(self) -> None:
        every = min(1.0, self.limits.idle_timeout_s / 4)
        while True:
            await asyncio.sleep(every)
            now = self.loop.time()
            for c in list(self.connections):
                c.check_idle(now, self.limits.idle_timeout_s)
            self.export.refusals.tick()

    async def stop(self) -> None:
        if self._ticker is not None:
            self._ticker.cancel()
        if self.listener is not None:
            self.listener.close()
        for c in list(self.connections):
            if c.transport is not None:
                c.transport.abort()
        if self.listener is not None:
            await self.listener.wait_closed()


class _ServerThread:
    """A :class:`_Server` on its own asyncio loop in a daemon thread."""

    def __init__(self, export: "ModbusExport", host: str, port: int, limits: ExportLimits) -> None:
        self.export = export
        self.host = host
        self.port = port
        self.limits = limits
        self._ready = threading.Event()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: _Server | None = None
        self._stopped: asyncio.Future | None = None
        self._error: BaseException | None = None

    def _run(self) -> None:
        loop = self._loop = asyncio.new_event_loop()

        async def main() -> None:
            self._server = _Server(self.export, loop, self.limits)
            self._stopped = loop.create_future()
            self.port = await self._server.start(self.host, self.port)
            self._ready.set()
            await self._stopped
            await self._server.stop()

        try:
            loop.run_until_complete(main())
        except BaseException as err:  # noqa: BLE001 - reported to start()
            self._error = err
            self._ready.set()
        finally:
            loop.close()

    def start(self, timeout_s: float) -> int:
        self._thread = threading.Thread(target=self._run, name=f"modbus-export-{self.export.buffer_name}",
                                        daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise ModbusExportError(f"Modbus export on {self.host}:{self.port} did not start within "
                                    f"{timeout_s:g} s")
        if self._error is not None:
            self._thread.join(timeout_s)
            self._thread = None
            err = self._error
            why = os.strerror(err.errno) if isinstance(err, OSError) and err.errno else str(err)
            raise ModbusExportError(f"Modbus export cannot listen on {self.host}:{self.port}: {why}") from err
        return self.port

    def stop(self, timeout_s: float) -> None:
        loop, stopped = self._loop, self._stopped
        if loop is not None and stopped is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(lambda: stopped.done() or stopped.set_result(None))
            except RuntimeError:  # loop already closed
                pass
        if self._thread is not None:
            self._thread.join(timeout_s)
        self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()


# ----------------------------------------------------------------------------------------
# the export


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
    :param limits: connections, buffers, time-outs, the summary interval
    """

    def __init__(self, buffer: str | Bit3Buffer = "pfma", host: str = "127.0.0.1",
                 port: int = DEFAULT_PORT, allow_writes: bool = False, *,
                 owner: str = DEFAULT_OWNER, device_id: int = 0,
                 layout: Layout | None = None, limits: ExportLimits | None = None,
                 requests_wm: str | None = None, wm_key: str | None = None) -> None:
        if not 0 <= int(port) <= 65535:
            raise ConfigError(f"Modbus export: port {port} out of range 0..65535")
        if not 0 <= int(device_id) <= 255:
            raise ConfigError(f"Modbus export: unit id {device_id} out of range 0..255")
        self._given = buffer if isinstance(buffer, Bit3Buffer) else None
        self.buffer_name = buffer.name if isinstance(buffer, Bit3Buffer) else str(buffer)
        self.layout = buffer.layout if isinstance(buffer, Bit3Buffer) else (layout or default_layout())
        self.host = host
        self.allow_writes = bool(allow_writes)
        #: the world model of the controller requests go to (None: no request block); with
        #: it the export never claims the command area (the running controller holds it)
        self.requests_wm = requests_wm
        self.wm_key = wm_key
        self._link: Any = None  # tools.console.control.ControllerLink, attached at the first request
        self._req = [0, 0, 0]  # the last request, its argument, the number it was posted under
        self.posted = 0  #: requests posted to the controller
        self.owner = owner
        self.device_id = int(device_id)
        self.limits = limits or ExportLimits()
        self.rows = register_map(self.layout)
        self.requests = 0  #: requests received (whole, framed)
        self.writes = 0  #: write requests applied
        self.refused = 0  #: requests answered with an exception
        self.connections_total = 0  #: connections accepted (within the limit)
        self.refusals = refusal_log(f"{host}:{port}", self.limits.summary_interval_s)
        self._port = int(port)
        self._buf: Bit3Buffer | None = None
        self._client: Client | None = None
        self._views: dict[str, _AreaView] = {}
        self._server: _ServerThread | None = None
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
        self._ident = np.array(ident + [MAP_VERSION, self._n_channels], dtype=">u2")
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
            if self.allow_writes and self.requests_wm is None:
                path = self.buffer_name if "/" in self.buffer_name else None  # file window
                self._client = Client.attach(self.buffer_name, writer="commands", owner=self.owner,
                                             layout=self.layout, path=path)
                rec = self._client.command  # the safe command, published with the first write
                for name, safe in SAFE_COMMAND.items():
                    rec[name] = safe
            self._views = {n: _AreaView(self._buf, n) for n in ("inputs", "stats", "commands")}
            server = _ServerThread(self, self.host, self._port, self.limits)
            server.start(timeout_s)
            self._server = server
            self.refusals.where = f"{self.host}:{server.port}"
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
        """Stop serving, release the controller role (if held) and detach; the refusals
        not yet said are logged (one line)."""
        server, self._server = self._server, None
        if server is not None:
            self._port = server.port
            server.stop(timeout_s)
            self.refusals.flush()
        self._close_buffers()

    def _close_buffers(self) -> None:
        self._views = {}
        self._drop_link()
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

    def stats(self) -> dict:
        """Counters: requests, writes, refused, connections (open and accepted), and the
        refusals by reason since the start."""
        srv = self._server._server if self._server is not None else None
        return {"requests": self.requests, "writes": self.writes, "refused": self.refused,
                "connections_open": len(srv.connections) if srv is not None else 0,
                "connections_total": self.connections_total,
                "refusals": dict(self.refusals.total)}

    # -- requests ----------------------------------------------------------------------------
    def note(self, reason: str) -> None:
        """Count something refused that got no exception answer (a dropped connection)."""
        self.refusals.note(reason)

    def _exception(self, fc: int, code: int, reason: str) -> bytes:
        self.refused += 1
        self.refusals.note(reason)
        return bytes(((fc | 0x80) & 0xFF, code))

    def handle_pdu(self, pdu: bytes) -> bytes:
        """The answer PDU to one request PDU (function code and data; never raises).

        Function codes 3 and 4 read, 6 and 16 write (refused unless writes are allowed);
        every other code answers exception 1, codes 0x80-0xFF too (as ``code | 0x80``:
        unchanged). A request of a known code whose length or counts are wrong answers
        exception 3; an unmapped address exception 2; a stuck writer exception 4.
        """
        fc = pdu[0]
        if fc in _READS:
            if len(pdu) != 5:
                return self._exception(fc, ILLEGAL_VALUE, f"malformed fc {fc} requests (length)")
            address, count = struct.unpack_from(">HH", pdu, 1)
            if not 1 <= count <= MAX_READ_REGISTERS:
                return self._exception(fc, ILLEGAL_VALUE, f"fc {fc} reads of 0 or more than "
                                                          f"{MAX_READ_REGISTERS} registers")
            try:
                regs = self._read(fc, address, count)
            except Bit3Error:  # SeqLockTimeout: writer stuck mid-write
                return self._exception(fc, DEVICE_FAILURE, "reads of an area stuck mid-write")
            if regs is None:
                return self._exception(fc, ILLEGAL_ADDRESS, f"fc {fc} reads of unmapped registers")
            return bytes((fc, 2 * count)) + regs
        if fc == 6:
            if len(pdu) != 5:
                return self._exception(fc, ILLEGAL_VALUE, "malformed fc 6 requests (length)")
            if not self.allow_writes:
                return self._exception(fc, ILLEGAL_FUNCTION, "writes (refused: read-only export)")
            address, value = struct.unpack_from(">HH", pdu, 1)
            code = self._write(address, [value])
            return self._exception(fc, code[0], code[1]) if code else pdu
        if fc == 16:
            if len(pdu) < 6:
                return self._exception(fc, ILLEGAL_VALUE, "malformed fc 16 requests (length)")
            address, count, nbytes = struct.unpack_from(">HHB", pdu, 1)
            if not 1 <= count <= MAX_WRITE_REGISTERS or nbytes != 2 * count or len(pdu) != 6 + nbytes:
                return self._exception(fc, ILLEGAL_VALUE, "malformed fc 16 requests (counts)")
            if not self.allow_writes:
                return self._exception(fc, ILLEGAL_FUNCTION, "writes (refused: read-only export)")
            code = self._write(address, list(struct.unpack_from(f">{count}H", pdu, 6)))
            return self._exception(fc, code[0], code[1]) if code else pdu[:5]
        what = f"0x{fc:02X}" if fc >= 0x80 else str(fc)
        return self._exception(fc, ILLEGAL_FUNCTION, f"requests of function code {what} "
                                                     f"(not in the map)")

    def _read(self, function_code: int, address: int, count: int) -> bytes | None:
        """Registers ``address .. address+count-1`` (big-endian bytes) from one snapshot,
        or None if unmapped."""
        end = address + count
        if function_code == 3:
            if COMMANDS_BASE <= address and end <= COMMANDS_BASE + self._hr_count:
                regs = self._views["commands"].registers()
                return regs[address - COMMANDS_BASE:end - COMMANDS_BASE].tobytes()
            if self.requests_wm is not None and REQUESTS_BASE <= address and end <= REQUESTS_BASE + REQUEST_REGISTERS:
                return self._request_registers()[address - REQUESTS_BASE:end - REQUESTS_BASE].tobytes()
            return None
        for base, n, area in self._ir_areas:
            if base <= address and end <= base + n:
                return self._views[area].registers()[address - base:end - base].tobytes()
        if CHANNELS_BASE <= address and end <= CHANNELS_BASE + 2 * self._n_channels:
            return self._channel_registers()[address - CHANNELS_BASE:end - CHANNELS_BASE].tobytes()
        if IDENT_BASE <= address and end <= IDENT_BASE + len(self._ident):
            return self._ident[address - IDENT_BASE:end - IDENT_BASE].tobytes()
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

    def _write(self, address: int, values: list[int]) -> tuple[int, str] | None:
        """Apply one write request to the command record and publish it (heartbeat + 1), or
        post it to the controller (the request block); ``(exception code, reason)`` when
        refused (nothing applied)."""
        if self.requests_wm is not None:
            if REQUESTS_BASE <= address and address + len(values) <= REQUESTS_BASE + 2:
                return self._request(address - REQUESTS_BASE, values)
            return ILLEGAL_ADDRESS, ("writes outside the request block (the command area is the "
                                     "controller's; the export never arms or moves the arm)")
        lo = address - COMMANDS_BASE
        hi = lo + len(values)  # exclusive
        if lo < 0 or hi > self._hr_count:
            return ILLEGAL_ADDRESS, "writes to unmapped registers"
        span_lo = self._hr_lo[lo:hi]
        span_hi = self._hr_hi[lo:hi]
        if (span_lo < 0).any() or (span_lo < lo).any() or (span_hi >= hi).any():
            # a register with no command field, or part of an element
            return ILLEGAL_ADDRESS, "writes of part of an element or of no command field"
        client = self._client
        assert client is not None
        rec = client.command
        le = np.frombuffer(rec.tobytes(), dtype=np.uint8)
        be = le[self._cmd_perm]
        be[2 * lo:2 * hi] = np.array(values, dtype=">u2").view(np.uint8)
        new = np.ndarray((), self._cmd_dtype, buffer=be[self._cmd_perm].tobytes())
        names: set[str] = set()
        for r in range(lo, hi):
            names |= self._hr_fields[r]
        never = sorted(names.difference(REQUEST_FIELDS, KEEPALIVE_FIELDS))
        if never:  # the export never arms or drives motion: only the requests are writable
            # (the first field only: a bounded set of reasons for the refusal log)
            return ILLEGAL_ADDRESS, (f"writes of {never[0]}{' and more' if len(never) > 1 else ''} "
                                     f"(writable: {', '.join(REQUEST_FIELDS)}; the export never arms "
                                     "or moves the arm)")
        fields = {n: (new[n].item() if new[n].ndim == 0 else new[n].copy())
                  for n in sorted(names) if n not in KEEPALIVE_FIELDS}
        if "matrix_route" in fields and int(fields["matrix_route"]) not in ALL_ROUTES:
            return ILLEGAL_VALUE, "writes of a matrix_route outside the route table"
        try:
            if fields:
                client.write_commands(**fields)
            else:
                client.publish_commands()
        except Bit3Error:  # not finite, out of range: nothing applied
            return ILLEGAL_VALUE, f"writes of values the command area refuses ({', '.join(sorted(fields))})"
        self.writes += 1
        return None

    def _request(self, offset: int, values: list[int]) -> tuple[int, str] | None:
        """A write to the request block: the argument is kept; a request (HR 9000) of
        :data:`MODBUS_REQUESTS` is posted to the controller, which answers it (validates)."""
        req = self._req
        if offset == 1:  # the argument alone
            req[1] = values[0]
            self.writes += 1
            return None
        kind = values[0]
        arg = values[1] if len(values) > 1 else req[1]
        if kind not in MODBUS_REQUESTS:
            return ILLEGAL_VALUE, (f"requests of kind {kind} (taken: "
                                   f"{', '.join(f'{k} {n}' for k, n in MODBUS_REQUESTS.items())}; "
                                   "the export never arms or moves the arm)")
        from tools.console.control import ControlError, ControllerLink
        try:
            if self._link is None:
                self._link = ControllerLink.attach(self.requests_wm, self.wm_key)
            seq = self._link.submit(kind, arg)
        except ControlError as err:
            self._drop_link()
            log.warning("Modbus export %s:%d: request %s not posted: %s", self.host, self.port,
                        MODBUS_REQUESTS[kind], err)
            return DEVICE_FAILURE, "requests while no controller answers"
        req[:] = [kind, arg, seq]
        self.posted += 1
        self.writes += 1
        return None

    def _request_registers(self) -> np.ndarray:
        kind, arg, seq = self._req
        code = answered = 0
        if self._link is not None:
            try:
                v = self._link.wm.get_task_inputs(("ui.response_seq", "ui.response"))
                answered, code = int(v["ui.response_seq"]), int(v["ui.response"])
            except Exception:  # noqa: BLE001 - a world model gone under us reads as no answer
                self._drop_link()
        return np.array([kind, arg, seq & 0xFFFF, code & 0xFFFF, answered & 0xFFFF], dtype=">u2")

    def _drop_link(self) -> None:
        if self._link is not None:
            try:
                self._link.wm.close()
            except Exception:  # noqa: BLE001 - closing a segment already gone
                pass
            self._link = None


# ----------------------------------------------------------------------------------------
# command-line helpers


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


#: the export process's priority below the service's (``os.nice`` increment): on a
#: loaded host the acquisition loop wins the CPU over Modbus clients
EXPORT_NICE = 5
#: the first line the export process prints when it listens
_READY = "modbus-export listening"


class ExportProcess:
    """The Modbus export in its own process (``python -m tools.modbus_export``), started
    by ``pfma serve --modbus``: Modbus clients cost the export's process CPU time, never
    the acquisition loop's interpreter (the in-process export shared the service's GIL:
    issue 20 measured ~50 extra dropped frames per 10 s under a 1,800 request/s flood).

    The process attaches to the buffer by name like any tool; it runs below the service
    (time-sharing even under ``pfma serve --realtime``, off the service's pinned CPU, nice
    :data:`EXPORT_NICE`), exits when its parent dies (``PR_SET_PDEATHSIG``) and stops
    cleanly on SIGTERM or SIGINT; its log lines (the refusal summaries) go to the
    service's stderr. Start it from a thread that lives as long as the service (the main
    thread): Linux sends the parent-death signal when the *thread* that started it ends.
    """

    def __init__(self, buffer_name: str, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 allow_writes: bool = False, *, rack: str | None = None,
                 limits: ExportLimits | None = None, nice: int = EXPORT_NICE,
                 requests_wm: str | None = None) -> None:
        self.buffer_name = buffer_name
        self.requests_wm = requests_wm
        self.host = host
        self.port = port
        self.allow_writes = allow_writes
        self.rack = rack
        self.limits = limits or ExportLimits()
        self.nice = nice
        self.proc: subprocess.Popen | None = None

    def argv(self) -> list[str]:
        lim = self.limits
        argv = [sys.executable, "-m", "tools.modbus_export", "--buffer", self.buffer_name,
                "--listen", self.address,
                "--max-connections", str(lim.max_connections),
                "--in-buffer-bytes", str(lim.in_buffer_bytes),
                "--out-buffer-bytes", str(lim.out_buffer_bytes),
                "--idle-timeout-s", repr(lim.idle_timeout_s),
                "--summary-interval-s", repr(lim.summary_interval_s),
                "--nice", str(self.nice), "--parent-pid", str(os.getpid())]
        if self.rack:
            argv += ["--rack", self.rack]
        if self.requests_wm is not None:
            argv += ["--requests", self.requests_wm]
        elif self.allow_writes:
            argv.append("--writes")
        return argv

    @property
    def address(self) -> str:
        """HOST:PORT as ``--listen`` takes it (an IPv6 host in brackets)."""
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"

    #: how :class:`pfma.process.HelperWatch` names it, and what its absence means
    label = "Modbus export"
    lost = "Modbus clients get no answers until it is back"

    def spawn(self) -> subprocess.Popen:
        """Start the process without waiting for it (its first line: :meth:`accept`); on the
        port it listens on (a restart keeps the port port 0 was given)."""
        self.proc = spawn_helper(self.argv())
        return self.proc

    def accept(self, line: str) -> str:
        """"" when ``line`` says it listens (its port noted), else why not (one line)."""
        if line.startswith(_READY):
            self.port = int(line.rsplit(":", 1)[1])
            return ""
        return line.removeprefix("error: ") or NO_WORD

    def start(self, timeout_s: float = 30.0) -> "ExportProcess":
        """Start the process; return once it listens.

        :raises ModbusExportError: it could not attach, claim or listen (its one-line
            reason), or did not say it listens within ``timeout_s``
        """
        why = bring_up(self, timeout_s)
        if not why:
            return self
        self.stop()
        raise ModbusExportError(why)

    def stop(self, timeout_s: float = 5.0) -> None:
        """SIGTERM, then SIGKILL after ``timeout_s``; waits for the process."""
        proc, self.proc = self.proc, None
        stop_helper(proc, timeout_s)

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


def start_export_from_args(buffer_name: str, host_port: str, allow_writes: bool,
                           rack: str | None = None, requests_wm: str | None = None) -> ExportProcess:
    """Parse ``HOST:PORT`` and start the export in its own process (for ``pfma serve
    --modbus``; :class:`ExportProcess`). The caller stops it (``export.stop()``) when the
    service stops.

    :param rack: the rack TOML of a buffer made from another rack file than the default
    :param requests_wm: the controller's world model: Modbus requests (HALT, CAMERA ROUTE)
        are posted to it (docs/modbus-map.md)
    """
    host, port = parse_host_port(host_port)
    return ExportProcess(buffer_name, host=host, port=port, allow_writes=allow_writes or requests_wm is not None,
                         rack=rack, requests_wm=requests_wm).start()


def _leave_the_service_alone(nice: int) -> None:
    """Run below the service: an ordinary time-sharing process (a ``pfma serve --realtime``
    parent's SCHED_FIFO is inherited by its children), off the CPU the service is pinned
    to (when it is pinned to fewer CPUs than there are), ``nice`` steps down. Best effort."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass
    try:
        pinned = os.sched_getaffinity(0)
        others = set(range(os.cpu_count() or 1)) - pinned
        if others and len(pinned) < (os.cpu_count() or 1):
            os.sched_setaffinity(0, others)
    except (OSError, AttributeError):
        pass
    if nice:
        try:
            os.nice(nice)
        except OSError:
            pass


def main(argv: list[str] | None = None) -> int:
    """``python -m tools.modbus_export``: one export process (what ``pfma serve --modbus``
    starts). Prints ``modbus-export listening on HOST:PORT`` once it listens, or one
    ``error: ...`` line and exits 1."""
    import argparse
    p = argparse.ArgumentParser(prog="python -m tools.modbus_export",
                                description="Serve a Bit3 buffer over Modbus TCP (docs/modbus-map.md).")
    d = ExportLimits()
    p.add_argument("--buffer", default="pfma", help="Bit3 shared-memory name (default pfma)")
    p.add_argument("--listen", default=f"127.0.0.1:{DEFAULT_PORT}", metavar="HOST:PORT",
                   help=f"address to serve (default 127.0.0.1:{DEFAULT_PORT}; port 0: any free one)")
    p.add_argument("--writes", action="store_true", help="accept camera-route requests (claims the controller role; never arms or moves the arm)")
    p.add_argument("--requests", default=None, metavar="WM",
                   help="post HALT and CAMERA ROUTE requests to the controller of world model WM "
                        "(holding registers 9000-9004; never arms or moves the arm)")
    p.add_argument("--rack", default=None, help="rack TOML of the buffer (default: the default rack)")
    p.add_argument("--max-connections", type=int, default=d.max_connections,
                   help=f"clients at once; one more is closed at once (default {d.max_connections})")
    p.add_argument("--in-buffer-bytes", type=int, default=d.in_buffer_bytes,
                   help=f"per connection: requests received, not yet answered (default {d.in_buffer_bytes})")
    p.add_argument("--out-buffer-bytes", type=int, default=d.out_buffer_bytes,
                   help=f"per connection: answers a slow reader has not taken (default {d.out_buffer_bytes})")
    p.add_argument("--idle-timeout-s", type=float, default=d.idle_timeout_s,
                   help=f"close a connection with no traffic for this long (default {d.idle_timeout_s:g})")
    p.add_argument("--summary-interval-s", type=float, default=d.summary_interval_s,
                   help=f"at most one log line about refused requests per interval "
                        f"(default {d.summary_interval_s:g})")
    p.add_argument("--nice", type=int, default=0, help="lower this process's priority by N")
    p.add_argument("--parent-pid", type=int, default=None,
                   help="exit when this process (the service) is gone")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                        format="pfma serve: %(message)s")
    logging.getLogger().handlers[0].addFilter(lambda r: r.levelno >= logging.WARNING)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    if args.parent_pid is not None:
        set_parent_death_signal(signal.SIGTERM)
        if os.getppid() != args.parent_pid:  # the parent died before the signal was armed
            return 0
    _leave_the_service_alone(args.nice)
    export = None
    try:
        host, port = parse_host_port(args.listen)
        limits = ExportLimits(args.max_connections, args.in_buffer_bytes, args.out_buffer_bytes,
                              args.idle_timeout_s, args.summary_interval_s)
        layout = None
        if args.rack:
            from bit3.layout import build_layout
            from pfma.rack import load_rack
            layout = build_layout(load_rack(args.rack))
        export = ModbusExport(args.buffer, host, port, args.writes or args.requests is not None, layout=layout,
                              limits=limits, requests_wm=args.requests).start()
    except PfmaError as err:
        print(f"error: {err}", flush=True)
        return 1
    try:
        try:
            print(f"{_READY} on {export.host}:{export.port}", flush=True)
        except BrokenPipeError:
            # the service that started it died before reading the line (the kill matrix's
            # SIGKILL at start-up): nobody to serve; stop without a traceback, and point the
            # stdout Python flushes at exit somewhere that cannot break
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            log.warning("Modbus export %s:%d: the process that started it is gone; stopping", export.host,
                        export.port)
            return 1
        while not stop.wait(0.5):
            if args.parent_pid is not None and os.getppid() != args.parent_pid:
                break
            if not export.running:
                log.warning("Modbus export %s:%d: its server stopped", export.host, export.port)
                return 1
    finally:
        export.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
