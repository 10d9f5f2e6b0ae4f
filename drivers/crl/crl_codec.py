"""CRL force-reflecting hand controller serial protocol -- **PLACEHOLDER FRAMING**.

No public description of the CRL / Sargent (Kraft) link protocol exists
(hardware-registers.md section 8: "No public protocol found"). This module is the
project-internal framing recommended there (R8) with the layout of pfma-model.md
section 8.6. It is the ONE module to replace when IRSS documentation turns up: the
driver (``drivers/crl/crl.py``) and the fake (``fakes/crl.py``) both go through it
and nothing else knows a byte offset.

Both directions use the same 16-byte frame (big-endian words)::

    0     0x7E  start of frame
    1     seq   0..255, +1 per frame, per direction
    2-13  6 x int16 BE   master->controller: positions x, y, z, roll, pitch, yaw
                         controller->master: force/torque commands Fx, Fy, Fz, Tx, Ty, Tz
    14    master->controller: buttons (bit0 deadman, bit1 index/clutch, bit2 trigger)
          controller->master: flags   (bit0 force-enable, bit1 fault)
    15    checksum: two's complement of the 8-bit sum of bytes 0..14
          (so the 8-bit sum of all 16 bytes is 0)

Every value below is an ASSUMPTION (pfma-model.md 8.6, "ALL VALUES ASSUMED") and is
listed in :data:`ASSUMPTIONS`.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from typing import Callable

SOF = 0x7E  #: start-of-frame byte (R8)
FRAME_LEN = 16  #: bytes per frame, both directions (8.6)
BAUD = 19200  #: RS-232 8N1 through short-haul modems (8.6; the seed says the MVME400 port runs 19200)
FRAME_PERIOD_S = 0.020  #: one frame every 20 ms (50 Hz) in each direction (8.6)
WATCHDOG_FRAMES = 3  #: 3 consecutive missing/bad frames (60 ms) = link lost (8.6)
FULL_SCALE_COUNTS = 32767  #: int16 full scale used by every LSB below

POS_FULL_SCALE_M = 0.20  #: translation workspace +-0.20 m; LSB = 0.20 m / 32767 (8.6)
ROT_FULL_SCALE_RAD = math.radians(60.0)  #: rotation workspace +-60 deg; LSB = 60 deg / 32767 (8.6)
FORCE_LIMIT_N = 40.0  #: display limit 40 N continuous; force LSB = 40 N / 32767 (8.6)
TORQUE_LIMIT_NM = 2.0  #: display limit 2 N.m; torque LSB = 2 N.m / 32767 (8.6)

# master -> controller buttons byte
BTN_DEADMAN = 0x01  #: bit0 deadman (8.6)
BTN_INDEX = 0x02  #: bit1 index / clutch button (8.6)
BTN_TRIGGER = 0x04  #: bit2 grip trigger (8.6)
BUTTONS_RESERVED = 0xF8  #: bits 3-7: must be 0 (assumed; used to reject false frames)

# controller -> master flags byte
FLAG_FORCE_ENABLE = 0x01  #: bit0 force display enabled (8.6)
FLAG_FAULT = 0x02  #: bit1 controller-side fault (8.6)
FLAGS_RESERVED = 0xFC  #: bits 2-7: must be 0 (assumed)

#: every placeholder choice of this protocol, in one table (printed by docs and ``pfma hand``)
ASSUMPTIONS: tuple[str, ...] = (
    "assumed (R8, pfma-model 8.6): whole framing is a project placeholder, no public CRL protocol",
    "assumed (8.6): 19200 baud 8N1, one 16-byte frame every 20 ms in each direction",
    "assumed (8.6): 0x7E, seq, 6 x int16 big-endian, buttons/flags, 8-bit two's-complement checksum",
    "assumed (8.6): position LSB 0.20 m/32767 and 60 deg/32767; force LSB 40 N/32767 and 2 N.m/32767",
    "assumed (8.6): buttons bit0 deadman, bit1 index, bit2 trigger; flags bit0 enable, bit1 fault",
    "assumed (this module): unused bits of the buttons/flags byte are 0 (frames with them set are bad)",
    "assumed (8.6): 3 consecutive missing or bad frames (60 ms) = link lost, deadman released",
)


class CodecError(ValueError):
    """A frame that does not decode (wrong length, start byte, checksum or reserved bits)."""


@dataclass(frozen=True)
class MasterFrame:
    """Master (hand controller) -> controller: six positions and the buttons."""

    seq: int  #: 0..255
    axes_counts: tuple[int, ...]  #: x, y, z, roll, pitch, yaw as int16 counts
    buttons: int  #: BTN_* bits

    @property
    def deadman(self) -> bool:
        return bool(self.buttons & BTN_DEADMAN)


@dataclass(frozen=True)
class ForceFrame:
    """Controller -> master: six force/torque commands and the flags."""

    seq: int  #: 0..255
    wrench_counts: tuple[int, ...]  #: Fx, Fy, Fz, Tx, Ty, Tz as int16 counts
    flags: int  #: FLAG_* bits

    @property
    def enabled(self) -> bool:
        return bool(self.flags & FLAG_FORCE_ENABLE)

    def wrench(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(force_n, torque_nm) in engineering units."""
        return counts_to_wrench(self.wrench_counts)


_BODY = struct.Struct(">BB6hB")  # SOF, seq, 6 x int16, buttons/flags: 15 bytes


def checksum8(data: bytes) -> int:
    """Two's complement of the 8-bit sum of ``data`` (the frame's last byte)."""
    return (-sum(data)) & 0xFF


def _encode(seq: int, counts: tuple[int, ...], bits: int, reserved: int, what: str) -> bytes:
    if len(counts) != 6:
        raise ValueError(f"CRL {what} frame needs 6 values, got {len(counts)}")
    if not 0 <= bits <= 0xFF or bits & reserved:
        raise ValueError(f"CRL {what} frame: bits 0x{bits:X} use reserved bits 0x{reserved:02X}")
    for c in counts:
        if not -32768 <= c <= 32767:
            raise ValueError(f"CRL {what} frame: count {c} outside int16")
    body = _BODY.pack(SOF, seq & 0xFF, *counts, bits)
    return body + bytes([checksum8(body)])


def encode_master_frame(seq: int, axes_counts: tuple[int, ...], buttons: int) -> bytes:
    """Master -> controller frame (16 bytes)."""
    return _encode(seq, tuple(axes_counts), buttons, BUTTONS_RESERVED, "master")


def encode_force_frame(seq: int, wrench_counts: tuple[int, ...], flags: int) -> bytes:
    """Controller -> master frame (16 bytes)."""
    return _encode(seq, tuple(wrench_counts), flags, FLAGS_RESERVED, "force")


def check_frame(frame: bytes, reserved: int) -> str:
    """Why ``frame`` is bad, or ``""`` when it is a good frame."""
    if len(frame) != FRAME_LEN:
        return f"length {len(frame)} != {FRAME_LEN}"
    if frame[0] != SOF:
        return f"start byte 0x{frame[0]:02X} != 0x{SOF:02X}"
    if sum(frame) & 0xFF:
        return f"checksum 0x{frame[-1]:02X} != 0x{checksum8(frame[:-1]):02X}"
    if frame[14] & reserved:
        return f"reserved bits set in 0x{frame[14]:02X}"
    return ""


def _decode(frame: bytes, reserved: int, what: str) -> tuple[int, tuple[int, ...], int]:
    why = check_frame(bytes(frame), reserved)
    if why:
        raise CodecError(f"bad CRL {what} frame: {why}")
    _, seq, *vals, bits = _BODY.unpack(bytes(frame[:15]))
    return seq, tuple(vals), bits


def decode_master_frame(frame: bytes) -> MasterFrame:
    """Decode a master -> controller frame. :raises CodecError: if it is not a good frame"""
    seq, vals, bits = _decode(frame, BUTTONS_RESERVED, "master")
    return MasterFrame(seq, vals, bits)


def decode_force_frame(frame: bytes) -> ForceFrame:
    """Decode a controller -> master frame. :raises CodecError: if it is not a good frame"""
    seq, vals, bits = _decode(frame, FLAGS_RESERVED, "force")
    return ForceFrame(seq, vals, bits)


# -- unit conversions --------------------------------------------------------------------
def counts_to_unit(counts: int) -> float:
    """int16 counts -> -1..1 (-32768 clamps to -1)."""
    return max(-1.0, min(1.0, counts / FULL_SCALE_COUNTS))


def unit_to_counts(u: float) -> int:
    """-1..1 -> int16 counts (clamped; NaN -> 0)."""
    if u != u:
        return 0
    return int(round(max(-1.0, min(1.0, u)) * FULL_SCALE_COUNTS))


def counts_to_pose(axes_counts: tuple[int, ...]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """Master position counts -> ((x_m, y_m, z_m), (roll_rad, pitch_rad, yaw_rad))."""
    u = [counts_to_unit(c) for c in axes_counts]
    return (tuple(v * POS_FULL_SCALE_M for v in u[:3]), tuple(v * ROT_FULL_SCALE_RAD for v in u[3:]))


def wrench_to_counts(force_n: tuple[float, ...], torque_nm: tuple[float, ...]) -> tuple[int, ...]:
    """Force (N) and torque (N.m) -> int16 command counts (per-axis clamp at the LSB range)."""
    return (tuple(unit_to_counts(f / FORCE_LIMIT_N) for f in force_n)
            + tuple(unit_to_counts(t / TORQUE_LIMIT_NM) for t in torque_nm))


def counts_to_wrench(wrench_counts: tuple[int, ...]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """int16 command counts -> (force_n, torque_nm)."""
    u = [counts_to_unit(c) for c in wrench_counts]
    return (tuple(v * FORCE_LIMIT_N for v in u[:3]), tuple(v * TORQUE_LIMIT_NM for v in u[3:]))


# -- incremental decoder --------------------------------------------------------------------
@dataclass
class LinkStats:
    """Counters of one receive direction (never reset by the decoder)."""

    frames_ok: int = 0  #: good frames delivered
    frames_bad: int = 0  #: frames that lost sync (bad checksum/reserved bits where a frame was due)
    bytes_discarded: int = 0  #: bytes thrown away while hunting for a frame start
    resyncs: int = 0  #: times sync was regained after a loss
    frames_lost: int = 0  #: frames missing according to the sequence numbers
    bytes_in: int = 0  #: bytes fed in

    def as_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class FrameDecoder:
    """Incremental, resynchronising decoder for a byte stream of 16-byte frames.

    Feed it any chunking of the stream (byte by byte is fine). While in sync a frame
    is accepted on start byte + checksum + reserved bits. At start and after sync is
    lost the decoder hunts for 0x7E; a candidate found while hunting is accepted only
    when the 16 bytes after it are also a good frame with the next sequence number,
    so noise that happens to checksum correctly is not delivered (the price: one
    frame of latency after a resync). Nothing but a fully checked frame comes out.

    :param kind: ``"master"`` (positions, for the driver) or ``"force"`` (for the fake)
    :param confirm_resync: require the confirming next frame while hunting (default True)
    """

    kind: str = "master"
    confirm_resync: bool = True
    stats: LinkStats = field(default_factory=LinkStats)
    locked: bool = False
    discarded_since_good: int = 0  #: bytes discarded since the last good frame
    _buf: bytearray = field(default_factory=bytearray, repr=False)
    _last_seq: int | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        self._decode: Callable[[bytes], MasterFrame | ForceFrame]
        if self.kind == "master":
            self._reserved, self._decode = BUTTONS_RESERVED, decode_master_frame
        elif self.kind == "force":
            self._reserved, self._decode = FLAGS_RESERVED, decode_force_frame
        else:
            raise ValueError(f"FrameDecoder kind must be 'master' or 'force', not {self.kind!r}")

    @property
    def bad_since_good(self) -> int:
        """Frames' worth of bad data since the last good frame (ceil(discarded / 16))."""
        return -(-self.discarded_since_good // FRAME_LEN)

    @property
    def pending(self) -> int:
        """Bytes held waiting for the rest of a frame."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes and sync (counters are kept)."""
        self._buf.clear()
        self.locked = False
        self._last_seq = None
        self.discarded_since_good = 0

    def _discard(self, n: int) -> None:
        del self._buf[:n]
        self.stats.bytes_discarded += n
        self.discarded_since_good += n
        self.locked = False

    def feed(self, data: bytes) -> list:
        """Add bytes; return the good frames completed by them (oldest first)."""
        self.stats.bytes_in += len(data)
        buf = self._buf
        buf += data
        out = []
        while buf:
            if buf[0] != SOF:
                i = buf.find(SOF)
                self._discard(len(buf) if i < 0 else i)
                continue
            if len(buf) < FRAME_LEN:
                break
            good = not check_frame(bytes(buf[:FRAME_LEN]), self._reserved)
            if good and not self.locked and self.confirm_resync:
                if len(buf) < 2 * FRAME_LEN:
                    break  # wait for the frame after it
                nxt = bytes(buf[FRAME_LEN:2 * FRAME_LEN])
                good = not check_frame(nxt, self._reserved) and nxt[1] == (buf[1] + 1) & 0xFF
            if not good:
                if self.locked:
                    self.stats.frames_bad += 1
                self._discard(1)
                continue
            frame = self._decode(bytes(buf[:FRAME_LEN]))
            del buf[:FRAME_LEN]
            self._accept(frame)
            out.append(frame)
        return out

    def _accept(self, frame) -> None:
        st = self.stats
        if not self.locked and st.frames_ok:
            st.resyncs += 1
        if self._last_seq is not None:
            st.frames_lost += (frame.seq - self._last_seq - 1) & 0xFF
        self._last_seq = frame.seq
        st.frames_ok += 1
        self.locked = True
        self.discarded_since_good = 0
