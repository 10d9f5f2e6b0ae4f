"""An INDEPENDENT emulation of the Lord/ATI F/T controller serial protocol on a real pty.

Written only from the protocol facts below (copied from
the hardware-registers reference notes section 7 and its R7 notes, and from
docs/ft-protocol.md); it shares no code with the project's fake (fakes/ft_sensor.py)
nor with ``drivers.serial_ft.protocol``. Tests never read anything outside the repository at run time.

Protocol facts used (quoted/condensed from the sources)
------------------------------------------------------

Line editor (hardware-registers.md 7 "Framing", R7):
  * "All commands are ASCII terminated by CR. The controller echoes each command
    and prompts with ``>``."
  * R7: "Characters are echoed, and CR ends a command. The reply is ``\\r\\n`` plus
    any output plus ``\\r\\n>``."  (So the CR itself is not echoed as a lone CR: the
    reply's CR LF follows the echoed characters.)
  * docs/ft-protocol.md: "Unknown commands: ... answers ``ERROR: unknown command ...``
    (text assumed); the driver raises LinkError for any output starting with ERROR."

Commands (section 7 command summary; docs/ft-protocol.md command table):
  * ``CD A`` / ``CD B``: ASCII (power-up default) / binary output records.
  * ``CD E`` / ``CD U``: append a checksum to binary output / no checksum (default).
  * ``CD R``: resolved F/T data (default) - accepted, no other data kinds emulated.
  * ``QR``: output one record in the current mode, with echo and prompt.
    docs: "QR output is one record without its own CR LF (the prompt's CR LF ends it;
    assumed)."
  * Ctrl-T (0x14): one record "with minimized handshaking", no echo, no prompt
    (mrrocpp ``"\\024"``). An ASCII record keeps its own CR LF (it is "the record").
  * ``QS``: "stream records continuously; any character received stops the stream
    (drivers send CR)". "After QS, drivers read the 4-5 byte echo (``QS\\r\\n``)
    before the stream starts." "To stop a stream they send CR and flush until
    ``\\r\\n\\r\\n>`` is seen." docs (assumption list): "the character that stops QS
    is consumed"; the controller then answers an empty command line, i.e.
    CR LF + CR LF ``>``. A record already on the wire is completed first (a UART
    does not cut a character stream mid-record in this emulation).
  * ``SB``: "sensor bias: store the current reading in a 3-level bias buffer";
    ``SU``: "unbias: pop the last bias"; ``SZ``: "clear all biases". R7: "keep a
    3-deep bias stack subtracted from the reported counts". Here the stack holds
    raw readings and the top entry is subtracted (SB, SB, SU gives back the first
    bias). A 4th SB drops the oldest entry (docs: assumed).
  * ``SA d``: "moving average over d samples (default 0)" (0 and 1 = off).

Record formats (section 7 "Record formats", R7, docs "Record formats"):
  * ASCII: "status as ``%d``, then six ``,%6d`` fields (Fx Fy Fz Tx Ty Tz counts),
    CR LF"; 45 bytes for status < 10. Example (sourced):
    ``0,  -102,   -99,  -225,   -20,    39,   -39\\r\\n``.
  * binary: "1 status byte, then 6 x int16 big-endian counts" (13 bytes; sourced by
    the capture ``00 FF93 FF98 FE69 FFBB 0006 FFDB``), "then an optional checksum
    byte". Checksum (ASSUMED, R7): "the low 7 bits of the sum of the preceding
    record bytes".
  * Status: 0 = OK (sourced); 0x01 = overload, any axis above 110 % of full scale
    (assumed; nominal range +-133 N, +-11.3 N.m).
  * Scaling: "Report counts only, never engineering units, over the wire";
    engineering value = counts / CPF (force) or / CPT (torque).

Pacing (section 7 "Maximum record rate at 19200 baud", R7 "Pacing"):
  * "19200 baud at 8N1 is 10 bits per character, i.e. 1920 characters per second."
    Binary 13 B -> 147.7 records/s, with checksum 14 B -> 137.1, ASCII 45 B -> 42.7.
  * "Emit records no faster than the 19200-baud byte rate allows."

Emulation choices (not protocol facts)
--------------------------------------

* Each record output (stream, QR, Ctrl-T) takes one new sample. By default the
  ``counter_axis`` (Tz) carries a per-sample counter instead of the load, so that
  every record is distinct; its bytes are never 0x00/0x01 (never a plausible status
  byte), so framing slips are detected deterministically.
* Faults: :meth:`IndependentFtController.inject_noise` and :meth:`drop_bytes` act on
  record ``k`` of the next/current QS stream at byte ``offset`` of that record. The
  ground truth (:attr:`sent`) holds every record put on the wire, with the intended
  counts, the actual wire bytes and whether the record was damaged.
* Output bytes are written on absolute deadlines ``t_line += 1/1920``; a late thread
  catches up, an idle line restarts at "now". Both pty ends are raw and the slave fd
  stays open for the emulator's lifetime.
"""

from __future__ import annotations

import os
import select
import struct
import threading
import time
import tty
from collections import deque
from dataclasses import dataclass, field

CR = 0x0D
LF = 0x0A
CTRL_T = 0x14


def ascii_record(status: int, counts) -> bytes:
    """``%d`` status, six ``,%6d`` count fields, CR LF (section 7 / R7)."""
    return ("%d" % status + "".join(",%6d" % c for c in counts)).encode("ascii") + b"\r\n"


def binary_record(status: int, counts, checksum: bool) -> bytes:
    """Status byte + six int16 big-endian counts (+ low 7 bits of the byte sum)."""
    body = bytes([status & 0xFF]) + b"".join(struct.pack(">h", c) for c in counts)
    return body + bytes([sum(body) & 0x7F]) if checksum else body


def counter_counts(k: int) -> int:
    """A per-sample counter value whose two bytes are never 0x00/0x01/CR/LF/'>':
    high byte 0x03..0x08, low byte 0x10..0xEF (1344 distinct values, then it wraps)."""
    return (0x03 + (k // 0xE0) % 6) * 0x100 + 0x10 + k % 0xE0


@dataclass
class SentRecord:
    """One record the emulator put on the wire."""

    n: int  #: running number over all records
    kind: str  #: "stream", "qr" or "poll"
    mode: str  #: "ascii" or "binary"
    status: int
    counts: tuple  #: the counts the record encodes (before any fault)
    wire: bytes  #: bytes actually sent (after faults)
    damaged: bool  #: a fault changed bytes inside the record
    stream_index: int | None  #: index within its QS stream
    t_s: float = 0.0  #: time.monotonic() when its last byte was written
    t_due: float = 0.0  #: the pacing deadline of its last byte (absolute schedule)


@dataclass
class _Fault:
    kind: str  # "noise" or "drop"
    record: int
    offset: int
    data: bytes = b""
    n: int = 0


@dataclass
class _Pending:
    """Output not yet on the wire, with the records ending at given positions."""

    data: bytearray = field(default_factory=bytearray)
    marks: deque = field(default_factory=deque)  # (end position in total bytes, SentRecord)


class IndependentFtController:
    """F/T controller emulator behind a pty. Use as a context manager or start()/stop().

    :param cpf: counts per newton; :param cpt: counts per newton-metre
    :param counter_axis: axis (0..5) that carries the per-sample counter, or None
    :param baud: line rate (8N1: baud/10 bytes/s)
    :param range_n / range_nm: full scale per axis, for the overload status
    """

    def __init__(self, cpf: float = 16.0, cpt: float = 200.0, counter_axis: int | None = 5,
                 baud: int = 19200, range_n: float = 133.0, range_nm: float = 11.3) -> None:
        self.cpf = cpf
        self.cpt = cpt
        self.counter_axis = counter_axis
        self.byte_time = 10.0 / baud
        self.full_scale = (range_n * cpf,) * 3 + (range_nm * cpt,) * 3
        # controller state
        self.mode = "ascii"  # power-up defaults: CD A, CD U
        self.checksum_on = False
        self.streaming = False
        self.average_n = 0
        self.biases: list[tuple] = []
        self.commands: list[str] = []  #: line commands received (text before CR)
        self.ctrl_t_count = 0
        self.sent: list[SentRecord] = []  #: ground truth, in wire order
        self.noise_bytes_sent = 0
        self.bytes_dropped = 0
        self.overrun_bytes = 0  #: bytes lost because the pty buffer was full
        self._load = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        self._samples: deque[tuple] = deque(maxlen=1000)
        self._sample_no = 0
        self._record_no = 0
        self._line = bytearray()
        self._stop_requested = False
        self._stream_index = 0
        self._faults: list[_Fault] = []
        self._out = _Pending()
        self._written = 0
        self._queued = 0
        self._t_line = 0.0
        self._continuous = False
        self._lock = threading.RLock()
        self._cond = threading.Condition(self._lock)
        self._quit = threading.Event()
        self._thread: threading.Thread | None = None
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.port_name = os.ttyname(self.slave)

    # -- test-side API ------------------------------------------------------------------------
    def set_load(self, force_n=(0.0, 0.0, 0.0), torque_nm=(0.0, 0.0, 0.0)) -> None:
        with self._lock:
            self._load = tuple(force_n) + tuple(torque_nm)

    def inject_noise(self, data: bytes, record: int, offset: int = 0) -> None:
        """Insert ``data`` before byte ``offset`` of record ``record`` of the next QS stream."""
        with self._lock:
            self._faults.append(_Fault("noise", record, offset, data=bytes(data)))

    def drop_bytes(self, n: int, record: int, offset: int = 0) -> None:
        """Drop ``n`` bytes from byte ``offset`` of record ``record`` of the next QS stream."""
        with self._lock:
            self._faults.append(_Fault("drop", record, offset, n=n))

    def stream_records(self) -> list[SentRecord]:
        with self._lock:
            return [r for r in self.sent if r.kind == "stream"]

    def wait_idle(self, timeout_s: float = 2.0) -> bool:
        """Wait until every queued byte is on the wire."""
        with self._cond:
            return self._cond.wait_for(lambda: self._written >= self._queued and not self.streaming, timeout_s)

    def start(self) -> "IndependentFtController":
        self._thread = threading.Thread(target=self._run, name="independent-ft", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._quit.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> "IndependentFtController":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- controller model ----------------------------------------------------------------------
    def _sample(self) -> tuple[int, tuple]:
        """Take one sample: (status, reported counts)."""
        load = self._load
        raw = [round(load[i] * (self.cpf if i < 3 else self.cpt)) for i in range(6)]
        if self.counter_axis is not None:
            raw[self.counter_axis] = counter_counts(self._sample_no)
        self._sample_no += 1
        raw_t = tuple(raw)
        self._samples.append(raw_t)
        if self.average_n > 1:
            window = list(self._samples)[-self.average_n:]
            raw_t = tuple(round(sum(s[i] for s in window) / len(window)) for i in range(6))
        status = 1 if any(abs(raw_t[i]) > 1.10 * self.full_scale[i] for i in range(6)) else 0
        bias = self.biases[-1] if self.biases else (0,) * 6
        counts = tuple(max(-32768, min(32767, raw_t[i] - bias[i])) for i in range(6))
        self._current_raw = raw_t
        return status, counts

    def _current_reading(self) -> tuple:
        """The reading SB stores: a fresh sample, before bias."""
        self._sample()
        return self._current_raw

    def _record(self, kind: str, with_terminator: bool = True) -> None:
        status, counts = self._sample()
        if self.mode == "binary":
            wire = binary_record(status, counts, self.checksum_on)
        else:
            wire = ascii_record(status, counts)
            if not with_terminator:
                wire = wire[:-2]
        damaged = False
        sidx = None
        if kind == "stream":
            sidx = self._stream_index
            self._stream_index += 1
            wire, damaged = self._apply_faults(sidx, wire)
        rec = SentRecord(self._record_no, kind, self.mode, status, counts, bytes(wire), damaged, sidx)
        self._record_no += 1
        self._queue(wire, rec)

    def _apply_faults(self, sidx: int, wire: bytes) -> tuple[bytes, bool]:
        damaged = False
        for f in [f for f in self._faults if f.record == sidx]:
            self._faults.remove(f)
            if f.kind == "noise":
                wire = wire[:f.offset] + f.data + wire[f.offset:]
                self.noise_bytes_sent += len(f.data)
                damaged = damaged or 0 < f.offset < len(wire) - len(f.data)
            else:
                cut = wire[f.offset:f.offset + f.n]
                wire = wire[:f.offset] + wire[f.offset + f.n:]
                self.bytes_dropped += len(cut)
                damaged = damaged or bool(cut)
        return wire, damaged

    def _queue(self, data: bytes, rec: SentRecord | None = None) -> None:
        if not data:
            return
        if self._written >= self._queued and not self._continuous:  # idle line: restart at "now"
            self._t_line = max(self._t_line, time.monotonic())
        self._out.data += data
        self._queued += len(data)
        if rec is not None:
            self._out.marks.append((self._queued, rec))

    def _reply(self, output: bytes = b"") -> None:
        self._queue(b"\r\n" + output + b"\r\n>")

    def _on_byte(self, b: int) -> None:
        if self.streaming:  # any character stops the stream; it is consumed
            self._stop_requested = True
            return
        if b == CTRL_T:
            self.ctrl_t_count += 1
            self._record("poll")
            return
        if b == LF:
            return
        if b != CR:
            self._line.append(b)
            self._queue(bytes([b]))  # echo
            return
        text = self._line.decode("ascii", "replace").strip()
        self._line.clear()
        self.commands.append(text)
        self._execute(text)

    def _execute(self, text: str) -> None:
        cmd = " ".join(text.upper().split())
        if cmd in ("CD A", "CD B"):
            self.mode = "ascii" if cmd == "CD A" else "binary"
        elif cmd in ("CD E", "CD U"):
            self.checksum_on = cmd == "CD E"
        elif cmd == "CD R":
            pass
        elif cmd == "QR":
            self._queue(b"\r\n")
            self._record("qr", with_terminator=False)
            self._queue(b"\r\n>")
            return
        elif cmd == "QS":
            self._queue(b"\r\n")
            self.streaming = True
            self._stop_requested = False
            self._stream_index = 0
            return
        elif cmd == "SB":
            self.biases.append(self._current_reading())
            del self.biases[:-3]
        elif cmd == "SU":
            if self.biases:
                self.biases.pop()
        elif cmd == "SZ":
            self.biases.clear()
        elif cmd.startswith("SA ") and cmd[3:].isdigit():
            self.average_n = int(cmd[3:])
        elif cmd == "":
            pass
        else:
            self._reply(f"ERROR: unknown command {text}".encode("ascii", "replace"))
            return
        self._reply()

    # -- the wire --------------------------------------------------------------------------------
    def _run(self) -> None:
        while not self._quit.is_set():
            with self._lock:
                if self._written < self._queued:
                    wait = max(0.0, self._t_line - time.monotonic())
                else:
                    wait = 0.05
            try:
                r, _, _ = select.select([self.master], [], [], wait)
            except (OSError, ValueError):
                return
            with self._cond:
                if r:
                    try:
                        data = os.read(self.master, 4096)
                    except BlockingIOError:
                        data = b""
                    except OSError:
                        return
                    for b in data:
                        self._on_byte(b)
                self._pump()
                self._cond.notify_all()

    def _pump(self) -> None:
        """Write every byte whose deadline has come; keep a stream's line busy."""
        while True:
            if self._written >= self._queued and self.streaming:
                # back to back: the next record's first byte follows the last one's
                # deadline (no restart at "now"), so a late thread catches up
                self._continuous = True
                if self._stop_requested:
                    self.streaming = False
                    self._queue(b"\r\n\r\n>")
                else:
                    self._record("stream")
                self._continuous = False
            now = time.monotonic()
            due = 0
            t = self._t_line
            while due < len(self._out.data) and t <= now:
                due += 1
                t += self.byte_time
            if due == 0:
                return
            chunk = bytes(self._out.data[:due])
            try:
                n = os.write(self.master, chunk)
            except BlockingIOError:
                n = 0
            except OSError:
                return
            self.overrun_bytes += due - n  # the receiver's buffer was full: bytes lost
            del self._out.data[:due]
            first, t_first = self._written, self._t_line
            self._written += due
            self._t_line = t
            stamp = time.monotonic()
            while self._out.marks and self._out.marks[0][0] <= self._written:
                end, rec = self._out.marks.popleft()
                rec.t_s = stamp
                rec.t_due = t_first + (end - 1 - first) * self.byte_time
                self.sent.append(rec)
