"""Fake F/T sensor node on a CAN bus (project-defined layout, see docs/ft-protocol.md).

Runs as a python-can ``Listener`` under a ``Notifier`` on its own bus object (e.g. a
second ``virtual`` bus on the same channel), answering as frames arrive (a thread); or,
without a Notifier, answers what is waiting on its bus when told to (:meth:`pump`): on
python-can's ``virtual`` interface a send lands in the other buses' queues at once, so a
simulated-time test that pumps the node between service frames is deterministic.
Answers only the identifiers it owns.
Reuses ``FtTransducer`` (load -> counts, bias stack) from ``fakes.ft_sensor``.
"""

from __future__ import annotations

from collections import deque

import struct
from typing import Any

import can

from drivers.serial_ft.protocol import (CAN_LAYOUT, NOMINAL, OP_BIAS, OP_CLEAR_BIAS, OP_READ,
                                        OP_UNBIAS, NominalSensor, node_base_id)
from fakes.ft_sensor import FtTransducer, LoadFn


class FakeCanFtNode(can.Listener):
    """F/T node: answers read requests with two frames and bias commands with an ack.

    :param bus: the node's own bus object
    :param node_id: 0..15
    :param clock: optional clock whose ``now()`` is the sample time for ``load_fn``
    """

    def __init__(self, bus: Any, node_id: int, sensor: NominalSensor = NOMINAL,
                 load_fn: LoadFn | None = None, clock: Any = None) -> None:
        self.bus = bus
        self.node_id = node_id
        self.base_id = node_base_id(node_id)
        self.transducer = FtTransducer(sensor, load_fn)
        self.clock = clock
        self.seq = 0
        #: ground truth (status, counts), the newest 20,000 (a node answering for hours must not grow)
        self.sent: deque[tuple[int, tuple[int, ...]]] = deque(maxlen=20_000)
        self.mute_replies = 0  #: fault: ignore this many requests
        self.break_pairing = 0  #: fault: send this many replies with mismatched seq
        self._notifier: can.Notifier | None = None

    def set_load(self, force_n: tuple[float, float, float], torque_nm: tuple[float, float, float]) -> None:
        """Apply a constant load (N, N.m)."""
        self.transducer.set_load(force_n, torque_nm)

    def start(self) -> "FakeCanFtNode":
        self._notifier = can.Notifier(self.bus, [self], timeout=0.05)
        return self

    def stop(self) -> None:  # also called by Notifier.stop()
        if self._notifier is not None:
            n, self._notifier = self._notifier, None
            n.stop()

    def pump(self) -> int:
        """Answer every frame waiting on the node's bus now (no Notifier: the caller's
        thread); returns how many frames were read."""
        if self._notifier is not None:
            raise RuntimeError("pump() on a node whose Notifier reads the bus (one consumer per bus)")
        n = 0
        while (msg := self.bus.recv(timeout=0)) is not None:
            n += 1
            self.on_message_received(msg)
        return n

    def __enter__(self) -> "FakeCanFtNode":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def on_message_received(self, msg: can.Message) -> None:
        req = CAN_LAYOUT["request"]
        if msg.is_extended_id or msg.arbitration_id != self.base_id + req.offset or len(msg.data) != req.dlc:
            return
        opcode, tag = struct.unpack(req.struct_fmt, bytes(msg.data))
        if self.mute_replies:
            self.mute_replies -= 1
            return
        self.transducer.sample(self.clock.now() if self.clock else 0.0)  # one sample per request
        if opcode == OP_READ:
            status, c = self.transducer.reading()
            self.sent.append((status, c))
            seq = self.seq & 0xFF
            self.seq += 1
            seq_a = seq
            if self.break_pairing:
                self.break_pairing -= 1
                seq_a = (seq + 1) & 0xFF
            self._send("forces", struct.pack(CAN_LAYOUT["forces"].struct_fmt, *c[:3], status, seq_a))
            self._send("torques", struct.pack(CAN_LAYOUT["torques"].struct_fmt, *c[3:], seq, tag))
            return
        action = {OP_BIAS: self.transducer.bias, OP_UNBIAS: self.transducer.unbias,
                  OP_CLEAR_BIAS: self.transducer.clear_bias}.get(opcode)
        result = 0 if action else 1
        if action:
            action()
        self._send("ack", struct.pack(CAN_LAYOUT["ack"].struct_fmt, opcode, tag, result,
                                      len(self.transducer.biases)))

    def _send(self, kind: str, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=self.base_id + CAN_LAYOUT[kind].offset,
                                  is_extended_id=False, data=data))
