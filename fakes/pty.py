"""Run a byte-stream device model on the far side of a real pseudo-terminal.

The model is any object with ``receive(data: bytes)``, ``transmit(max_bytes: int) ->
bytes`` and ``advance(dt_s: float)`` (e.g. ``fakes.ft_sensor.FakeFtController``).
A thread owns the pty master: it feeds host bytes to the model, advances the model
in real time and writes at most ``baud / 10`` bytes per second (8N1), paced on
absolute deadlines, so the driver under test sees wire-rate data.

pty pitfalls handled here (the packages reference notes section 1): both ends
are set raw at once (no echo before the driver opens), the slave fd stays open for
the device's lifetime (no EIO on the master), and ``disconnect()`` closes the master
so the driver's read raises like a pulled USB adapter.

Usage::

    with PtyDevice(FakeFtController(), baud=19200) as dev:
        port = serial.serial_for_url(dev.port_name, baudrate=19200, timeout=0.05)
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from typing import Protocol


class ByteDeviceModel(Protocol):
    def receive(self, data: bytes) -> None: ...
    def transmit(self, max_bytes: int) -> bytes: ...
    def advance(self, dt_s: float) -> None: ...


class PtyDevice:
    """A device model behind a real pty, paced at ``baud`` (8N1).

    :param model: the byte-stream device model
    :param baud: line rate; bytes leave at most ``baud / 10`` per second
    :param tick_s: pacing/poll period of the device thread
    """

    BITS_PER_CHAR = 10
    MAX_BACKLOG_S = 0.05  # after a scheduling hiccup, catch up at most this much wire time

    def __init__(self, model: ByteDeviceModel, baud: int = 19200, tick_s: float = 0.001) -> None:
        self.model = model
        self.baud = baud
        self.tick_s = tick_s
        self._master, self._slave = os.openpty()
        tty.setraw(self._master)
        tty.setraw(self._slave)
        self.port_name: str = os.ttyname(self._slave)  #: the /dev/pts path the driver opens
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._noise = bytearray()
        self._drop = 0
        self._stall_until = 0.0
        self._disconnect = False
        self.bytes_written = 0  #: bytes put on the wire (including noise)
        self.bytes_read = 0  #: bytes received from the host
        self.error: BaseException | None = None  #: what ended the thread, if anything

    # -- life cycle ---------------------------------------------------------------------
    def start(self) -> "PtyDevice":
        """Start the device thread (idempotent)."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name=f"PtyDevice {self.port_name}", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and close both pty ends."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for attr in ("_master", "_slave"):
            fd = getattr(self, attr)
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
                setattr(self, attr, None)

    def __enter__(self) -> "PtyDevice":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- wire-level faults (apply to any model) -------------------------------------------
    def inject_noise(self, data: bytes) -> None:
        """Put ``data`` on the wire next, ahead of the model's output."""
        with self._lock:
            self._noise += data

    def drop_next(self, n: int) -> None:
        """Lose the next ``n`` bytes the model sends."""
        with self._lock:
            self._drop += int(n)

    def stall(self, seconds: float) -> None:
        """Send nothing for ``seconds`` (the model keeps running)."""
        with self._lock:
            self._stall_until = time.monotonic() + seconds

    def disconnect(self) -> None:
        """Close the master: the driver's next read fails like a pulled cable."""
        self._disconnect = True

    # -- thread ---------------------------------------------------------------------------
    def _run(self) -> None:
        byte_s = self.BITS_PER_CHAR / self.baud
        t_last = time.monotonic()
        wire_free_at = t_last  # absolute time the line finishes the bytes already sent
        try:
            while not self._stop.is_set():
                if self._disconnect or not getattr(self.model, "connected", True):
                    os.close(self._master)
                    self._master = None
                    return
                r, _, _ = select.select([self._master], [], [], self.tick_s)
                if r:
                    data = os.read(self._master, 4096)
                    self.bytes_read += len(data)
                    self.model.receive(data)
                now = time.monotonic()
                self.model.advance(now - t_last)
                t_last = now
                wire_free_at = max(wire_free_at, now - self.MAX_BACKLOG_S)
                budget = int((now - wire_free_at) / byte_s)
                if budget <= 0:
                    continue
                with self._lock:
                    if now < self._stall_until:
                        wire_free_at = now
                        continue
                    out = bytes(self._noise[:budget])
                    del self._noise[:budget]
                lost = 0
                if len(out) < budget:
                    data = self.model.transmit(budget - len(out))
                    with self._lock:
                        lost = min(self._drop, len(data))
                        self._drop -= lost
                    out += data[lost:]
                used_s = (len(out) + lost) * byte_s  # lost bytes used the line too
                if out:
                    os.write(self._master, out)
                    self.bytes_written += len(out)
                if len(out) + lost < budget:
                    wire_free_at = now + used_s  # the model ran dry: new bytes start now
                else:
                    wire_free_at += used_s
        except BaseException as err:  # noqa: BLE001 - reported through .error
            self.error = err
