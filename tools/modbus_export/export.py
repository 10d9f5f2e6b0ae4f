"""The export itself (:class:`ModbusExport`): the buffer's areas as big-endian registers
from seqlocked snapshots, the answer to each request PDU, the command writes and the
requests posted to a running controller.
"""

from __future__ import annotations

import ipaddress
import logging
import struct
from typing import Any

import numpy as np

from bit3.buffer import Bit3Buffer, Bit3Error
from bit3.client import PRIMARY_FIELD, Client
from bit3.layout import Layout, default_layout
from controller.routes import ALL_ROUTES
from pfma.errors import ConfigError
from tools.modbus_export.map import (
    CHANNELS_BASE, COMMANDS_BASE, DEFAULT_OWNER, DEFAULT_PORT, IDENT_BASE, INPUTS_BASE,
    KEEPALIVE_FIELDS, MAP_VERSION, MAX_READ_REGISTERS, MODBUS_REQUESTS, REQUEST_FIELDS,
    REQUEST_REGISTERS, REQUESTS_BASE, SAFE_COMMAND, STATS_BASE, ModbusExportError, _rack_channels,
    register_map,
)
from tools.modbus_export.server import (
    _READS, DEVICE_FAILURE, ILLEGAL_ADDRESS, ILLEGAL_FUNCTION, ILLEGAL_VALUE, MAX_WRITE_REGISTERS,
    ExportLimits, _ServerThread, refusal_log,
)

log = logging.getLogger("tools.modbus_export")  # one logger for the package: its records keep their name


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


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
