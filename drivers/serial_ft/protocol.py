"""Lord/ATI F/T controller serial protocol: the one table of commands, record codecs,
checksum and the incremental stream decoders.

Shared by the driver (``drivers.serial_ft.ftsensor``) and the fake controller
(``fakes.ft_sensor``), as ``registers.py`` tables are for boards. Every assumption
about the protocol is in :data:`ASSUMPTIONS` and in ``docs/ft-protocol.md``.

Sources (copied from the hardware-registers reference notes section 7 and R7):
ATI F/T Controller command summary as used by public drivers (mrrocpp
``src/edp/ati3084/edp_s.cc``, ``KonstantinosAng/ATI-FT-Gamma: FTsensor3.py``).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

#: 8N1 = 10 bit-times per character (hardware-registers.md section 7, "Maximum record rate").
BITS_PER_CHAR = 10
DEFAULT_BAUD = 19200
#: Ctrl-T: one record "with minimized handshaking" - no echo, no prompt (sourced: mrrocpp "\024").
CTRL_T = b"\x14"
CR = b"\r"
CRLF = b"\r\n"
#: Every reply ends with CR LF and the prompt ">" (sourced: driver behaviour, section 7 "Framing").
PROMPT = b"\r\n>"
#: After a stream is stopped with CR the controller answers an empty command line: CR LF CR LF >.
STOP_PROMPT = b"\r\n\r\n>"


@dataclass(frozen=True)
class Command:
    """One controller command (ASCII, terminated by CR, echoed, answered with a prompt)."""

    text: str  #: what is sent before CR ("{n}" is filled in by the driver)
    meaning: str
    source: str  #: "sourced: ..." or "assumed: ..."


#: The command set this project uses. Text per the ATI F/T controller command summary.
COMMANDS: dict[str, Command] = {
    "ascii": Command("CD A", "ASCII output records (controller default)", "sourced: ATI command summary"),
    "binary": Command("CD B", "binary output records", "sourced: ATI command summary"),
    "checksum_on": Command("CD E", "append a checksum byte to binary records", "sourced: ATI command summary"),
    "checksum_off": Command("CD U", "no checksum (controller default)", "sourced: ATI command summary"),
    "resolved": Command("CD R", "resolved F/T data (controller default)", "sourced: ATI command summary"),
    "query": Command("QR", "output one record in the current mode (with echo and prompt)",
                     "sourced: ATI command summary"),
    "stream": Command("QS", "stream records until any character is received", "sourced: ATI command summary"),
    "bias": Command("SB", "push the current reading onto the 3-level bias buffer", "sourced: ATI command summary"),
    "unbias": Command("SU", "pop the last bias", "sourced: ATI command summary"),
    "clear_bias": Command("SZ", "clear all biases", "sourced: ATI command summary"),
    "average": Command("SA {n}", "moving average over n samples (0 = off)", "sourced: ATI command summary"),
    # Ctrl-T is not a line command (no CR, no echo, no prompt); listed for completeness.
    "poll": Command("\x14", "one record, no echo, no prompt (Ctrl-T, 0x14)", "sourced: mrrocpp edp_s.cc"),
}

#: Status byte/field values the decoders accept as plausible. 0 = OK is sourced; the
#: overload code is assumed (the real error codes are in the unread manual).
STATUS_CODES: dict[int, str] = {
    0x00: "ok (sourced: status 0 = OK in every public driver)",
    0x01: "overload, |load| > 110 % of full scale (assumed: pfma-model.md 8.7 overload flag)",
}

#: Everything about the protocol that no public source confirms.
ASSUMPTIONS: tuple[str, ...] = (
    "binary record = 1 status byte + 6 x int16 big-endian counts (sourced by one capture only; "
    "other firmware uses 24-bit values)",
    "checksum (CD E) = low 7 bits of the sum of the preceding record bytes (assumed, R7; unverified)",
    "ASCII record = status as %d, then six ',%6d' fields, then CR LF (45 bytes for status < 10; "
    "matches the FTsensor3.py example line)",
    "command reply = echo + CR LF + output + CR LF + '>' (R7 line editor)",
    "QR reply output = one record without its own CR LF (the prompt's CR LF ends it)",
    "stream stop: the character that stops QS is consumed; the driver sends CR and waits for "
    "CR LF CR LF '>'",
    "status 0x01 = overload (assumed); any other non-zero status is treated as corrupt framing",
)

@dataclass(frozen=True)
class NominalSensor:
    """Scale and range of the nominal wrist sensor. ALL VALUES ASSUMED.

    Range from the pfma-model reference notes section 8.7 (Lord-type "30/100":
    +-133 N, +-11.3 N.m, 12-bit effective resolution, overload flag at 110 % FS).
    The counts-per-unit factors are calibration-specific on a real controller; these
    are chosen so that full scale is about 2^11 counts (12-bit resolution) and
    must be replaced by the unit's calibration (CPF/CPT) in configuration.
    """

    cpf: float = 16.0  #: counts per newton (assumed)
    cpt: float = 200.0  #: counts per newton-metre (assumed)
    range_force_n: float = 133.0  #: full scale, each force axis (pfma-model.md 8.7)
    range_torque_nm: float = 11.3  #: full scale, each torque axis (pfma-model.md 8.7)
    overload_fraction: float = 1.10  #: overload flag above this fraction of FS (8.7)
    sample_rate_hz: float = 150.0  #: controller's internal update rate (assumed; R7 suggests 150)


#: The one place the nominal sensor's defaults live (driver, fakes, CLI and docs use it).
NOMINAL = NominalSensor()

ASCII_FIELD_WIDTH = 6
BINARY_FORMAT = ">B6h"
BINARY_BYTES = struct.calcsize(BINARY_FORMAT)  # 13
#: Typical ASCII record length (status < 10): "0" + 6 * ",%6d" + CR LF.
ASCII_RECORD_BYTES = 1 + 6 * (1 + ASCII_FIELD_WIDTH) + 2  # 45


def checksum(record: bytes) -> int:
    """Assumed checksum (R7): low 7 bits of the byte sum of ``record``."""
    return sum(record) & 0x7F


def record_bytes(mode: str, checksum_on: bool = False) -> int:
    """Bytes on the wire per record for ``mode`` ("ascii" or "binary")."""
    if mode == "binary":
        return BINARY_BYTES + (1 if checksum_on else 0)
    if mode == "ascii":
        return ASCII_RECORD_BYTES
    raise ValueError(f"unknown F/T output mode {mode!r} (expected 'ascii' or 'binary')")


def max_rate_hz(mode: str, baud: int = DEFAULT_BAUD, checksum_on: bool = False) -> float:
    """Most records per second the line can carry (8N1): ``baud / 10 / record_bytes``."""
    return baud / BITS_PER_CHAR / record_bytes(mode, checksum_on)


def _clamp16(v: int) -> int:
    return max(-32768, min(32767, int(v)))


def encode_binary(status: int, counts: tuple[int, ...] | list[int], checksum_on: bool = False) -> bytes:
    """One binary record: status byte, six int16 BE counts, optional checksum byte."""
    body = struct.pack(BINARY_FORMAT, status & 0xFF, *(_clamp16(c) for c in counts))
    return body + bytes([checksum(body)]) if checksum_on else body


def encode_ascii(status: int, counts: tuple[int, ...] | list[int], terminator: bytes = CRLF) -> bytes:
    """One ASCII record: ``status`` then six right-justified ``%6d`` fields, comma separated."""
    return (f"{int(status)}" + "".join(f",{_clamp16(c):6d}" for c in counts)).encode("ascii") + terminator


_ASCII_LINE = re.compile(rb"^(\d{1,3})((?:,[ \-0-9]{6}){6})$")
_ASCII_FIELD = re.compile(rb"^ *-?\d+$")
#: text that is not a record but belongs in the stream: an echoed command ("QS", "CD B",
#: "SA 4") or a prompt line (">"); any other line is a garbled record and is counted
_ECHO_LINE = re.compile(rb"^(>.*|[A-Z]{2}(?: [A-Z0-9 ]*)?)$")


def decode_ascii_line(line: bytes) -> tuple[int, tuple[int, ...]] | None:
    """Parse one ASCII record line (without CR LF); None if it is not exactly the format.

    The check is strict (fixed field widths, right-justified), so an inserted or lost
    character anywhere in the line is rejected. A changed digit cannot be detected.
    """
    m = _ASCII_LINE.match(line)
    if not m:
        return None
    status = int(m.group(1))
    if status not in STATUS_CODES:
        return None
    fields = m.group(2).split(b",")[1:]
    counts = []
    for f in fields:
        if not _ASCII_FIELD.match(f):
            return None
        v = int(f)
        if not -32768 <= v <= 32767:
            return None
        counts.append(v)
    return status, tuple(counts)


def decode_binary(record: bytes, checksum_on: bool = False) -> tuple[int, tuple[int, ...]] | None:
    """Parse one binary record of exactly :func:`record_bytes` bytes; None if implausible."""
    n = record_bytes("binary", checksum_on)
    if len(record) != n or record[0] not in STATUS_CODES:
        return None
    if checksum_on and checksum(record[:BINARY_BYTES]) != record[BINARY_BYTES]:
        return None
    status, *counts = struct.unpack(BINARY_FORMAT, record[:BINARY_BYTES])
    return status, tuple(counts)


@dataclass
class DecoderStats:
    """Counters kept by a stream decoder."""

    records: int = 0  #: records accepted
    bad_records: int = 0  #: records rejected (broken framing, bad status, bad checksum)
    resyncs: int = 0  #: times the decoder regained framing after losing it
    bytes_in: int = 0  #: bytes fed
    bytes_discarded: int = 0  #: bytes thrown away while hunting for framing


class AsciiStreamDecoder:
    """Incremental decoder for ASCII record streams, fed with whatever bytes arrived.

    Lines are split at LF (a CR before it is dropped). The first fragment after a
    (re)start is discarded as a partial line. Lines that are echo/prompt text (a prompt
    ``>...`` or an echoed command: two capitals and optional upper-case arguments) are
    skipped without counting; anything else that is not exactly the record format
    (including a record garbled into a letter at its start) counts as a bad record.
    """

    MAX_LINE = 128

    def __init__(self) -> None:
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._synced = False
        self._resyncing = False

    @property
    def buffered(self) -> int:
        """Bytes of an unfinished line."""
        return len(self._buf)

    def reset(self, synced: bool = False) -> None:
        """Forget buffered bytes; ``synced=True`` when the next byte starts a record."""
        self._buf.clear()
        self._synced = synced
        self._resyncing = False

    def finish(self) -> list[tuple[int, tuple[int, ...]]]:
        """End of stream: drop any unterminated tail (not counted as bad)."""
        self.stats.bytes_discarded += len(self._buf)
        self._buf.clear()
        return []

    def feed(self, data: bytes) -> list[tuple[int, tuple[int, ...]]]:
        """Feed bytes; return the (status, counts) records completed by them."""
        self.stats.bytes_in += len(data)
        self._buf += data
        out: list[tuple[int, tuple[int, ...]]] = []
        while True:
            i = self._buf.find(b"\n")
            if i < 0:
                if len(self._buf) > self.MAX_LINE:  # no terminator: garbage
                    self.stats.bytes_discarded += len(self._buf)
                    self.stats.bad_records += 1
                    self._buf.clear()
                    self._resyncing = True
                return out
            line = bytes(self._buf[:i])
            del self._buf[: i + 1]
            if line.endswith(b"\r"):
                line = line[:-1]
            if not self._synced:
                # first fragment after a (re)start: may be the tail of a record
                self._synced = True
                rec = decode_ascii_line(line)
                if rec is None:
                    self.stats.bytes_discarded += len(line) + 1
                    continue
                out.append(rec)
                self.stats.records += 1
                continue
            if not line or _ECHO_LINE.match(line):
                continue  # blank line, echo or prompt
            rec = decode_ascii_line(line)
            if rec is None:
                self.stats.bad_records += 1
                self.stats.bytes_discarded += len(line) + 1
                self._resyncing = True
                continue
            if self._resyncing:
                self.stats.resyncs += 1
                self._resyncing = False
            self.stats.records += 1
            out.append(rec)


class BinaryStreamDecoder:
    """Incremental decoder for back-to-back binary records (no sync byte exists).

    Framing rules (see docs/ft-protocol.md for what they can and cannot detect):

    * in sync: the record at the buffer head is accepted when its status byte is a
      known code, its checksum matches (if enabled) AND the byte after it (the next
      record's status byte) is also a known code - one byte of look-ahead (with
      ``trust_checksum`` set, a failed look-ahead only ends sync after a record whose
      checksum matches);
    * otherwise the decoder counts a bad record, drops one byte at a time and re-enters
      sync on the first position that passes ``resync_records`` whole-record checks:
      with the checksum one record (the same test as in sync, so the first whole record
      after a loss is decoded at once: a lost character costs only the record it hit),
      without it two consecutive records (a slip is otherwise too likely to pass).
      Bytes after a bad record are always kept and searched: no good record is thrown
      away with a bad one.

    :param checksum_on: records carry the (assumed) checksum byte
    :param resync_records: whole valid records needed to regain sync (default 1 with the
        checksum, 2 without)
    """

    def __init__(self, checksum_on: bool = False, resync_records: int | None = None) -> None:
        self.checksum_on = checksum_on
        self.length = record_bytes("binary", checksum_on)
        if resync_records is None:
            resync_records = 1 if checksum_on else 2
        if resync_records not in (1, 2):
            raise ValueError(f"resync_records must be 1 or 2, not {resync_records!r}")
        self.resync_records = resync_records
        #: in sync, accept a record whose checksum matches even when the byte after it is
        #: no status code (characters lost right behind a whole record). Off by default: it
        #: saves one record in about 20 losses but lets ~0.2 % more corrupt records through
        #: per loss at small loads (docs/ft-protocol.md), and a wrong wrench is worse than
        #: a missing one
        self.trust_checksum = False
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._synced = True

    @property
    def buffered(self) -> int:
        """Bytes held for the next record (or the hunt)."""
        return len(self._buf)

    @property
    def synced(self) -> bool:
        """False while hunting for framing after a bad record."""
        return self._synced

    def reset(self, synced: bool = True) -> None:
        """Forget buffered bytes; ``synced=True`` when the next byte starts a record."""
        self._buf.clear()
        self._synced = synced

    def finish(self) -> list[tuple[int, tuple[int, ...]]]:
        """End of stream (the prompt followed): accept a last whole record without
        look-ahead; drop any other tail (not counted as bad)."""
        out = []
        if self._synced and len(self._buf) == self.length:
            rec = self._valid(0)
            if rec is not None:
                self.stats.records += 1
                out.append(rec)
        if not out:
            self.stats.bytes_discarded += len(self._buf)
        self._buf.clear()
        return out

    def _valid(self, at: int) -> tuple[int, tuple[int, ...]] | None:
        return decode_binary(bytes(self._buf[at: at + self.length]), self.checksum_on)

    def feed(self, data: bytes) -> list[tuple[int, tuple[int, ...]]]:
        """Feed bytes; return the (status, counts) records confirmed by them."""
        self.stats.bytes_in += len(data)
        self._buf += data
        out: list[tuple[int, tuple[int, ...]]] = []
        n = self.length
        buf = self._buf
        while True:
            if self._synced:
                if len(buf) < n + 1:
                    return out
                rec = self._valid(0)
                if rec is not None and (buf[n] in STATUS_CODES or self.trust_checksum):
                    del buf[:n]
                    self.stats.records += 1
                    out.append(rec)
                    if buf[0] not in STATUS_CODES:  # the loss came right after this record
                        self.stats.bad_records += 1
                        self._synced = False
                        del buf[:1]
                        self.stats.bytes_discarded += 1
                    continue
                self.stats.bad_records += 1
                self._synced = False
                del buf[:1]
                self.stats.bytes_discarded += 1
                continue
            # hunting: the first position that passes the resync test
            need = n + 1 if self.resync_records == 1 else 2 * n
            if len(buf) < need:
                return out
            rec = None
            if buf[0] in STATUS_CODES:  # cheap test first: most positions fail here
                rec = self._valid(0)
                if rec is not None:
                    ok = buf[n] in STATUS_CODES if self.resync_records == 1 else self._valid(n) is not None
                    rec = rec if ok else None
            if rec is not None:
                del buf[:n]
                self._synced = True
                self.stats.resyncs += 1
                self.stats.records += 1
                out.append(rec)
                continue
            del buf[:1]
            self.stats.bytes_discarded += 1


# ---------------------------------------------------------------------------------------
# CAN F/T layout (PROJECT-DEFINED, all assumed; used by can_ft.py and fakes/ft_can.py).
# No public Lord/ATI CAN layout was available; ATI CAN F/T interfaces are recalled
# (unverified) to answer a read request with the gauge data split over two frames.
# 11-bit identifiers, base = 0x100 + 0x10 * node_id (node 0..15).
# ---------------------------------------------------------------------------------------
CAN_BASE_ID = 0x100  #: assumed (project-defined)
CAN_NODE_STRIDE = 0x10  #: assumed: each node owns 16 identifiers
MAX_NODE_ID = 15


@dataclass(frozen=True)
class CanFrameLayout:
    """One row of the CAN layout table."""

    offset: int  #: identifier = base + offset
    direction: str  #: "host->node" or "node->host"
    dlc: int
    payload: str  #: byte layout
    struct_fmt: str  #: struct format of the payload (big-endian)


#: The one table of the project-defined CAN F/T layout (all ASSUMED).
CAN_LAYOUT: dict[str, CanFrameLayout] = {
    "request": CanFrameLayout(0x0, "host->node", 2, "opcode u8, tag u8", ">BB"),
    "forces": CanFrameLayout(0x1, "node->host", 8, "Fx Fy Fz int16 BE counts, status u8, seq u8", ">3hBB"),
    "torques": CanFrameLayout(0x2, "node->host", 8, "Tx Ty Tz int16 BE counts, seq u8, tag u8", ">3hBB"),
    "ack": CanFrameLayout(0x3, "node->host", 4, "opcode u8, tag u8, result u8 (0 = ok), bias depth u8", ">BBBB"),
}

#: Request opcodes (assumed; mirror the serial commands QR, SB, SU, SZ).
OP_READ, OP_BIAS, OP_UNBIAS, OP_CLEAR_BIAS = 0x01, 0x02, 0x03, 0x04


def node_base_id(node_id: int) -> int:
    """First CAN identifier of ``node_id``.

    :raises ValueError: node id outside 0..15
    """
    if not 0 <= node_id <= MAX_NODE_ID:
        raise ValueError(f"CAN F/T node id must be 0..{MAX_NODE_ID}, not {node_id}")
    return CAN_BASE_ID + CAN_NODE_STRIDE * node_id


def frame_id(node_id: int, kind: str) -> int:
    """Identifier of frame ``kind`` (a :data:`CAN_LAYOUT` key) for ``node_id``."""
    return node_base_id(node_id) + CAN_LAYOUT[kind].offset


