"""The recorder: every published frame of a buffer into an MCAP file (see the package
docstring for the channels, the time stamps and the counters that prove nothing was lost)."""

from __future__ import annotations

import json
import os
import time
from collections import defaultdict
from pathlib import Path
from typing import IO, TYPE_CHECKING, Callable

import numpy as np
from mcap.writer import CompressionType, Writer

from bit3.client import Client
from bit3.buffer import decode_messages
from bit3.layout import QUEUE_LEN, Layout
from tools.recording.spool import spool_chunk_indexes
from tools.recording.schema import (
    CHUNK_SIZE, COUNTERS_EVERY_S, FLUSH_EVERY_S, LIBRARY, PROFILE, RAW_ENCODING, RAW_SCHEMA, RAW_SCHEMA_ENCODING,
    RAW_TOPIC, _ns, epoch_offset_ns, raw_schema,
)
from tools.recording.topics import DEVICE_TOPICS, RecorderCounters, _dumps, _Topics, json_schema

if TYPE_CHECKING:
    from tools.recording.wm import WmSampler

#: recent recorded frame numbers kept to count frames before a stats snapshot
_RING = 4096


def epoch_offset_ns_default() -> int:
    return epoch_offset_ns()


# ----------------------------------------------------------------------------------------
# the recorder


class Recorder:
    """Writes every frame of a buffer to an MCAP file. Not thread-safe; call :meth:`poll`
    at least once per frame period (the CLI loop does; tests call it from the rig).

    :param client: a read-only :class:`Client` on the buffer (see :meth:`attach`)
    :param out: file path or binary stream
    :param rack: the rack configuration (for the ``pfma channels --json`` metadata)
    :param epoch_offset_ns: added to service-clock ns for log_time (default: Unix - monotonic)
    :param json_every: write the JSON device channels for every Nth sample (1 = all)
    :param flush_every_s: close the chunk and flush at least this often (wall time)
    :param wall: wall-time source for flushing and the counters channel
    :param wm: chosen world-model variables (``/pfma/wm/<area>`` topics, sampled from
        :meth:`poll`; :mod:`tools.recording.wm`); the recorder closes it
    """

    def __init__(self, client: Client | None, out: str | Path | IO[bytes], *, rack=None,
                 epoch_offset_ns: int | None = None, json_every: int = 1,
                 flush_every_s: float = FLUSH_EVERY_S, chunk_size: int = CHUNK_SIZE,
                 compression: CompressionType = CompressionType.ZSTD,
                 wall: Callable[[], float] = time.monotonic, layout: Layout | None = None,
                 meta: dict[str, str] | None = None, wm: "WmSampler | None" = None) -> None:
        if client is None and layout is None:
            raise ValueError("Recorder needs a client or a layout")
        self.layout = layout or client.layout
        self.rack = rack
        self.offset_ns = epoch_offset_ns if epoch_offset_ns is not None else epoch_offset_ns_default()
        self.json_every = max(1, int(json_every))
        self.flush_every_s = flush_every_s
        self.wall = wall
        self.counters = RecorderCounters()
        self.topic_counts: dict[str, int] = defaultdict(int)
        self._own_file = not hasattr(out, "write")
        self._f = open(out, "wb") if self._own_file else out
        self.path = str(out) if self._own_file else getattr(out, "name", "<stream>")
        self.w = Writer(self._f, chunk_size=chunk_size, compression=compression)
        #: the writer's chunk indexes, on disk until the summary (None: this mcap keeps them
        #: in memory; tools/recording/spool.py)
        self.index_spool = spool_chunk_indexes(self.w, Path(out).resolve().parent if self._own_file else None)
        self.w.start(profile=PROFILE, library=LIBRARY)
        self.t = _Topics(self.layout)
        self._device_topics = tuple((topic, tf, getattr(self.t, enc)) for topic, tf, enc in DEVICE_TOPICS)
        self._ch: dict[str, int] = {}
        self._schema_raw = raw_schema(self.layout)
        self._raw_len = self._schema_raw["stored_bytes"]
        sid = self.w.register_schema(RAW_SCHEMA, RAW_SCHEMA_ENCODING,
                                     json.dumps(self._schema_raw).encode())
        self._ch[RAW_TOPIC] = self.w.register_channel(RAW_TOPIC, RAW_ENCODING, sid,
                                                      {"area": "inputs", "layout_hash": self.layout.hash_hex})
        self.wm = wm
        wm_topics = wm.topics() if wm is not None else {}
        for topic, schema in {**self.t.schemas(), **wm_topics}.items():
            name, doc = json_schema(topic, schema)
            sid = self.w.register_schema(name, "jsonschema", doc)
            self._ch[topic] = self.w.register_channel(
                topic, "json", sid, {"world_model": wm.name} if topic in wm_topics and wm else {})
        self._meta_extra = dict(meta or {})
        self._wrote_meta = False
        self.client: Client | None = None
        self._t0_wall = wall()
        self._last_flush = self._t0_wall
        self._last_counters = self._t0_wall
        self._ring = np.full(_RING, -1, dtype=np.int64)
        self._stats_pending: tuple[int, int, int] | None = None
        self._ring_i = 0
        self._win_acc = (0, 0, 0)
        self._win_new = False
        self._closed = False
        self._log_ns = self.offset_ns
        #: True while a capture thread copies the message queues (``InputsCapture(messages=
        #: True)``, written through :meth:`feed_messages`): :meth:`poll` then reads none
        self.messages_captured = False
        #: what went wrong as it happened (lost message entries), for the process to say
        self.notes: list[str] = []
        if client is not None:
            self.attach(client)

    # --- session management ---
    def attach(self, client: Client) -> None:
        """Start recording from a (new) client: a new session (service start or restart)."""
        if client.layout.hash != self.layout.hash:
            raise ValueError(f"recorder: buffer layout {client.layout.hash_hex} differs from the "
                             f"recording's {self.layout.hash_hex}")
        self._count_stats()  # the last session's last snapshot, with what it recorded
        self.client = client
        self.counters.sessions += 1
        t_frame = client.header().frame_t_s  # the service's newest frame: messages recorded
        if t_frame > 0:  # before the first frame (a command area never written) are stamped
            self._log_ns = _ns(t_frame, self.offset_ns)  # there, not at host boot (t = 0)
        self._last_seq = -1
        self._last_frame = -1
        self._last_t = {}
        self._json_n = 0
        self._stats_first = None  # (frame, frames, dropped, recorded_before)
        self._stats_pending = None  # a stats snapshot not yet counted (see _stats)
        self._links_key = b""
        self._boards_key = b""
        self._msg_cursor = {"service": None, "controller": None}
        if not self._wrote_meta:
            self._write_metadata(client)
        # skip messages posted before the recording (they are history, not this recording)...
        for q in self._msg_cursor:
            try:
                self._msg_cursor[q] = client.buffer.queue(q + "_messages").head_seq
            except Exception:  # noqa: BLE001 - an unclaimed queue reads as 0
                self._msg_cursor[q] = 0
        self._new_window()

    def _write_metadata(self, client: Client) -> None:
        hdr = client.header()
        lay = self.layout
        self.w.add_metadata("pfma.recording", {
            "epoch_offset_ns": str(self.offset_ns),
            "log_time": "service clock t_s * 1e9 + epoch_offset_ns (Unix ns)",
            "buffer": client.buffer.name, "host": os.uname().nodename, "pid": str(os.getpid()),
            "started_unix_ns": str(time.time_ns()), "json_every": str(self.json_every),
            "flush_every_s": str(self.flush_every_s), "raw_topic": RAW_TOPIC,
            "raw_encoding": RAW_ENCODING, **self._meta_extra})
        self.w.add_metadata("pfma.layout", {
            "hash": lay.hash_hex, "version": str(lay.version), "rack": lay.rack_name,
            "buffer_layout_hash": hdr.layout_hash.hex(), "size": str(lay.size)})
        self.w.add_metadata("pfma.calibration", {"hash": hdr.calibration_hash.hex()})
        if self.wm is not None:
            self.w.add_metadata("pfma.wm", self.wm.metadata())
        now = time.time_ns()
        self.w.add_attachment(now, now, "bit3-layout.json", "application/json",
                              json.dumps(lay.as_json()).encode())
        if self.rack is not None:
            chans = [c.as_dict() for c in self.rack.channels()]
            self.w.add_metadata("pfma.rack", {"name": self.rack.name, "source": str(self.rack.source),
                                              "channels": str(len(chans))})
            self.w.add_attachment(now, now, "rack-channels.json", "application/json",
                                  json.dumps(chans).encode())
        self._wrote_meta = True

    # --- writing ---
    def put(self, topic: str, t_ns: int, payload: bytes) -> None:
        """Write one message on a registered topic (log time = publish time = ``t_ns``)."""
        self._put(topic, t_ns, payload)

    def _put(self, topic: str, t_ns: int, payload: bytes) -> None:
        n = self.topic_counts[topic]
        self.w.add_message(self._ch[topic], t_ns, payload, t_ns, n & 0xFFFFFFFF)
        self.topic_counts[topic] = n + 1
        self.counters.messages_total += 1

    def poll(self, inputs: bool = True) -> int:
        """Read what changed since the last call and write it; returns frames written (0/1).

        :param inputs: False when an :class:`InputsCapture` thread reads the inputs area
            (its snapshots go through :meth:`feed_inputs`)
        """
        c = self.client
        n = 0
        if c is not None:
            if inputs and c.changed("inputs"):
                n = self._inputs(c.read_inputs())
            if c.changed("commands"):
                self._commands(c.read_commands())
            if c.changed("stats"):
                self._stats(c.read_stats())
            self._messages()
        if self.wm is not None:  # the world model at its requested rates, from this loop
            self.wm.poll(self)
        now = self.wall()
        if now - self._last_counters >= COUNTERS_EVERY_S:
            self._last_counters = now
            self.write_counters()
        if now - self._last_flush >= self.flush_every_s:
            self._last_flush = now
            self.w.flush()
        return n

    def feed_inputs(self, snap) -> int:
        """Write one inputs snapshot captured elsewhere (a private copy, in publish order);
        returns frames written (0/1). Publishes the capture never saw show as
        ``recorder_missed`` from the sequence numbers, as with :meth:`poll`."""
        return self._inputs(snap)

    def _inputs(self, snap) -> int:
        r = snap.record
        seq = snap.seq
        if seq == 0:  # never published (a buffer the service has not written yet)
            return 0
        frame = int(r["frame"])
        t_s = float(r["t_s"])
        consecutive = self._count_seq(seq)
        head = {"t_s": t_s, "frame": frame}
        t_ns = _ns(t_s, self.offset_ns)
        self._log_ns = t_ns
        if frame == self._last_frame:  # the same frame published again (stop: STOPPED state)
            self.counters.republished += 1
            self._put("/pfma/status", t_ns, _dumps(self.t.status(r, head)))
            return 0
        self._count_frame(frame, consecutive)
        if self._stats_pending is not None and frame >= self._stats_pending[0] - 1:
            self._count_stats()
        self._put(RAW_TOPIC, t_ns, self._raw_bytes(snap.record))
        self._put("/pfma/status", t_ns, _dumps(self.t.status(r, head)))
        self._json_n += 1
        if self._json_n % self.json_every:
            return 1
        self._derived(r, frame, head, t_ns)
        return 1

    def _count_seq(self, seq: int) -> bool:
        """Count the publishes missed before sequence number ``seq``; True when it follows
        the last one read directly (or is the first)."""
        consecutive = self._last_seq < 0 or seq - self._last_seq == 2
        if self._last_seq >= 0 and seq - self._last_seq > 2:
            self.counters.recorder_missed += (seq - self._last_seq) // 2 - 1
        self._last_seq = seq
        return consecutive

    def _count_frame(self, frame: int, consecutive: bool) -> None:
        """Count a new frame: a restart, the frames missing before it (the service's skips
        when no publish was missed), first and last frame, the ring of recent frames."""
        cnt = self.counters
        if self._last_frame >= 0:
            if frame < self._last_frame:  # the service restarted on the same buffer
                self.counters.sessions += 1
                self._new_window()
            elif frame > self._last_frame + 1:
                gap = frame - self._last_frame - 1
                cnt.frame_gaps += gap
                if consecutive:
                    cnt.service_skipped += gap
        self._last_frame = frame
        if self._session_first < 0:
            self._session_first = frame
        if cnt.first_frame < 0:
            cnt.first_frame = frame
        cnt.last_frame = frame
        cnt.frames_recorded += 1
        self._ring[self._ring_i % _RING] = frame
        self._ring_i += 1

    def _derived(self, r, frame: int, head: dict, t_ns: int) -> None:
        """The JSON topics derived from an inputs frame, each when it changed: the devices'
        samples, the hand controller, the boards, the links."""
        lt = self._last_t
        for topic, tf, fn in self._device_topics:
            ts = float(r[tf])
            if ts != lt.get(tf) and ts > 0:
                lt[tf] = ts
                self._put(topic, _ns(ts, self.offset_ns), _dumps(fn(r, {"t_s": ts, "frame": frame})))
        hk = r["hc_t_s"].tobytes()
        if hk != lt.get("hc"):
            lt["hc"] = hk
            self._put("/pfma/hand", t_ns, _dumps(self.t.hand(r, head)))
        bk = self.t.boards_key(r)
        if bk != self._boards_key:
            self._boards_key = bk
            self._put("/pfma/boards", t_ns, _dumps(self.t.boards(r, head)))
        lk = self.t.links_key(r)
        if lk != self._links_key:
            self._links_key = lk
            self._put("/pfma/links", t_ns, _dumps(self.t.links(r, head)))

    def _raw_bytes(self, record: np.ndarray) -> bytes:
        """The stored part of the body, from the snapshot's private copy (one copy)."""
        base = record.base
        if isinstance(base, (bytearray, bytes)):
            return bytes(memoryview(base)[:self._raw_len])
        return record.tobytes()[:self._raw_len]

    def _commands(self, snap) -> None:
        d = snap.as_dict()
        self.counters.commands_recorded += 1
        self._put("/pfma/commands", _ns(float(d.get("t_s", 0.0)), self.offset_ns) if d.get("t_s")
                  else self._log_ns, _dumps(d))

    def _stats(self, snap) -> None:
        d = snap.as_dict()
        cnt = self.counters
        cnt.stats_snapshots += 1
        self._put("/pfma/stats", _ns(float(d["t_s"]), self.offset_ns), _dumps(d))
        # counted once every frame before k that will be recorded is: the capture thread may
        # still hold frames this snapshot follows (counted now, the window came out one or
        # two frames short at random); frames come in order, so that is when frame k - 1 or
        # a later one has been recorded, or at the end
        self._stats_pending = (int(d["frame"]), int(d["frames"]), int(d["dropped_frames"]))
        if self._last_frame >= self._stats_pending[0] - 1:
            self._count_stats()

    def _count_stats(self) -> None:
        """The stats window with the pending snapshot (see :meth:`_stats`)."""
        pending, self._stats_pending = self._stats_pending, None
        if pending is None or self._last_frame < pending[0] - 1:
            # not every frame before k was recorded when the recording (or the session) ended:
            # the window ends at the snapshot before (counted now, it came out a frame short)
            return
        cnt = self.counters
        k, frames, dropped = pending
        # frames recorded with frame number < k
        before = self._ring_i - int(np.count_nonzero(self._ring >= k))
        first = self._stats_first
        if first is None:
            # a baseline needs every frame >= k to be recordable: k at or after our first frame
            if self._session_first >= 0 and k >= self._session_first:
                self._stats_first = (k, frames, dropped, before)
            return
        k1, f1, d1, b1 = first
        if k <= k1:
            return
        a = self._win_acc
        if cnt.window_first_frame < 0 or self._win_new:
            cnt.window_first_frame = k1
            self._win_new = False
        cnt.window_last_frame = k
        cnt.window_service_frames = a[0] + frames - f1
        cnt.window_recorded = a[1] + before - b1
        cnt.window_service_dropped = a[2] + dropped - d1

    def _new_window(self) -> None:
        """A new service session: keep the finished window's counts, start a new window."""
        self._count_stats()  # the last session's last snapshot, with what it recorded
        cnt = self.counters
        self._win_acc = (cnt.window_service_frames, cnt.window_recorded, cnt.window_service_dropped)
        self._win_new = True
        self._stats_first = None
        self._session_first = -1
        self._ring[:] = -1

    def _messages(self) -> None:
        if self.messages_captured:  # the capture thread copies them (feed_messages)
            return
        c = self.client
        for q in ("service", "controller"):
            cur = self._msg_cursor[q]
            try:
                head = c.buffer.queue(q + "_messages").head_seq
            except Exception:  # noqa: BLE001
                continue
            if head != cur:
                self._write_messages(q, head, c.messages(0 if head < cur else cur, q))

    def feed_messages(self, queue: str, body) -> None:
        """Write the messages new in ``body``, a copy of one message queue's body taken
        elsewhere (the capture thread's ``MessagesCopy``), as :meth:`poll` does."""
        cur, head = self._msg_cursor[queue], int(body["head_seq"])
        if cur is None or head == cur:
            return
        self._write_messages(queue, head, decode_messages(queue + "_messages", body,
                                                          0 if head < cur else cur))

    def _write_messages(self, q: str, head: int, got: list) -> None:
        """Write ``got``, the messages of queue ``q`` after its cursor (now at ``head``); a
        gap before the first is counted (``messages_missed``) and said (:attr:`notes`)."""
        cur = self._msg_cursor[q]
        if head < cur:  # a new buffer (service restart): start over
            cur = 0
        if got and got[0].first_seq > cur + 1:  # a long message takes several entries
            lost = got[0].first_seq - cur - 1
            self.counters.messages_missed += lost
            self.notes.append(f"{lost} {q} message entries ({cur + 1}..{got[0].first_seq - 1}) were "
                              f"overwritten before the recorder read them (the queue holds "
                              f"{QUEUE_LEN[q + '_messages']}); the recording is not lossless")
        for m in got:
            self._put("/pfma/messages", _ns(m.t_s, self.offset_ns), _dumps({
                "queue": q, "seq": m.seq, "t_s": m.t_s, "severity": m.severity.name,
                "code": m.code, "source": m.source, "text": m.text}))
        self._msg_cursor[q] = got[-1].seq if got else head

    def _finish_counters(self) -> RecorderCounters:
        self._count_stats()
        cnt = self.counters
        cnt.wall_s = self.wall() - self._t0_wall
        cnt.topic_counts = json.dumps(dict(self.topic_counts))
        window_ok = cnt.window_recorded == cnt.window_service_frames
        cnt.lossless = cnt.recorder_missed == 0 and window_ok and cnt.messages_missed == 0
        return cnt

    def write_counters(self) -> RecorderCounters:
        """Write the counters on ``/pfma/recorder`` now."""
        cnt = self._finish_counters()
        self._put("/pfma/recorder", self._log_ns, _dumps(cnt.as_dict()))
        cnt.topic_counts = json.dumps(dict(self.topic_counts))
        return cnt

    def flush(self) -> None:
        self.w.flush()

    def close(self) -> RecorderCounters:
        """Final poll, counters, summary metadata, MCAP summary; closes the file (idempotent)."""
        if self._closed:
            return self.counters
        try:
            if self.client is not None:
                try:
                    self.poll()
                except Exception:  # noqa: BLE001 - a vanished buffer must not lose the file
                    pass
            if self.wm is not None and self.client is None:  # the final poll above did not reach it
                try:
                    self.wm.poll(self)
                except Exception:  # noqa: BLE001 - a vanished world model must not lose the file
                    pass
            cnt = self.write_counters()
            self.w.flush()
            self.w.add_metadata("pfma.recorder.summary", {k: str(v) for k, v in cnt.as_dict().items()})
            if self.wm is not None:
                self.w.add_metadata("pfma.wm.summary", {k: json.dumps(v) if isinstance(v, dict) else str(v)
                                                        for k, v in self.wm.counters.as_dict().items()})
            self.w.finish()
        finally:
            self._closed = True
            if self.index_spool is not None:
                self.index_spool.close()
            if self.wm is not None:
                self.wm.close()
            if self._own_file:
                self._f.close()
            else:
                self._f.flush()
        return self.counters
