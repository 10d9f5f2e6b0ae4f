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

The package, along its seams: :mod:`~tools.modbus_export.map` (the register map),
:mod:`~tools.modbus_export.markdown` (docs/modbus-map.md), :mod:`~tools.modbus_export.server`
(Modbus TCP framing, limits, the server thread), :mod:`~tools.modbus_export.export`
(:class:`ModbusExport`), :mod:`~tools.modbus_export.process` (the export's own process,
``python -m tools.modbus_export``).
"""

from __future__ import annotations

from tools.modbus_export.map import (
    CHANNELS_BASE, COMMANDS_BASE, IDENT_BASE, INPUTS_BASE, MAP_DOC_PATH, MAP_VERSION, REQUESTS_BASE,
    STATS_BASE, MapRow, ModbusExportError, map_row, register_map,
)
from tools.modbus_export.server import ExportLimits, refusal_log
from tools.modbus_export.markdown import modbus_map_markdown, write_modbus_map_doc
from tools.modbus_export.export import ModbusExport
from tools.modbus_export.process import ExportProcess, main, parse_host_port, start_export_from_args

__all__ = [
    "CHANNELS_BASE", "COMMANDS_BASE", "IDENT_BASE", "INPUTS_BASE", "MAP_DOC_PATH", "MAP_VERSION",
    "REQUESTS_BASE", "STATS_BASE", "ExportLimits", "ExportProcess", "MapRow", "ModbusExport",
    "ModbusExportError", "refusal_log", "main", "map_row", "modbus_map_markdown", "parse_host_port",
    "register_map", "start_export_from_args", "write_modbus_map_doc",
]
