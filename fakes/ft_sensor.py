"""Fake Lord/ATI F/T controller: a byte-stream state machine per R7.

No threads, no ptys: the owner moves bytes and time. ``receive(data)`` takes what
the host sent, ``transmit(max_bytes)`` returns what is ready on the wire (at most
``max_bytes``; the owner paces it at the baud rate), ``advance(dt_s)`` moves the
controller's own time (internal sampling). The same object runs behind
``fakes.pty.PtyDevice`` (a real pty) or on the fake MVME400 serial channel.

Protocol facts: the hardware-registers reference notes section 7 and R7, via
the shared table ``drivers.serial_ft.protocol`` (fakes may import protocol tables,
as they import ``registers.py`` tables; never a driver).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

from fakes.byteline import FaultyLine
from drivers.serial_ft.protocol import (CR, CRLF, CTRL_T, NOMINAL, PROMPT, NominalSensor,
                                        encode_ascii, encode_binary)

Vec3 = tuple[float, float, float]
LoadFn = Callable[[float], tuple[Vec3, Vec3]]  # t_s -> (force_n, torque_nm)

BIAS_DEPTH = 3  #: sourced: "3-level bias buffer" (ATI command summary)


#: records of ground truth a fake F/T controller keeps (newest first out): 25 s at 80 Hz, more
#: than any test compares; a soak of the simulated stack then levels off within its first minute
HISTORY_KEEP = 2_000

class FtTransducer:
    """Load -> counts, with the controller's moving average and 3-deep bias stack.

    :param sensor: scale and range (default: the nominal, assumed sensor)
    :param load_fn: optional ``t_s -> (force_n, torque_nm)``; otherwise ``set_load``
    """

    def __init__(self, sensor: NominalSensor = NOMINAL, load_fn: LoadFn | None = None) -> None:
        self.sensor = sensor
        self.load_fn = load_fn
        self._force_n: Vec3 = (0.0, 0.0, 0.0)
        self._torque_nm: Vec3 = (0.0, 0.0, 0.0)
        self.average_n = 0
        self.biases: list[tuple[int, ...]] = []
        self._window: deque[tuple[int, ...]] = deque(maxlen=1)
        self._status = 0
        self.sample(0.0)

    def set_load(self, force_n: Vec3, torque_nm: Vec3) -> None:
        """Apply a constant load (N, N.m); clears ``load_fn``."""
        self.load_fn = None
        self._force_n = tuple(float(v) for v in force_n)  # type: ignore[assignment]
        self._torque_nm = tuple(float(v) for v in torque_nm)  # type: ignore[assignment]

    def sample(self, t_s: float) -> None:
        """Take one sample of the load at time ``t_s`` into the averaging window."""
        if self.load_fn is not None:
            self._force_n, self._torque_nm = self.load_fn(t_s)
        s = self.sensor
        fs = [s.range_force_n] * 3 + [s.range_torque_nm] * 3
        vals = list(self._force_n) + list(self._torque_nm)
        self._status = 1 if any(abs(v) > s.overload_fraction * f for v, f in zip(vals, fs)) else 0
        raw = tuple(round(v * s.cpf) for v in self._force_n) + tuple(round(v * s.cpt) for v in self._torque_nm)
        self._window.append(raw)

    def set_average(self, n: int) -> None:
        """``SA n``: moving average over n samples (0 or 1 = off)."""
        n = max(1, int(n))
        self.average_n = int(n) if n > 1 else 0
        last = self._window[-1]
        self._window = deque([last], maxlen=n)

    def averaged(self) -> tuple[int, ...]:
        """Moving average of the window (counts, before bias)."""
        w = self._window
        return tuple(int(round(sum(c[i] for c in w) / len(w))) for i in range(6))

    def reading(self) -> tuple[int, tuple[int, ...]]:
        """(status, counts) as the controller reports them: averaged, minus the top bias."""
        avg = self.averaged()
        if self.biases:
            avg = tuple(a - b for a, b in zip(avg, self.biases[-1]))
        return self._status, tuple(max(-32768, min(32767, c)) for c in avg)

    def bias(self) -> None:
        """``SB``: push the current averaged reading (the oldest of 3 is dropped, assumed)."""
        self.biases.append(self.averaged())
        del self.biases[:-BIAS_DEPTH]

    def unbias(self) -> None:
        """``SU``: pop the last bias (no-op when empty)."""
        if self.biases:
            self.biases.pop()

    def clear_bias(self) -> None:
        """``SZ``: clear all biases."""
        self.biases.clear()


@dataclass
class SentRecord:
    """Ground truth: one record the controller put on the wire."""

    index: int
    status: int
    counts: tuple[int, ...]
    t_s: float  #: controller time when the record was encoded


class FakeFtController(FaultyLine):
    """Byte-stream model of the F/T controller (R7 line editor, QS/Ctrl-T, SB/SU/SZ, SA).

    :param sensor: nominal sensor (scale, range, internal sample rate)
    :param load_fn: optional ``t_s -> (force_n, torque_nm)`` (e.g. the arm model's contact)
    :param sample_rate_hz: internal sampling; default ``sensor.sample_rate_hz`` (150 Hz)
    """

    def __init__(self, sensor: NominalSensor = NOMINAL, load_fn: LoadFn | None = None,
                 sample_rate_hz: float | None = None) -> None:
        self.transducer = FtTransducer(sensor, load_fn)
        self.sample_period_s = 1.0 / (sample_rate_hz or sensor.sample_rate_hz)
        self.t_s = 0.0
        self._next_sample_s = self.sample_period_s
        self.mode = "ascii"  #: "ascii" (default) or "binary"
        self.checksum_on = False
        self.streaming = False
        self._pending = False  # a new sample is waiting for the line
        self._line = bytearray()
        self._init_line()
        #: ground truth: the newest records sent (bounded: HISTORY_KEEP: 25 s of a streaming line, so a
        #: long-running simulated rack does not grow; the tests compare far fewer)
        self.sent_records: deque[SentRecord] = deque(maxlen=HISTORY_KEEP)
        self.records_sent = 0
        self.skipped_samples = 0  #: samples overwritten because the line was busy
        self.commands: list[str] = []  #: command log (the host's commands: a handful per session)

    # -- load ---------------------------------------------------------------------------
    def set_load(self, force_n: Vec3, torque_nm: Vec3) -> None:
        """Apply a constant load (N, N.m) from the next sample on."""
        self.transducer.set_load(force_n, torque_nm)

    @property
    def load_fn(self) -> LoadFn | None:
        return self.transducer.load_fn

    @load_fn.setter
    def load_fn(self, fn: LoadFn | None) -> None:
        self.transducer.load_fn = fn

    # -- device interface -----------------------------------------------------------------
    def advance(self, dt_s: float) -> None:
        """Move controller time by ``dt_s``: take the internal samples that fall in it."""
        self.t_s += dt_s
        while self._next_sample_s <= self.t_s:
            self.transducer.sample(self._next_sample_s)
            self._next_sample_s += self.sample_period_s
            if self.streaming:
                if self._pending:
                    self.skipped_samples += 1
                self._pending = True

    def receive(self, data: bytes) -> None:
        """Bytes from the host (line editor: echo, CR ends a command)."""
        if not self.connected:
            return
        for b in data:
            ch = bytes([b])
            if self.streaming:  # any character stops the stream and is consumed
                self.streaming = False
                self._pending = False
                if ch == CR:
                    self._tx += CRLF + PROMPT
                continue
            if ch == CTRL_T:
                self._tx += self._record(with_terminator=True)
            elif ch == CR:
                self._execute(self._line.decode("ascii", "replace").strip())
                self._line.clear()
            elif ch == b"\n":
                continue
            elif ch in (b"\x08", b"\x7f"):
                if self._line:
                    self._line.pop()
                    self._tx += b"\x08 \x08"
            else:
                self._line += ch
                self._tx += ch

    def _quiet_until_s(self) -> float | None:
        """Streaming: the next internal sample (a pending one goes out now); else only a
        received character makes output (a command's echo and answer)."""
        if not self.streaming:
            return math.inf
        return self.t_s if self._pending else self._next_sample_s

    def _refill(self) -> None:
        if self.streaming and self._pending:  # the newest sample, when the line is free
            self._tx += self._record(with_terminator=True)
            self._pending = False

    # -- internals --------------------------------------------------------------------------
    def _record(self, with_terminator: bool) -> bytes:
        status, counts = self.transducer.reading()
        self.sent_records.append(SentRecord(self.records_sent, status, counts, self.t_s))
        self.records_sent += 1
        if self.mode == "binary":
            return encode_binary(status, counts, self.checksum_on)
        return encode_ascii(status, counts, CRLF if with_terminator else b"")

    def _execute(self, line: str) -> None:
        self.commands.append(line)
        words = line.upper().split()
        out = b""
        cmd = words[0] if words else ""
        arg = words[1] if len(words) > 1 else ""
        if cmd == "":
            pass
        elif cmd == "CD" and arg in ("A", "B", "E", "U", "R"):
            if arg in "AB":
                self.mode = "ascii" if arg == "A" else "binary"
            elif arg in "EU":
                self.checksum_on = arg == "E"
        elif cmd == "QR" and not arg:
            out = self._record(with_terminator=False)
        elif cmd == "QS" and not arg:
            self._tx += CRLF
            self.streaming = True
            self._pending = True
            return
        elif cmd == "SB":
            self.transducer.bias()
        elif cmd == "SU":
            self.transducer.unbias()
        elif cmd == "SZ":
            self.transducer.clear_bias()
        elif cmd == "SA" and arg.isdigit():
            self.transducer.set_average(int(arg))
        else:
            out = f"ERROR: unknown command {line!r}".encode("ascii", "replace")  # assumed text
        self._tx += CRLF + out + PROMPT


def gentle_load(t_s: float) -> tuple[Vec3, Vec3]:
    """A slowly varying, plausible wrist load (tool weight plus a little motion)."""
    force = (8.0 * math.sin(0.7 * t_s), 5.0 * math.cos(0.45 * t_s), -14.7 + 2.0 * math.sin(0.3 * t_s))
    torque = (0.6 * math.sin(0.5 * t_s), -0.4 * math.cos(0.35 * t_s), 0.1 * math.sin(1.1 * t_s))
    return force, torque
