"""Driver for the Lord/ATI F/T controller over any pyserial-like byte port.

``port`` is anything with ``read(n)``, ``write(b)``, ``timeout``, ``in_waiting`` and
``reset_input_buffer()``: a ``serial.Serial`` from ``serial.serial_for_url`` (device,
pty, ``socket://``, ``rfc2217://``, ``loop://``) or the MVME400 byte port. The
protocol table and codecs are in ``drivers.serial_ft.protocol``.

Timestamps come from the injected clock. A bounded wait ends when ``reply_timeout_s``
has passed on the real clock OR on the injected clock: real ports wait in real time,
a port on a simulated line (the fake MVME400) advances the simulated clock.
"""

from __future__ import annotations

import threading
import time
import warnings
from collections import deque
from dataclasses import dataclass
from typing import Any, Protocol

from pfma.clock import Clock, MonotonicClock
from pfma.errors import ConfigError, LinkError, PfmaTimeoutError
from drivers.ratewindow import RateWindow

from . import protocol as P


class BytePort(Protocol):
    """The part of pyserial's interface the driver uses."""

    timeout: float | None

    def read(self, size: int = 1) -> bytes: ...
    def write(self, data: bytes) -> int | None: ...
    @property
    def in_waiting(self) -> int: ...
    def reset_input_buffer(self) -> None: ...


@dataclass(frozen=True)
class FtReading:
    """One F/T record."""

    status: int  #: controller status (0 = OK; see protocol.STATUS_CODES)
    counts: tuple[int, int, int, int, int, int]  #: Fx, Fy, Fz, Tx, Ty, Tz in counts
    force_n: tuple[float, float, float]  #: counts / cpf
    torque_nm: tuple[float, float, float]  #: counts / cpt
    t_s: float  #: clock time when the record's last byte was decoded
    seq: int  #: driver's running number of accepted records


@dataclass(frozen=True)
class LinkStats:
    """Link statistics of one F/T link."""

    records: int  #: records accepted
    bad_records: int  #: records rejected (framing, status, checksum, length)
    resyncs: int  #: times framing was regained
    rate_hz: float  #: accepted records per second over the sliding window
    age_s: float | None  #: time since the last record (None before the first)
    bytes_in: int  #: bytes received
    bytes_discarded: int = 0  #: bytes thrown away while hunting for framing


UNSAFE_BINARY_STREAM = (
    "F/T on {name}: binary QS stream without checksum cannot detect a framing slip reliably "
    "(records have no sync byte; a shifted record whose first byte is 0x00 passes). "
    "Use set_checksum(True) or Ctrl-T polling (FtReader framing='poll').")


def _port_label(port: Any) -> str:
    return str(getattr(port, "port", None) or getattr(port, "name", None) or type(port).__name__)


class FtSensor:
    """Lord/ATI F/T controller driver.

    :param port: pyserial-like byte port (see module docstring)
    :param cpf: counts per newton (default: assumed nominal sensor, ``protocol.NOMINAL``)
    :param cpt: counts per newton-metre (default: assumed nominal sensor)
    :param clock: timestamps (default ``MonotonicClock``)
    :param baud: line rate, used for the rate check (the port's own rate is not changed)
    :param reply_timeout_s: bound on every command reply
    :param rate_window_s: sliding window for ``rate_hz``
    :param resync_records: whole valid binary records the stream decoder needs to regain
        framing after a bad one (default: 1 with the checksum, 2 without; see
        ``protocol.BinaryStreamDecoder``)
    :raises ConfigError: when cpf/cpt are not positive
    """

    def __init__(self, port: BytePort, *, cpf: float = P.NOMINAL.cpf, cpt: float = P.NOMINAL.cpt,
                 clock: Clock | None = None, baud: int = P.DEFAULT_BAUD, reply_timeout_s: float = 0.5,
                 rate_window_s: float = 1.0, resync_records: int | None = None) -> None:
        if not (cpf > 0 and cpt > 0):
            raise ConfigError(f"F/T sensor on {_port_label(port)}: cpf and cpt must be > 0 (got {cpf}, {cpt})")
        self.port = port
        if getattr(port, "timeout", 0) is None:  # a blocking port would defeat the bounded waits
            port.timeout = 0.05
        self.cpf = float(cpf)
        self.cpt = float(cpt)
        self.clock = clock or MonotonicClock()
        self.baud = baud
        self.reply_timeout_s = reply_timeout_s
        self.mode = "ascii"  # controller power-up defaults (CD A, CD U)
        self.checksum_on = False
        self.streaming = False
        self.latest: FtReading | None = None  #: last accepted reading (atomic reference)
        self._stats = P.DecoderStats()
        self._seq = 0
        self._rate = RateWindow(rate_window_s)
        self.resync_records = resync_records
        self._decoder: P.AsciiStreamDecoder | P.BinaryStreamDecoder = self._new_decoder()
        self.name = _port_label(port)

    # -- rates ----------------------------------------------------------------------------
    @staticmethod
    def max_rate_hz(mode: str, baud: int = P.DEFAULT_BAUD, checksum_on: bool = False) -> float:
        """Most records/s the line carries in ``mode`` at ``baud`` (8N1)."""
        return P.max_rate_hz(mode, baud, checksum_on)

    def check_rate(self, rate_hz: float, on_slow: str = "raise") -> float:
        """Compare ``rate_hz`` with what the line allows in the current mode.

        :param on_slow: "raise" (ConfigError), "warn" (RuntimeWarning) or "ignore"
        :returns: the line's maximum record rate
        :raises ConfigError: when the line is too slow and ``on_slow == "raise"``
        """
        limit = self.max_rate_hz(self.mode, self.baud, self.checksum_on)
        if rate_hz > limit:
            msg = (f"F/T on {self.name}: {self.mode.upper()} at {self.baud} baud gives at most "
                   f"{limit:.1f} records/s, below the {rate_hz:g} Hz the rack samples at; "
                   f"use binary mode (CD B) or a faster baud rate")
            if on_slow == "raise":
                raise ConfigError(msg)
            if on_slow == "warn":
                warnings.warn(msg, RuntimeWarning, stacklevel=3)
        return limit

    # -- configuration commands -------------------------------------------------------------
    def set_mode(self, mode: str) -> None:
        """``CD A`` / ``CD B``: ASCII or binary records."""
        if mode not in ("ascii", "binary"):
            raise ValueError(f"F/T mode must be 'ascii' or 'binary', not {mode!r}")
        self.command(P.COMMANDS[mode].text)
        self.mode = mode
        self._decoder = self._new_decoder()

    def set_checksum(self, on: bool) -> None:
        """``CD E`` / ``CD U``: checksum byte on binary records (algorithm assumed, R7)."""
        self.command(P.COMMANDS["checksum_on" if on else "checksum_off"].text)
        self.checksum_on = bool(on)
        self._decoder = self._new_decoder()

    def bias(self) -> None:
        """``SB``: push the current reading onto the controller's 3-level bias stack."""
        self.command(P.COMMANDS["bias"].text)

    def unbias(self) -> None:
        """``SU``: pop the last bias."""
        self.command(P.COMMANDS["unbias"].text)

    def clear_bias(self) -> None:
        """``SZ``: clear all biases."""
        self.command(P.COMMANDS["clear_bias"].text)

    def set_average(self, n: int) -> None:
        """``SA n``: moving average over ``n`` samples (0 = off)."""
        if not isinstance(n, int) or not 0 <= n <= 999:
            raise ValueError(f"F/T average must be an integer 0..999, not {n!r}")
        self.command(P.COMMANDS["average"].text.format(n=n))

    # -- records ----------------------------------------------------------------------------
    def query(self) -> FtReading:
        """``QR``: one record with echo and prompt.

        :raises LinkError: garbled or corrupt reply; :raises PfmaTimeoutError: no reply
        """
        body_len = P.record_bytes("binary", self.checksum_on) if self.mode == "binary" else None
        body = self.command(P.COMMANDS["query"].text, body_len=body_len)
        if self.mode == "binary":
            rec = P.decode_binary(body, self.checksum_on)
        else:
            rec = P.decode_ascii_line(body.strip(b"\r\n"))
        if rec is None:
            self._stats.bad_records += 1
            raise LinkError(f"F/T on {self.name}: corrupt QR record {body!r} discarded")
        self._stats.records += 1
        return self._accept(rec)

    def poll(self) -> FtReading:
        """Ctrl-T: one record, no echo, no prompt (framed by request/response).

        The reply must be exactly one record followed by silence for ``guard_s``
        (3 character times), else it is discarded and counted as bad.
        :raises LinkError: corrupt or over-long reply, port failure
        :raises PfmaTimeoutError: short or missing reply within ``reply_timeout_s``
        """
        rec, why = self._poll_once()
        if rec is None:
            if why.startswith("no reply") or why.startswith("short"):
                raise PfmaTimeoutError(f"F/T on {self.name}: Ctrl-T poll: {why}")
            raise LinkError(f"F/T on {self.name}: Ctrl-T reply discarded: {why}")
        return rec

    @property
    def guard_s(self) -> float:
        """Silence required after a polled record (3 character times)."""
        return 3 * P.BITS_PER_CHAR / self.baud

    def _poll_once(self) -> tuple[FtReading | None, str]:
        """One Ctrl-T transaction; (reading, "") or (None, reason). Raises only on port failure."""
        self._require_idle("poll")
        self._reset_input()
        self._write(P.CTRL_T)
        deadline = self._deadline()
        buf = bytearray()
        binary = self.mode == "binary"
        n = P.record_bytes("binary", self.checksum_on) if binary else 0
        while (len(buf) < n) if binary else (not buf.endswith(b"\n") and len(buf) <= 128):
            if self._expired(deadline, self.clock):
                self._stats.bad_records += 1
                self._stats.bytes_in += len(buf)
                self._stats.bytes_discarded += len(buf)
                if not buf:
                    return None, f"no reply within {self.reply_timeout_s:g} s"
                return None, f"short reply ({len(buf)} bytes) within {self.reply_timeout_s:g} s: {bytes(buf)!r}"
            try:
                buf += self.port.read((n - len(buf)) if binary else 1)
            except OSError as err:
                raise LinkError(f"F/T on {self.name}: read failed during Ctrl-T poll: {err}") from err
        # silence check: an inserted byte shows up as an extra byte right behind the record
        extra = self._in_waiting()
        if getattr(self.clock, "simulated", False):
            if not extra:
                self.clock.sleep_until(self.clock.now() + self.guard_s)  # simulated line: jump
                extra = self._in_waiting()
        t_guard = time.monotonic() + (0.0 if getattr(self.clock, "simulated", False) else self.guard_s)
        while not extra and time.monotonic() < t_guard:
            time.sleep(self.guard_s / 6)  # driver-side guard of a few character times
            extra = self._in_waiting()
        self._stats.bytes_in += len(buf)
        rec = P.decode_binary(bytes(buf), self.checksum_on) if binary else \
            P.decode_ascii_line(bytes(buf).rstrip(b"\r\n"))
        if rec is None or extra:
            self._stats.bad_records += 1
            self._stats.bytes_discarded += len(buf)
            why = f"{extra} unexpected extra byte(s)" if rec is not None else "corrupt record"
            return None, f"{why}: {bytes(buf)!r}"
        self._stats.records += 1
        return self._accept(rec), ""

    def start_stream(self, rate_hz: float | None = None, on_slow: str = "raise") -> None:
        """``QS``: start streaming; records are then read with :meth:`read_records`.

        :param rate_hz: the rate the caller needs (e.g. the rack's 80 Hz); checked
            against the line limit for the mode first (see :meth:`check_rate`)
        :raises ConfigError: line too slow for ``rate_hz`` (``on_slow="raise"``)
        """
        self._require_idle("start a stream")
        if rate_hz is not None:
            self.check_rate(rate_hz, on_slow)
        if self.mode == "binary" and not self.checksum_on:
            warnings.warn(UNSAFE_BINARY_STREAM.format(name=self.name), RuntimeWarning, stacklevel=2)
        self._reset_input()
        text = P.COMMANDS["stream"].text.encode("ascii")
        self._write(text + P.CR)
        deadline = self._deadline()
        buf = bytearray()
        echo = text + P.CRLF
        while echo not in buf:
            buf += self._read_some(1, deadline, "QS", buf)
        rest = bytes(buf[buf.index(echo) + len(echo):])
        self._decoder = self._new_decoder()
        self.streaming = True
        self._rate.clear()
        if rest:
            self._feed(rest)

    def read_records(self) -> list[FtReading]:
        """Read whatever bytes are there (blocking up to ``port.timeout`` for the first)
        and return the records they complete. Never returns a record that failed a check.

        :raises LinkError: the port failed (disconnect)
        """
        n = self._in_waiting()
        try:
            data = self.port.read(n if n > 0 else 1)
        except OSError as err:  # pyserial's SerialException is an IOError
            raise LinkError(f"F/T on {self.name}: read failed: {err}") from err
        return self._feed(data) if data else []

    def record_due(self) -> bool:
        """While streaming: the port's buffer holds enough bytes to complete a record (a
        whole record plus the next status byte in binary, a line's worth in ASCII), so a
        :meth:`read_records` now is worth its cost. Never blocks, no bus access on a port
        whose owner drains it (the MVME400 port with ``autopoll`` off).

        :raises LinkError: the port failed
        """
        if not self.streaming:
            return False
        n = P.record_bytes(self.mode, self.checksum_on) + (1 if self.mode == "binary" else 0)
        return self._in_waiting() + self._decoder.buffered >= n

    def stop_stream(self) -> list[FtReading]:
        """Stop ``QS``: send CR, keep decoding until the prompt ``CR LF CR LF >``.

        :returns: the last records that arrived before the prompt
        :raises PfmaTimeoutError: no prompt within ``reply_timeout_s``
        """
        if not self.streaming:
            return []
        self._write(P.CR)
        deadline = self._deadline()
        buf = bytearray()
        while P.STOP_PROMPT not in buf:
            try:
                buf += self._read_some(max(1, self._in_waiting()), deadline, "stream stop (CR)", buf)
            except (PfmaTimeoutError, LinkError):
                self.streaming = False
                raise
        self.streaming = False
        out = self._feed(bytes(buf[: buf.index(P.STOP_PROMPT)]))
        for rec in self._decoder.finish():
            out.append(self._accept(rec))
        return out

    # -- statistics -------------------------------------------------------------------------
    def stats(self) -> LinkStats:
        """Link statistics now (rate over the last ``rate_window_s``)."""
        now = self.clock.now()
        s = self._stats
        return LinkStats(records=s.records, bad_records=s.bad_records, resyncs=s.resyncs,
                         rate_hz=self._rate.rate_hz(now),
                         age_s=None if self.latest is None else now - self.latest.t_s,
                         bytes_in=s.bytes_in, bytes_discarded=s.bytes_discarded)

    # -- generic command ----------------------------------------------------------------------
    def command(self, text: str, body_len: int | None = None) -> bytes:
        """Send one line command; return the output between the echo and the prompt.

        :param body_len: exact output length for binary output (which may contain CR LF)
        :raises LinkError: no echo, garbled reply, or the controller reported an error
        :raises PfmaTimeoutError: no complete reply within ``reply_timeout_s``
        """
        self._require_idle(f"send {text!r}")
        self._reset_input()
        cmd = text.encode("ascii")
        self._write(cmd + P.CR)
        head = cmd + P.CRLF
        deadline = self._deadline()
        buf = bytearray()
        while True:
            i = buf.find(head)
            if i >= 0:
                start = i + len(head)
                if body_len is not None:
                    end = start + body_len
                    if len(buf) >= end + len(P.PROMPT):
                        if buf[end: end + len(P.PROMPT)] != P.PROMPT:
                            self._stats.bad_records += 1
                            raise LinkError(f"F/T on {self.name}: reply to {text!r} has the wrong "
                                            f"length: {bytes(buf)!r}")
                        body = bytes(buf[start:end])
                        break
                else:
                    j = buf.find(P.PROMPT, start)
                    if j >= 0:
                        body = bytes(buf[start:j])
                        break
            buf += self._read_some(max(1, self._in_waiting()), deadline, repr(text), buf)
        self._stats.bytes_in += len(buf)
        if body.startswith(b"ERROR"):
            raise LinkError(f"F/T controller on {self.name} rejected {text!r}: {body.decode('ascii', 'replace')}")
        return body

    def close(self) -> None:
        """Stop a stream if one runs (best effort) and close the port."""
        if self.streaming:
            try:
                self.stop_stream()
            except (LinkError, PfmaTimeoutError):
                pass
        close = getattr(self.port, "close", None)
        if close:
            close()

    def __enter__(self) -> "FtSensor":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals -----------------------------------------------------------------------------
    def _new_decoder(self) -> P.AsciiStreamDecoder | P.BinaryStreamDecoder:
        dec = P.BinaryStreamDecoder(self.checksum_on, self.resync_records) if self.mode == "binary" \
            else P.AsciiStreamDecoder()
        dec.stats = self._stats  # one set of counters across mode changes
        dec.reset(synced=True)
        return dec

    def _feed(self, data: bytes) -> list[FtReading]:
        return [self._accept(rec) for rec in self._decoder.feed(data)]

    def _accept(self, rec: tuple[int, tuple[int, ...]]) -> FtReading:
        status, c = rec
        t = self.clock.now()
        # ignore: the decoder yields a tuple[int, ...] of exactly 6 counts (one per record field)
        reading = FtReading(status=status, counts=c,  # type: ignore[arg-type]
                            force_n=(c[0] / self.cpf, c[1] / self.cpf, c[2] / self.cpf),
                            torque_nm=(c[3] / self.cpt, c[4] / self.cpt, c[5] / self.cpt),
                            t_s=t, seq=self._seq)
        self._seq += 1
        self._rate.mark(t)
        self.latest = reading
        return reading

    def _require_idle(self, what: str) -> None:
        if self.streaming:
            raise LinkError(f"F/T on {self.name}: cannot {what} while streaming; call stop_stream() first")

    def _write(self, data: bytes) -> None:
        try:
            self.port.write(data)
        except OSError as err:
            raise LinkError(f"F/T on {self.name}: write failed: {err}") from err

    def _in_waiting(self) -> int:
        try:
            n = self.port.in_waiting  # a property in pyserial, a method on some ports
            return int(n() if callable(n) else n)
        except OSError as err:
            raise LinkError(f"F/T on {self.name}: port failed: {err}") from err

    def _reset_input(self) -> None:
        n = self._in_waiting()
        self._stats.bytes_discarded += n
        try:
            self.port.reset_input_buffer()
        except OSError as err:
            raise LinkError(f"F/T on {self.name}: port failed: {err}") from err

    def _deadline(self) -> tuple[float, float]:
        """Reply deadline on the real clock and on the injected clock (a port that waits in
        simulated time, like the fake MVME400's, ends the wait by advancing the clock)."""
        return time.monotonic() + self.reply_timeout_s, self.clock.now() + self.reply_timeout_s

    @staticmethod
    def _expired(deadline: tuple[float, float], clock: Clock) -> bool:
        return time.monotonic() > deadline[0] or clock.now() > deadline[1]

    def _read_some(self, n: int, deadline: tuple[float, float], what: str, got: bytes | bytearray) -> bytes:
        if self._expired(deadline, self.clock):
            if got:
                raise LinkError(f"F/T on {self.name}: garbled or incomplete reply to {what} within "
                                f"{self.reply_timeout_s:g} s: {bytes(got[-64:])!r} (wrong mode/baud, or line noise?)")
            raise PfmaTimeoutError(f"F/T controller on {self.name} did not answer {what} within "
                                   f"{self.reply_timeout_s:g} s (no bytes; check cable, port, baud and power)")
        try:
            return self.port.read(n)
        except OSError as err:
            raise LinkError(f"F/T on {self.name}: read failed during {what}: {err}") from err


class FtReader:
    """Reader thread: keeps the latest reading for the DAQ loop (``latest()`` never blocks).

    Framing (see docs/ft-protocol.md, "What the decoder can detect"):

    * ``"stream"``: ``QS`` and the incremental decoder - ASCII, or binary WITH checksum;
    * ``"poll"``: one Ctrl-T request per record, framed by request/response (exact
      length, then silence) - the safe choice for binary without checksum;
    * ``"auto"`` (default): poll for binary without checksum, stream otherwise.

    ``error`` holds what stopped the thread (a port failure), if anything.

    :param sensor: a configured :class:`FtSensor`
    :param rate_hz: rate the loop needs (checked against the line on start)
    :param on_slow: see :meth:`FtSensor.check_rate`
    :param keep: also keep the last ``keep`` readings in ``history``
    """

    def __init__(self, sensor: FtSensor, rate_hz: float = 80.0, on_slow: str = "raise", keep: int = 0,
                 framing: str = "auto") -> None:
        if framing not in ("auto", "stream", "poll"):
            raise ValueError(f"framing must be 'auto', 'stream' or 'poll', not {framing!r}")
        self.sensor = sensor
        self.rate_hz = rate_hz
        self.on_slow = on_slow
        self.framing = framing
        self.history: deque[FtReading] = deque(maxlen=keep or 1)
        self._keep = keep
        self._stop = threading.Event()
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self.error: BaseException | None = None

    def start(self) -> "FtReader":
        """Start the stream (or the poll loop) and the thread.

        :raises ConfigError: the line cannot carry ``rate_hz`` and ``on_slow == "raise"``
        """
        s = self.sensor
        if self.framing == "auto":
            self.framing = "poll" if (s.mode == "binary" and not s.checksum_on) else "stream"
        if self.framing == "stream":
            s.start_stream(self.rate_hz, self.on_slow)
        else:
            s.check_rate(self.rate_hz, self.on_slow)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"FtReader {s.name}", daemon=True)
        self._thread.start()
        return self

    def latest(self) -> FtReading | None:
        """Latest reading, or None before the first; never blocks."""
        return self.sensor.latest

    def wait_records(self, count: int, timeout_s: float) -> bool:
        """Block until ``count`` records were accepted in total (True) or timeout (False)."""
        with self._cond:
            return self._cond.wait_for(lambda: self.sensor._stats.records >= count or self.error is not None,
                                       timeout=timeout_s) and self.error is None

    def stop(self) -> list[FtReading]:
        """Stop the thread, then the stream; returns the records decoded during the stop."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self.error is None and self.sensor.streaming:
            out = self.sensor.stop_stream()
            if self._keep:
                self.history.extend(out)
            return out
        return []

    def __enter__(self) -> "FtReader":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                if self.framing == "stream":
                    out = self.sensor.read_records()
                else:
                    rec, _why = self.sensor._poll_once()  # bad replies are counted, not fatal
                    out = [rec] if rec is not None else []
                if out:
                    if self._keep:
                        self.history.extend(out)
                    with self._cond:
                        self._cond.notify_all()
        except (LinkError, OSError) as err:
            self.error = err
            with self._cond:
                self._cond.notify_all()


def open_ft(url: str, baud: int = P.DEFAULT_BAUD, *, timeout_s: float = 0.05, **kwargs: Any) -> FtSensor:
    """Open an F/T controller by pyserial URL (``/dev/ttyS0``, ``/dev/pts/3``, ``socket://h:p``,
    ``rfc2217://h:p``, ``loop://``) at ``baud`` 8N1.

    :param timeout_s: the port's read timeout (bounds how long a reader blocks)
    :param kwargs: passed to :class:`FtSensor` (cpf, cpt, clock, reply_timeout_s)
    :raises LinkError: the port cannot be opened
    """
    import serial  # pyserial; imported here so the driver also works without it (MVME400 port)

    try:
        port = serial.serial_for_url(url, baudrate=baud, timeout=timeout_s, write_timeout=0.5)
    except (serial.SerialException, ValueError) as err:
        raise LinkError(f"cannot open F/T port {url!r}: {err}") from err
    return FtSensor(port, baud=baud, **kwargs)
