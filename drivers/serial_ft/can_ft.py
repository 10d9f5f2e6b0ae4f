"""F/T sensor over CAN (python-can), producing the same ``FtReading`` as the serial driver.

No public Lord/ATI CAN layout could be consulted here. ATI's CAN F/T interfaces are
recalled (unverified) to answer one read request with the gauge values split over
two data frames; this PROJECT-DEFINED layout keeps that shape. Its one table, ``CAN_LAYOUT``, lives in
``protocol.py`` (shared with the fake node, re-exported here) and in docs/ft-protocol.md;
change both when the real node's layout is known.

Identifiers are 11-bit: ``base = 0x100 + 0x10 * node_id`` (node 0..15).
"""

from __future__ import annotations

import struct
import time
from typing import TYPE_CHECKING

from pfma.clock import Clock, MonotonicClock
from pfma.errors import ConfigError, LinkError, PfmaTimeoutError
from drivers.ratewindow import RateWindow

from .ftsensor import FtReading, LinkStats
from .protocol import (CAN_BASE_ID, CAN_LAYOUT, CAN_NODE_STRIDE, MAX_NODE_ID, NOMINAL,  # noqa: F401
                       OP_BIAS, OP_CLEAR_BIAS, OP_READ, OP_UNBIAS, STATUS_CODES, CanFrameLayout,
                       frame_id, node_base_id)

if TYPE_CHECKING:
    import can  # python-can, imported by whoever opens the bus


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

    def read(self) -> FtReading:
        """Request one record; pair the forces and torques frames by seq and tag.

        :raises PfmaTimeoutError: no complete answer within ``timeout_s``
        :raises LinkError: the bus failed
        """
        tag = self._request(OP_READ)
        forces = None
        deadline = time.monotonic() + self.timeout_s
        while True:
            msg = self._recv(deadline, "read")
            if msg.arbitration_id == self.base_id + CAN_LAYOUT["forces"].offset and len(msg.data) == 8:
                forces = struct.unpack(CAN_LAYOUT["forces"].struct_fmt, bytes(msg.data))
            elif msg.arbitration_id == self.base_id + CAN_LAYOUT["torques"].offset and len(msg.data) == 8:
                tx, ty, tz, seq, rtag = struct.unpack(CAN_LAYOUT["torques"].struct_fmt, bytes(msg.data))
                if rtag != tag:
                    continue  # a late answer to an earlier request
                if forces is None or forces[4] != seq or forces[3] not in STATUS_CODES:
                    self._bad += 1
                    raise LinkError(f"F/T on {self.name}: forces/torques frames do not pair "
                                    f"(seq {seq}, forces {forces}); record discarded")
                return self._accept(forces[3], forces[:3] + (tx, ty, tz))

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
