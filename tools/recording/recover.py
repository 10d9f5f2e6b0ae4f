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



class _Rewrite:
    """The state of one recovery: the records read so far, rewritten into ``w``."""

    def __init__(self, w: Writer, rep: RecoverReport):
        self.w, self.rep = w, rep
        self.started = False
        self.schemas: dict[int, Any] = {}
        self.sid_map: dict[int, int] = {}
        self.cid_map: dict[int, int] = {}
        self.topic_of: dict[int, str] = {}
        self.counts: dict[str, int] = defaultdict(int)
        self.last_frame = -1
        self.raw_dt = None
        self.raw_schema_d = None

    def start(self, profile: str = PROFILE, library: str = LIBRARY) -> None:
        """Start the output (once): with the source's header, else with ours."""
        if not self.started:
            self.w.start(profile=profile, library=library)
            self.started = True

    def header(self, rec) -> None:
        self.w.start(profile=rec.profile, library=rec.library)
        self.started = True

    def schema(self, rec) -> None:
        if rec.id not in self.sid_map:
            self.schemas[rec.id] = rec
            self.sid_map[rec.id] = self.w.register_schema(rec.name, rec.encoding, rec.data)
            self.rep.schemas += 1

    def channel(self, rec) -> None:
        if rec.id in self.cid_map:
            return
        self.cid_map[rec.id] = self.w.register_channel(rec.topic, rec.message_encoding,
                                                       self.sid_map.get(rec.schema_id, 0), rec.metadata)
        self.topic_of[rec.id] = rec.topic
        self.rep.channels += 1
        if rec.topic == RAW_TOPIC and rec.schema_id in self.schemas:
            self.raw_schema_d = json.loads(self.schemas[rec.schema_id].data)
            self.raw_dt = raw_dtype(self.raw_schema_d)

    def message(self, rec) -> None:
        if rec.channel_id not in self.cid_map:
            return
        self.w.add_message(self.cid_map[rec.channel_id], rec.log_time, rec.data, rec.publish_time,
                           rec.sequence)
        self.rep.messages += 1
        topic = self.topic_of[rec.channel_id]
        self.counts[topic] += 1
        if topic == RAW_TOPIC and self.raw_dt is not None:
            self._count_frame(int(decode_raw(self.raw_schema_d, rec.data, self.raw_dt)["frame"]))

    def _count_frame(self, fr: int) -> None:
        """Count a raw inputs frame, and the frame numbers missing before it."""
        if self.last_frame >= 0 and fr > self.last_frame + 1:
            self.rep.frame_gaps += fr - self.last_frame - 1
        self.last_frame = fr
        self.rep.frames += 1

    def attachment(self, rec) -> None:
        self.w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
        self.rep.attachments += 1

    def metadata(self, rec) -> None:
        self.w.add_metadata(rec.name, rec.metadata)
        self.rep.metadata += 1

    def footer(self, rec) -> None:
        self.rep.had_footer = True

    def take(self, rec) -> None:
        """Rewrite one record (a record of a kind not listed is skipped)."""
        from mcap.records import Attachment, Channel, Footer, Header, Message, Metadata, Schema
        if isinstance(rec, Header):
            self.header(rec)
            return
        self.start()
        handlers = ((Schema, self.schema), (Channel, self.channel), (Message, self.message),
                    (Attachment, self.attachment), (Metadata, self.metadata), (Footer, self.footer))
        for kind, handle in handlers:
            if isinstance(rec, kind):
                handle(rec)
                return

    def finish(self, src: Path) -> None:
        """Close the output: the per-topic counts, and a ``pfma.recovered`` metadata record."""
        self.start()
        rep = self.rep
        rep.topic_counts = dict(self.counts)
        self.w.add_metadata("pfma.recovered", {"source": str(src), "messages": str(rep.messages),
                                               "had_footer": str(rep.had_footer),
                                               "stopped_by": rep.stopped_by})
        rep.metadata += 1
        self.w.finish()


def recover(src: str | Path, dst: str | Path | None = None, *,
            compression: CompressionType = CompressionType.ZSTD) -> RecoverReport:
    """Rewrite what is readable of ``src`` (e.g. a recorder killed mid-file) as a whole MCAP.

    :param dst: output path (default ``<src stem>-recovered.mcap``)
    """
    src = Path(src)
    dst = Path(dst) if dst is not None else src.with_name(src.stem + "-recovered.mcap")
    if dst.resolve() == src.resolve():
        raise ValueError("recover: the output must differ from the input")
    rep = RecoverReport(str(src), str(dst))
    with open(dst, "wb") as out:
        w = Writer(out, compression=compression, chunk_size=CHUNK_SIZE)
        spool = spool_chunk_indexes(w, dst.resolve().parent)  # an hour's recording: ~29,000 chunks
        rw = _Rewrite(w, rep)
        for rec, reason in iter_records_tolerant(src):
            if rec is None:
                rep.stopped_by = reason
                break
            rw.take(rec)
        rw.finish(src)
        if spool is not None:
            spool.close()
    return rep
