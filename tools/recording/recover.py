"""Recovery: rewrite what is readable of a cut recording (a recorder killed with SIGKILL,
no summary, cut anywhere) as a whole MCAP file."""

from __future__ import annotations

import json
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, Writer

from tools.recording.reader import iter_records_tolerant
from tools.recording.spool import spool_chunk_indexes
from tools.recording.schema import CHUNK_SIZE, LIBRARY, PROFILE, RAW_TOPIC, decode_raw, raw_dtype

@dataclass
class RecoverReport:
    """What :func:`recover` found."""

    source: str
    output: str
    messages: int = 0
    channels: int = 0
    schemas: int = 0
    attachments: int = 0
    metadata: int = 0
    had_footer: bool = False
    stopped_by: str = ""       #: why reading stopped early ("" = clean end)
    topic_counts: dict[str, int] = field(default_factory=dict)
    frames: int = 0            #: raw inputs frames recovered
    frame_gaps: int = 0        #: missing frame numbers inside the recovered raw stream

    def describe(self) -> str:
        tc = ", ".join(f"{t} {n}" for t, n in sorted(self.topic_counts.items()))
        return (f"{self.source}: {'complete file' if self.had_footer else 'no footer (unfinished)'}"
                f"{'; stopped at: ' + self.stopped_by if self.stopped_by else ''}; recovered "
                f"{self.messages} messages ({self.frames} frames, {self.frame_gaps} frame gaps), "
                f"{self.channels} channels, {self.attachments} attachments, {self.metadata} "
                f"metadata -> {self.output}" + (f"\n  per topic: {tc}" if tc else ""))



def recover(src: str | Path, dst: str | Path | None = None, *,
            compression: CompressionType = CompressionType.ZSTD) -> RecoverReport:
    """Rewrite what is readable of ``src`` (e.g. a recorder killed mid-file) as a whole MCAP.

    :param dst: output path (default ``<src stem>-recovered.mcap``)
    """
    from mcap.records import Attachment, Channel, Footer, Header, Message, Metadata, Schema
    src = Path(src)
    dst = Path(dst) if dst is not None else src.with_name(src.stem + "-recovered.mcap")
    if dst.resolve() == src.resolve():
        raise ValueError("recover: the output must differ from the input")
    rep = RecoverReport(str(src), str(dst))
    schemas: dict[int, Any] = {}
    sid_map: dict[int, int] = {}
    cid_map: dict[int, int] = {}
    topic_of: dict[int, str] = {}
    counts: dict[str, int] = defaultdict(int)
    last_frame = -1
    raw_dt = None
    raw_schema_d = None
    with open(dst, "wb") as out:
        w = Writer(out, compression=compression, chunk_size=CHUNK_SIZE)
        spool = spool_chunk_indexes(w, dst.resolve().parent)  # an hour's recording: ~29,000 chunks
        started = False
        for rec, reason in iter_records_tolerant(src):
            if rec is None:
                rep.stopped_by = reason
                break
            if isinstance(rec, Header):
                w.start(profile=rec.profile, library=rec.library)
                started = True
                continue
            if not started:
                w.start(profile=PROFILE, library=LIBRARY)
                started = True
            if isinstance(rec, Schema):
                if rec.id not in sid_map:
                    schemas[rec.id] = rec
                    sid_map[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                    rep.schemas += 1
            elif isinstance(rec, Channel):
                if rec.id not in cid_map:
                    cid_map[rec.id] = w.register_channel(rec.topic, rec.message_encoding,
                                                         sid_map.get(rec.schema_id, 0), rec.metadata)
                    topic_of[rec.id] = rec.topic
                    rep.channels += 1
                    if rec.topic == RAW_TOPIC and rec.schema_id in schemas:
                        raw_schema_d = json.loads(schemas[rec.schema_id].data)
                        raw_dt = raw_dtype(raw_schema_d)
            elif isinstance(rec, Message):
                if rec.channel_id not in cid_map:
                    continue
                w.add_message(cid_map[rec.channel_id], rec.log_time, rec.data, rec.publish_time,
                              rec.sequence)
                rep.messages += 1
                topic = topic_of[rec.channel_id]
                counts[topic] += 1
                if topic == RAW_TOPIC and raw_dt is not None:
                    fr = int(decode_raw(raw_schema_d, rec.data, raw_dt)["frame"])
                    if last_frame >= 0 and fr > last_frame + 1:
                        rep.frame_gaps += fr - last_frame - 1
                    last_frame = fr
                    rep.frames += 1
            elif isinstance(rec, Attachment):
                w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
                rep.attachments += 1
            elif isinstance(rec, Metadata):
                w.add_metadata(rec.name, rec.metadata)
                rep.metadata += 1
            elif isinstance(rec, Footer):
                rep.had_footer = True
        if not started:
            w.start(profile=PROFILE, library=LIBRARY)
        rep.topic_counts = dict(counts)
        w.add_metadata("pfma.recovered", {"source": str(src), "messages": str(rep.messages),
                                          "had_footer": str(rep.had_footer),
                                          "stopped_by": rep.stopped_by})
        rep.metadata += 1
        w.finish()
        if spool is not None:
            spool.close()
    return rep
