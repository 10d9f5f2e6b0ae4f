"""The recording's constants, its time stamps and the raw stream's schema and decoding.

``/pfma/inputs_raw`` carries the inputs area body byte for byte; its schema
(:func:`raw_schema`, encoding ``pfma-bit3-layout``) is the field table that decodes
it without this program (:func:`decode_raw`). Time stamps are the service clock plus
``epoch_offset_ns`` (see the package docstring).
"""

from __future__ import annotations

import json
import math
import time

import numpy as np

from bit3.layout import Layout

PROFILE = "pfma"
LIBRARY = "pfma-recorder 1"
RAW_TOPIC = "/pfma/inputs_raw"
RAW_SCHEMA = "pfma.bit3.inputs"
RAW_SCHEMA_ENCODING = "pfma-bit3-layout"
RAW_ENCODING = "pfma-bit3-v1"
#: close the chunk and flush the file this often (packages.md 4: a flush every 0.5 s lost
#: < 0.5 s on SIGKILL; the default 1 MiB chunk without flushes lost everything)
FLUSH_EVERY_S = 0.25
#: chunks are closed when they exceed this (bounds one zstd call to well under a frame)
CHUNK_SIZE = 256 * 1024
#: /pfma/recorder counters message period (wall time)
COUNTERS_EVERY_S = 1.0


def epoch_offset_ns() -> int:
    """Unix time minus monotonic time, in ns (maps the service's monotonic ``t_s`` to wall time)."""
    return time.time_ns() - time.monotonic_ns()


def _ns(t_s: float, offset_ns: int) -> int:
    if not math.isfinite(t_s) or t_s < 0:
        t_s = 0.0
    return offset_ns + int(round(t_s * 1e9))



# ----------------------------------------------------------------------------------------
# raw stream: schema and decoding


def raw_schema(layout: Layout, area: str = "inputs") -> dict:
    """The field table of one area body, enough to decode its bytes without ioservice."""
    a = layout.area(area)
    fields = [f for f in layout.fields if f.area == area]
    stored = max(f.offset + f.nbytes for f in fields) - a.body_offset
    return {
        "title": f"PFMA Bit3 {area} area body, {RAW_ENCODING}",
        "encoding": RAW_ENCODING,
        "area": area, "body_size": a.body_size, "stored_bytes": stored,
        "layout_hash": layout.hash_hex, "layout_version": layout.version, "rack": layout.rack_name,
        "doc": "each message is the first stored_bytes bytes of the area body (little-endian, "
               "numpy layout); pad with zeros to body_size and view with the fields below "
               "(offset: bytes from the start of the body)",
        "fields": [{"name": f.name, "offset": f.offset - a.body_offset, "dtype": f.dtype,
                    "shape": list(f.shape), "units": f.units} for f in fields],
    }


def raw_dtype(schema: dict) -> np.dtype:
    """numpy record type of a ``pfma.bit3.inputs`` schema (see :func:`raw_schema`)."""
    fl = schema["fields"]
    return np.dtype({"names": [f["name"] for f in fl],
                     "formats": [(np.dtype(f["dtype"]), tuple(f["shape"])) if f["shape"]
                                 else np.dtype(f["dtype"]) for f in fl],
                     "offsets": [f["offset"] for f in fl], "itemsize": schema["body_size"]})


def decode_raw(schema: dict | bytes, data: bytes, dtype: np.dtype | None = None) -> np.ndarray:
    """One ``pfma-bit3-v1`` message -> a 0-d numpy record (a copy)."""
    if not isinstance(schema, dict):
        schema = json.loads(schema)
    dt = dtype if dtype is not None else raw_dtype(schema)
    buf = bytearray(schema["body_size"])
    buf[:len(data)] = data
    return np.ndarray((), dt, buffer=buf)
