"""Reading a recording back: every readable record of a (possibly cut) file, the decoded
frames and JSON messages of a finished one, its metadata."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from tools.recording.schema import RAW_ENCODING, RAW_TOPIC, decode_raw, raw_dtype

def iter_records_tolerant(path: str | Path) -> Iterator[tuple[Any, str]]:
    """Every record readable from an MCAP file from the start; stops at the first damage.

    Yields ``(record, "")``; the last item is ``(None, reason)`` when reading stopped
    before a footer (truncated or corrupt), ``(None, "")`` after a clean end.
    """
    from mcap.records import Footer
    from mcap.stream_reader import StreamReader
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, record_size_limit=1 << 30).records:
                yield rec, ""
                if isinstance(rec, Footer):
                    yield None, ""
                    return
        except Exception as err:  # noqa: BLE001 - any damage ends the readable part
            yield None, f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
            return
    yield None, "end of file without a footer"


def read_frames(path: str | Path, topics: tuple[str, ...] = (RAW_TOPIC,)) -> Iterator[tuple[str, int, Any]]:
    """``(topic, log_time_ns, decoded)`` for the given topics of a finished recording,
    in log-time order: raw frames as numpy records, JSON topics as dicts."""
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        r = make_reader(f)
        dts: dict[int, tuple[dict, np.dtype]] = {}
        for schema, channel, msg in r.iter_messages(topics=list(topics), log_time_order=True):
            if channel.message_encoding == RAW_ENCODING:
                if schema.id not in dts:
                    sd = json.loads(schema.data)
                    dts[schema.id] = (sd, raw_dtype(sd))
                sd, dt = dts[schema.id]
                yield channel.topic, msg.log_time, decode_raw(sd, msg.data, dt)
            else:
                yield channel.topic, msg.log_time, json.loads(msg.data)


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """All metadata records of a finished recording, by name (the last of each name wins)."""
    from mcap.reader import make_reader
    with open(path, "rb") as f:
        return {m.name: dict(m.metadata) for m in make_reader(f).iter_metadata()}
