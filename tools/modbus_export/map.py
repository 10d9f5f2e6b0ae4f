"""The Modbus register map of the Bit3 buffer, derived from the layout (:func:`register_map`),
and the constants of the map (bases, the writable fields, the safe command).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bit3.client import PRIMARY_FIELD
from bit3.layout import Layout, default_layout
from pfma.errors import PfmaError

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
#: Modbus limit on registers per read (fc 3/4)
MAX_READ_REGISTERS = 125
DEFAULT_PORT = 5020
DEFAULT_OWNER = "modbus-export"

MAP_DOC_PATH = Path(__file__).resolve().parents[2] / "docs" / "modbus-map.md"

#: numpy element dtype -> pymodbus DATATYPE name
_MODBUS_TYPE = {"<f8": "FLOAT64", "<f4": "FLOAT32", "<u8": "UINT64", "<i8": "INT64",
                "<u4": "UINT32", "<i4": "INT32", "<u2": "UINT16", "<i2": "INT16",
                "|u1": "UINT8", "|i1": "INT8"}


class ModbusExportError(PfmaError):
    """The Modbus export could not start (port in use, bad address, buffer missing)."""


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
