"""F/T sensor over CAN (python-can), producing the same ``FtReading`` as the serial driver.

No public Lord/ATI CAN layout could be consulted here. ATI's CAN F/T interfaces are
recalled (unverified) to answer one read request with the gauge values split over
two data frames; this PROJECT-DEFINED layout keeps that shape. Its one table, ``CAN_LAYOUT``, lives in
``protocol.py`` (shared with the fake node, re-exported here) and in docs/ft-protocol.md;
change both when the real node's layout is known.

Identifiers are 11-bit: ``base = 0x100 + 0x10 * node_id`` (node 0..15).

Two ways to read: :meth:`CanFtSensor.read` (request, then wait up to ``timeout_s`` for
the answer: tools, tests) and :meth:`CanFtSensor.read_records` (never waits: collect the
answer to the previous request, send the next; the I/O service's F/T slot, where a
record then arrives one F/T period after its request).

The service names a CAN F/T by URL, ``can://INTERFACE/CHANNEL[?node=N&bitrate=B]``
(python-can's interface names: ``can://socketcan/can0``, ``can://virtual/ft``;
:func:`parse_can_url`, :func:`open_can_url`).
"""

from __future__ import annotations

import struct
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qsl, urlsplit

from pfma.clock import Clock, MonotonicClock
from pfma.errors import ConfigError, LinkError, PfmaTimeoutError, did_you_mean
from drivers.ratewindow import RateWindow

from .ftsensor import FtReading, LinkStats
from .protocol import (CAN_BASE_ID, CAN_LAYOUT, CAN_NODE_STRIDE, MAX_NODE_ID, NOMINAL,  # noqa: F401
                       OP_BIAS, OP_CLEAR_BIAS, OP_READ, OP_UNBIAS, STATUS_CODES, CanFrameLayout,
                       frame_id, node_base_id)

if TYPE_CHECKING:
    import can  # python-can, imported by whoever opens the bus

#: the URL form of a CAN F/T (``pfma serve --ft``)
CAN_URL_FORM = "can://INTERFACE/CHANNEL[?node=N&bitrate=BPS]"
#: node id when the URL names none
DEFAULT_NODE_ID = 0


class CanUrlError(ConfigError):
    """A ``can://`` URL that is not of the form :data:`CAN_URL_FORM` (a usage mistake)."""


def is_can_url(url: str) -> bool:
    """True for a ``can:`` URL (anything else is a pyserial URL or device path)."""
    return url[:4].lower() == "can:"


@dataclass(frozen=True)
class CanUrl:
    """A parsed ``can://`` URL."""

    interface: str  #: python-can interface name (socketcan, virtual, pcan, ...)
    channel: str  #: its channel (can0, vcan0, a virtual channel name, PCAN_USBBUS1, ...)
    node_id: int = DEFAULT_NODE_ID
    bitrate: int | None = None  #: passed to ``can.Bus`` when given (socketcan ignores it)


def parse_can_url(url: str) -> CanUrl:
    """``can://INTERFACE/CHANNEL[?node=N&bitrate=BPS]`` -> :class:`CanUrl` (no python-can
    needed: the form only).

    :raises CanUrlError: not of that form, or a node id / bit rate that is not a number
        in range
    """
    try:
        parts = urlsplit(url)
        query = parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError as err:
        raise CanUrlError(f"{url!r} is not a URL of the form {CAN_URL_FORM}: {err}") from err
    iface, channel = parts.netloc, parts.path.removeprefix("/")
    if parts.scheme.lower() != "can" or not url[4:].startswith("//") or not iface or not channel:
        raise CanUrlError(f"{url!r} is not of the form {CAN_URL_FORM} (e.g. can://socketcan/can0, "
                          f"can://virtual/ft)")
    node, bitrate = DEFAULT_NODE_ID, None
    for key, value in query:
        if key == "node":
            if not value.isdigit() or int(value) > MAX_NODE_ID:
                raise CanUrlError(f"{url}: node={value!r}: a CAN F/T node id is 0..{MAX_NODE_ID}")
            node = int(value)
        elif key == "bitrate":
            if not value.isdigit() or int(value) == 0:
                raise CanUrlError(f"{url}: bitrate={value!r}: a bit rate is a positive whole "
                                  f"number of bit/s (e.g. 1000000)")
            bitrate = int(value)
        else:
            raise CanUrlError(f"{url}: unknown option {key!r} (known: node, bitrate)")
    return CanUrl(iface, channel, node, bitrate)


def open_can_url(url: str, clock: Clock | None = None, timeout_s: float = 0.1) -> "CanFtSensor":
    """Open the CAN bus a ``can://`` URL names and the F/T node on it (the sensor owns the
    bus: :meth:`CanFtSensor.close` shuts it down).

    :raises CanUrlError: a malformed URL
    :raises ConfigError: python-can is not installed, or it has no such interface
    :raises LinkError: the interface could not open the channel (no such device, no
        permission, the vendor library missing)
    """
    spec = parse_can_url(url)
    try:
        import can
        from can.interfaces import VALID_INTERFACES
    except ImportError as err:
        raise ConfigError(f"{url}: python-can is not installed ({err}); pip install python-can") from err
    if spec.interface not in VALID_INTERFACES:
        raise ConfigError(f"{url}: python-can has no interface {spec.interface!r}"
                          f"{did_you_mean(spec.interface, VALID_INTERFACES)} (known: "
                          f"{', '.join(sorted(VALID_INTERFACES))})")
    kw: dict[str, Any] = {} if spec.bitrate is None else {"bitrate": spec.bitrate}
    try:
        bus = can.Bus(interface=spec.interface, channel=spec.channel, **kw)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as err:
        raise LinkError(f"{url}: cannot open CAN channel {spec.channel!r} on {spec.interface}: "
                        f"{err or type(err).__name__}") from err
    sensor = CanFtSensor(bus, spec.node_id, clock=clock, timeout_s=timeout_s)
    sensor.owns_bus = True
    sensor.url = url
    return sensor


class CanFtSensor:
    """F/T node on a CAN bus, request/response.

    :param bus: any ``can.BusABC`` (``socketcan`` in the lab, ``virtual`` in tests); the
        driver is the bus's only consumer (python-can: one consumer per bus)
    :param node_id: 0..15
    :param cpf: counts per newton; :param cpt: counts per newton-metre (defaults assumed)
    :param clock: timestamps; :param timeout_s: bound on each reply
    """

    def __init__(self, bus: can.BusABC, node_id: int, cpf: float = NOMINAL.cpf, cpt: float = NOMINAL.cpt,
                 clock: Clock | None = None, timeout_s: float = 0.1, rate_window_s: float = 1.0) -> None:
        if not (cpf > 0 and cpt > 0):
            raise ConfigError(f"CAN F/T node {node_id}: cpf and cpt must be > 0 (got {cpf}, {cpt})")
        self.bus = bus
        self.node_id = node_id
        try:
            self.base_id = node_base_id(node_id)
        except ValueError as err:
            raise ConfigError(str(err)) from err
        self.cpf, self.cpt = float(cpf), float(cpt)
        self.clock = clock or MonotonicClock()
        self.timeout_s = timeout_s
        self.latest: FtReading | None = None
        self._tag = 0
        self._seq = 0
        self._records = 0
        self._bad = 0
        self._frames_in = 0
        self._rate = RateWindow(rate_window_s)
        self.name = f"CAN node {node_id} (ids 0x{self.base_id:03X}..0x{self.base_id + 3:03X})"
        self.url = ""  #: the can:// URL it was opened from (open_can_url), else ""
        self.owns_bus = False  #: close() shuts the bus down (open_can_url opened it)
        self.streaming = False  #: the serial driver's flag; nothing streams on this request/response link
        self.errors = 0  #: send/receive failures, unanswered requests, bad pairs of read_records
        self.last_error = ""  #: what the last of those was
        self._pending: int | None = None  # tag of the request read_records waits on
        self._pending_t = 0.0
        self._forces: tuple | None = None  # the forces frame of the answer being paired

    def read(self) -> FtReading:
        """Request one record; pair the forces and torques frames by seq and tag.

        :raises PfmaTimeoutError: no complete answer within ``timeout_s``
        :raises LinkError: the bus failed
        """
        tag = self._request(OP_READ)
        self._forces = None
        deadline = time.monotonic() + self.timeout_s
        while True:
            r = self._take(self._recv(deadline, "read"), tag)
            if r is not None:
                return r

    def read_records(self) -> list[FtReading]:
        """Never waits: the records whose answers have arrived since the last call, then
        the next read request (unless one is outstanding and younger than ``timeout_s`` of
        the clock). Called once per F/T slot, a record arrives one slot after its request.

        Never raises for link trouble: an unanswered request counts as a bad record, a
        mis-paired answer likewise, a send/receive failure in :attr:`errors` (with
        :attr:`last_error`); the caller sees the link go stale.
        """
        import can

        out: list[FtReading] = []
        while True:
            try:
                msg = self.bus.recv(timeout=0)
            except can.CanError as err:
                self._fail(f"receive failed: {err}")
                break
            if msg is None:
                break
            if msg.is_extended_id or not self.base_id < msg.arbitration_id <= self.base_id + 3:
                continue
            self._frames_in += 1
            if self._pending is None:
                continue  # an answer nobody waits for any more
            try:
                r = self._take(msg, self._pending)
            except LinkError as err:
                self._fail(str(err))
                self._pending = None
                continue
            if r is not None:
                out.append(r)
                self._pending = None
        now = self.clock.now()
        if self._pending is not None and now - self._pending_t > self.timeout_s:
            self._bad += 1  # unanswered: ask again
            self._fail(f"no answer within {self.timeout_s:g} s")
            self._pending = None
        if self._pending is None:
            try:
                self._pending = self._request(OP_READ)
                self._pending_t = now
                self._forces = None
            except LinkError as err:
                self._fail(str(err))
        return out

    def record_due(self) -> bool:
        """The serial driver's "a record is waiting" check: never here (records are taken
        in :meth:`read_records` at the F/T slot)."""
        return False

    def stop_stream(self) -> list[FtReading]:
        """Nothing streams on this request/response link: a request still outstanding is
        forgotten (its answer is ignored)."""
        self._pending = None
        return []

    def close(self) -> None:
        """Shut the bus down when this sensor opened it (:func:`open_can_url`)."""
        self._pending = None
        if self.owns_bus:
            self.owns_bus = False
            self.bus.shutdown()

    def bias(self) -> int:
        """Push the current reading onto the node's bias stack; returns the stack depth."""
        return self._command(OP_BIAS, "bias")

    def unbias(self) -> int:
        """Pop the last bias; returns the stack depth."""
        return self._command(OP_UNBIAS, "unbias")

    def clear_bias(self) -> int:
        """Clear all biases; returns the stack depth (0)."""
        return self._command(OP_CLEAR_BIAS, "clear bias")

    def stats(self) -> LinkStats:
        """Link statistics (bytes_in counts payload bytes of this node's frames)."""
        now = self.clock.now()
        return LinkStats(records=self._records, bad_records=self._bad, resyncs=0,
                         rate_hz=self._rate.rate_hz(now),
                         age_s=None if self.latest is None else now - self.latest.t_s,
                         bytes_in=self._frames_in * 8)

    # -- internals ----------------------------------------------------------------------
    def _take(self, msg: can.Message, tag: int) -> FtReading | None:
        """One frame of this node's answer to request ``tag``: the forces frame is kept, the
        torques frame completes the record (a torques frame of another tag is a late answer
        to an earlier request: ignored).

        :raises LinkError: the torques frame does not pair with the forces frame
        """
        if msg.arbitration_id == self.base_id + CAN_LAYOUT["forces"].offset and len(msg.data) == 8:
            self._forces = struct.unpack(CAN_LAYOUT["forces"].struct_fmt, bytes(msg.data))
        elif msg.arbitration_id == self.base_id + CAN_LAYOUT["torques"].offset and len(msg.data) == 8:
            tx, ty, tz, seq, rtag = struct.unpack(CAN_LAYOUT["torques"].struct_fmt, bytes(msg.data))
            if rtag != tag:
                return None
            forces, self._forces = self._forces, None
            if forces is None or forces[4] != seq or forces[3] not in STATUS_CODES:
                self._bad += 1
                raise LinkError(f"F/T on {self.name}: forces/torques frames do not pair "
                                f"(seq {seq}, forces {forces}); record discarded")
            return self._accept(forces[3], forces[:3] + (tx, ty, tz))
        return None

    def _fail(self, text: str) -> None:
        """Count a link error of :meth:`read_records`; :attr:`last_error` says what, without
        the node's name (the caller names the node)."""
        self.errors += 1
        self.last_error = text.removeprefix(f"F/T on {self.name}").lstrip(": ")

    def _request(self, opcode: int) -> int:
        import can  # python-can; only needed when a CAN node is used

        self._tag = (self._tag + 1) & 0xFF
        msg = can.Message(arbitration_id=self.base_id + CAN_LAYOUT["request"].offset, is_extended_id=False,
                          data=struct.pack(CAN_LAYOUT["request"].struct_fmt, opcode, self._tag))
        try:
            self.bus.send(msg, timeout=self.timeout_s)
        except can.CanError as err:
            raise LinkError(f"F/T on {self.name}: send failed: {err}") from err
        return self._tag

    def _recv(self, deadline: float, what: str) -> can.Message:
        import can

        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self._bad += 1
                raise PfmaTimeoutError(f"F/T on {self.name} did not answer {what} within {self.timeout_s:g} s")
            try:
                msg = self.bus.recv(timeout=left)
            except can.CanError as err:
                raise LinkError(f"F/T on {self.name}: receive failed: {err}") from err
            if msg is not None and not msg.is_extended_id and self.base_id < msg.arbitration_id <= self.base_id + 3:
                self._frames_in += 1
                return msg

    def _command(self, opcode: int, what: str) -> int:
        tag = self._request(opcode)
        deadline = time.monotonic() + self.timeout_s
        ack = CAN_LAYOUT["ack"]
        while True:
            msg = self._recv(deadline, what)
            if msg.arbitration_id == self.base_id + ack.offset and len(msg.data) == ack.dlc:
                op, rtag, result, depth = struct.unpack(ack.struct_fmt, bytes(msg.data))
                if op == opcode and rtag == tag:
                    if result != 0:
                        raise LinkError(f"F/T on {self.name} rejected {what} (result {result})")
                    return depth

    def _accept(self, status: int, c: tuple[int, ...]) -> FtReading:
        t = self.clock.now()
        # ignore: c is a tuple[int, ...] of exactly 6 counts (the forces and torques frames)
        r = FtReading(status=status, counts=tuple(c),  # type: ignore[arg-type]
                      force_n=(c[0] / self.cpf, c[1] / self.cpf, c[2] / self.cpf),
                      torque_nm=(c[3] / self.cpt, c[4] / self.cpt, c[5] / self.cpt), t_s=t, seq=self._seq)
        self._seq += 1
        self._records += 1
        self._rate.mark(t)
        self.latest = r
        return r
