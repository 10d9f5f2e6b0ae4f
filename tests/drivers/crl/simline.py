"""Test helper: a byte-stream device model on a REAL pty, stepped in simulated time.

The test owns the pty master and moves bytes itself, so the driver (pyserial on the
slave) and the model see exactly the bytes of each simulated tick, deterministically.
Waits are on data with timeouts (select), never sleeps. For a free-running model in
real time use ``fakes.pty.PtyDevice`` instead.
"""

from __future__ import annotations

import os
import select
import time
import tty

import serial

WAIT_S = 2.0  # generous bound for the kernel to move bytes across the pty


class SimPtyLink:
    def __init__(self, model, clock, baud: int = 19200) -> None:
        self.model = model
        self.clock = clock
        self.baud = baud
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)  # raw before anyone writes (no echo)
        self.port = serial.serial_for_url(os.ttyname(self.slave), baudrate=baud, timeout=0)

    def _wait(self, cond) -> None:
        deadline = time.monotonic() + WAIT_S
        while not cond():
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("pty did not deliver the bytes in time")
            select.select([self.port.fileno()], [], [], min(left, 0.01))

    def to_host(self, data: bytes) -> None:
        """Write ``data`` on the wire towards the driver and wait until it is readable."""
        if not data:
            return
        before = self.port.in_waiting
        os.write(self.master, data)
        self._wait(lambda: self.port.in_waiting >= before + len(data))

    def from_host(self, expect_bytes: int = 0) -> bytes:
        """Hand what the driver wrote to the model; wait for at least ``expect_bytes``."""
        got = bytearray()
        deadline = time.monotonic() + WAIT_S
        while True:
            r, _, _ = select.select([self.master], [], [], 0 if len(got) >= expect_bytes
                                    else max(0.0, deadline - time.monotonic()))
            if not r:
                break
            got += os.read(self.master, 4096)
        if len(got) < expect_bytes:
            raise TimeoutError(f"driver wrote {len(got)} bytes, expected {expect_bytes}")
        self.model.receive(bytes(got))
        return bytes(got)

    def step(self, dt_s: float) -> bytes:
        """One tick: host bytes to the model, time passes, the model's output to the host."""
        self.from_host()
        self.clock.advance(dt_s)
        self.model.advance(dt_s)
        data = self.model.transmit(int(dt_s * self.baud / 10))  # 8N1 wire budget
        self.to_host(data)
        return data

    def close(self) -> None:
        self.port.close()
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass
