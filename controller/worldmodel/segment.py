"""The world-model shared-memory segment format: header, variable table (JSON),
user-request ring slots, and the seqlocked data body.

The layout is described in ``docs/world-model.md``. The sequence lock, the shared-memory
open without the resource-tracker, the liveness check and the byte lock are those of the
Bit3 buffer (:mod:`bit3.buffer`), including its x86-64 memory-ordering argument.
"""

from __future__ import annotations

import hashlib
import json
import struct
from dataclasses import dataclass
from pathlib import Path

from bit3.layout import SEQ_BLOCK  # the SeqLock counter block before the body
from bit3.seqlock import SeqLock
from controller.worldmodel.spec import AREAS, VarSpec, WorldModelError

MAGIC = b"PFMA-WM\0"
FORMAT_VERSION = 1
HEADER_SIZE = 512
#: user-request ring: slots, fixed part of a slot, minimum value payload
REQUEST_SLOTS = 16
SLOT_HEADER = 192
MIN_PAYLOAD = 64
READ_TIMEOUT_S = 0.1

#: header field -> (offset, struct format); all little-endian, naturally aligned
HEADER_FIELDS: dict[str, tuple[int, str]] = {
    "magic": (0, "8s"), "version": (8, "I"), "header_size": (12, "I"),
    "total_size": (16, "Q"), "spec_offset": (24, "Q"), "spec_len": (32, "Q"),
    "spec_hash": (40, "8s"), "req_offset": (48, "Q"), "req_slots": (56, "I"),
    "req_slot_size": (60, "I"), "seq_offset": (64, "Q"), "body_size": (72, "Q"),
    "powered_up": (80, "I"), "owner_pid": (84, "i"), "frame": (88, "Q"),
    "frame_t_s": (96, "d"), "created_ns": (104, "Q"), "req_next_id": (112, "Q"),
    "lock_byte": (120, "Q"), "user_applied": (128, "Q"), "user_rejected": (136, "Q"),
    "owner_name": (144, "32s"), "key_salt": (176, "16s"), "key_hash": (192, "32s"),
}
#: request-slot field -> (offset, struct format)
SLOT_FIELDS: dict[str, tuple[int, str]] = {
    "state": (0, "I"), "var_index": (4, "I"), "req_id": (8, "Q"), "submit_ns": (16, "Q"),
    "pid": (24, "i"), "nbytes": (28, "I"), "applied_frame": (32, "Q"), "key_hash": (40, "32s"),
    "user": (72, "24s"), "result": (96, "96s"),
}
#: request-slot states
FREE, WRITING, PENDING, APPLIED, REJECTED = 0, 1, 2, 3, 4
STATE_NAMES = {FREE: "free", WRITING: "writing", PENDING: "pending", APPLIED: "applied",
               REJECTED: "rejected"}


class _WMSeqLock(SeqLock):
    __slots__ = ()
    kind = "world model"


def _round(n: int, to: int) -> int:
    return (n + to - 1) // to * to


# ----------------------------------------------------------------------------------------
# segment layout


@dataclass(frozen=True)
class _Layout:
    """Where everything lives in one segment (offsets from its start)."""

    spec_json: bytes
    spec_hash: bytes
    offsets: tuple[int, ...]       # of each variable, from the body start
    body_size: int
    spec_offset: int
    req_offset: int
    req_slot_size: int
    seq_offset: int
    total_size: int

    @classmethod
    def build(cls, specs: tuple[VarSpec, ...], name: str | None, owner: str) -> "_Layout":
        offsets, pos = [], 0
        for s in specs:  # specs are sorted by area already
            align = min(8, s.np_dtype.itemsize)
            pos = _round(pos, align)
            offsets.append(pos)
            pos += s.nbytes
        body_size = _round(max(pos, 8), 8)
        doc = {"format": "pfma.worldmodel", "version": FORMAT_VERSION, "name": name,
               "owner": owner, "areas": list(AREAS), "body_size": body_size,
               "variables": [dict(s.to_json(), offset=o, nbytes=s.nbytes)
                             for s, o in zip(specs, offsets)]}
        raw = json.dumps(doc, separators=(",", ":"), sort_keys=True).encode()
        spec_offset = HEADER_SIZE
        req_offset = _round(spec_offset + len(raw), 64)
        payload = _round(max(MIN_PAYLOAD, max((s.nbytes for s in specs), default=0)), 8)
        slot = SLOT_HEADER + payload
        seq_offset = _round(req_offset + REQUEST_SLOTS * slot, 64)
        total = _round(seq_offset + SEQ_BLOCK + body_size, 4096)
        return cls(raw, hashlib.sha256(raw).digest()[:8], tuple(offsets), body_size, spec_offset,
                   req_offset, slot, seq_offset, total)


def decode(mv: memoryview, name: str) -> tuple[tuple[VarSpec, ...], _Layout]:
    """The variables and layout of an initialised segment (what :meth:`WorldModel.attach`
    reads; names and types come from the JSON stored in it).

    :raises WorldModelError: no magic, another format version, sizes or table corrupt
    """
    size = len(mv)
    if size < HEADER_SIZE or bytes(mv[0:8]) != MAGIC:
        raise WorldModelError(f"world model {name!r}: no magic {MAGIC!r} (not initialised yet, "
                              f"or not a world model)")
    h = {k: struct.unpack_from("<" + f, mv, o)[0] for k, (o, f) in HEADER_FIELDS.items()
         if k in ("version", "total_size", "spec_offset", "spec_len", "spec_hash",
                  "req_offset", "req_slot_size", "req_slots", "seq_offset", "body_size")}
    if h["version"] != FORMAT_VERSION:
        raise WorldModelError(f"world model {name!r}: format version {h['version']}, this "
                              f"program reads {FORMAT_VERSION}")
    if h["total_size"] > size or h["spec_offset"] + h["spec_len"] > size:
        raise WorldModelError(f"world model {name!r}: header sizes exceed the segment "
                              f"({size} bytes)")
    raw = bytes(mv[h["spec_offset"]:h["spec_offset"] + h["spec_len"]])
    if hashlib.sha256(raw).digest()[:8] != h["spec_hash"]:
        raise WorldModelError(f"world model {name!r}: variable table does not match its hash "
                              f"{h['spec_hash'].hex()} (corrupt segment)")
    doc = json.loads(raw)
    specs = tuple(VarSpec.from_json(v) for v in doc["variables"])
    offsets = tuple(int(v["offset"]) for v in doc["variables"])
    for s, o in zip(specs, offsets):
        if o + s.nbytes > h["body_size"]:
            raise WorldModelError(f"world model {name!r}: variable {s.name!r} lies outside the body")
    if h["req_slots"] != REQUEST_SLOTS:
        raise WorldModelError(f"world model {name!r}: {h['req_slots']} request slots, "
                              f"expected {REQUEST_SLOTS}")
    lay = _Layout(raw, h["spec_hash"], offsets, h["body_size"], h["spec_offset"],
                  h["req_offset"], h["req_slot_size"], h["seq_offset"], h["total_size"])
    return specs, lay


@dataclass(frozen=True)
class ModelInfo:
    """Header summary of a world model."""

    name: str | None
    owner: str
    owner_pid: int
    owner_alive: bool
    frame: int
    frame_t_s: float
    powered_up: bool
    created_ns: int
    n_variables: int
    total_size: int
    spec_hash: str
    user_applied: int
    user_rejected: int


def list_segments(shm_dir: str = "/dev/shm") -> list[str]:
    """Names of world-model segments on this host (files starting with the magic)."""
    out = []
    try:
        entries = sorted(Path(shm_dir).iterdir())
    except OSError:
        return out
    for p in entries:
        try:
            with open(p, "rb") as f:
                if f.read(8) == MAGIC:
                    out.append(p.name)
        except OSError:
            continue
    return out
