"""Live plots in Foxglove (issue 19 item 4): ``pfma foxglove`` serves a running service's
channels over the foxglove-sdk WebSocket server, under the same names and schemas as an
MCAP recording (docs/recording.md), so the Foxglove app shows the live system as it shows
a recording, with the same layouts.

It is a reader in its own process, outside the service's frame loop: every ``1/rate``
seconds (20-60 Hz; the foxglove-sdk reference notes measured ~111 us for one ``log()`` of
a 50-field dict, too much for a 320 Hz loop) it takes the newest inputs and sends

- ``/pfma/inputs_raw``: the newest inputs body, byte for byte (``pfma-bit3-v1``, its field
  table in the schema: ``tools.recording.decode_raw`` decodes it), and ``/pfma/status``;
- ``/pfma/joints``, ``/adc``, ``/dac``, ``/ft``, ``/pio`` when that group's sample time
  changed since the last tick, ``/pfma/hand``, ``/boards``, ``/links`` when they changed
  (the recorder's rules, :data:`tools.recording.topics.DEVICE_TOPICS`);
- ``/pfma/commands`` and ``/pfma/stats`` when their areas changed, ``/pfma/messages`` for
  each new message of both queues.

So the live view is decimated to the tick rate (a recording has every frame). The
encoders and schemas are the recorder's (:class:`tools.recording.topics._Topics`,
:func:`tools.recording.topics.json_schema`); ``/pfma/recorder`` (a recorder's own counters)
is not served. Log times are the recording's: the service clock plus the Unix-minus-
monotonic offset taken at start.
"""

from __future__ import annotations

import json
import time
from typing import Any, Callable

from tools.recording.schema import RAW_ENCODING, RAW_SCHEMA, RAW_SCHEMA_ENCODING, RAW_TOPIC, _ns, epoch_offset_ns, raw_schema
from tools.recording.topics import DEVICE_TOPICS, _dumps, _Topics, json_schema

#: the tick rates ``pfma foxglove --rate`` accepts, Hz (issue 19: a reader at 20-60 Hz)
RATE_MIN_HZ, RATE_MAX_HZ = 20.0, 60.0
DEFAULT_RATE_HZ = 30.0
#: the WebSocket server's default port (Foxglove's own default) and address (loopback:
#: nothing leaves the host unless --host says so)
DEFAULT_PORT = 8765
DEFAULT_HOST = "127.0.0.1"
#: the recorder's topic not served live
NOT_SERVED = ("/pfma/recorder",)


class LiveChannels:
    """The recording's channels on a foxglove-sdk context, fed from a reader client.

    :param client: a read-only :class:`bit3.client.Client` (or a RemoteBuffer)
    :param context: the foxglove :class:`Context` whose sinks (a WebSocket server) get the
        messages (default: the SDK's global context)
    """

    def __init__(self, client: Any, *, context: Any = None, epoch_offset: int | None = None) -> None:
        import foxglove
        self.client = client
        self.layout = client.layout
        self.offset_ns = epoch_offset_ns() if epoch_offset is None else epoch_offset
        self.t = _Topics(self.layout)
        self.channels: dict[str, Any] = {}
        for topic, schema in self.t.schemas().items():
            if topic in NOT_SERVED:
                continue
            name, doc = json_schema(topic, schema)
            self.channels[topic] = foxglove.Channel(
                topic, message_encoding="json", context=context,
                schema=foxglove.Schema(name=name, encoding="jsonschema", data=doc))
        raw = raw_schema(self.layout)
        self._raw_len = raw["stored_bytes"]
        self.channels[RAW_TOPIC] = foxglove.Channel(
            RAW_TOPIC, message_encoding=RAW_ENCODING, context=context,
            schema=foxglove.Schema(name=RAW_SCHEMA, encoding=RAW_SCHEMA_ENCODING, data=json.dumps(raw).encode()),
            metadata={"area": "inputs", "layout_hash": self.layout.hash_hex})
        self._device = tuple((topic, tf, getattr(self.t, enc)) for topic, tf, enc in DEVICE_TOPICS)
        self._last_frame = -1
        self._last_t: dict[str, Any] = {}
        self._boards_key = b""
        self._links_key = b""
        self._msg_seq = {q: self._head(q) for q in ("service", "controller")}
        self.sent: dict[str, int] = {t: 0 for t in self.channels}  #: messages logged, by topic
        self.ticks = 0

    def _head(self, queue: str) -> int:
        """The newest message's sequence number (messages before the start are history)."""
        try:
            return int(self.client.buffer.queue(queue + "_messages").head_seq)
        except Exception:  # noqa: BLE001 - an unclaimed queue reads as 0
            return 0

    def _log(self, topic: str, t_s: float, payload: bytes) -> None:
        self.channels[topic].log(payload, log_time=_ns(t_s, self.offset_ns))
        self.sent[topic] += 1

    def tick(self) -> int:
        """Send what changed since the last tick; returns the messages logged."""
        self.ticks += 1
        c = self.client
        n = sum(self.sent.values())
        snap = c.read_inputs()
        r = snap.record
        frame = int(r["frame"])
        if snap.seq and frame != self._last_frame:
            self._last_frame = frame
            t_s = float(r["t_s"])
            head = {"t_s": t_s, "frame": frame}
            self._log(RAW_TOPIC, t_s, r.tobytes()[:self._raw_len])
            self._log("/pfma/status", t_s, _dumps(self.t.status(r, head)))
            lt = self._last_t
            for topic, tf, fn in self._device:
                ts = float(r[tf])
                if ts != lt.get(tf) and ts > 0:
                    lt[tf] = ts
                    self._log(topic, ts, _dumps(fn(r, {"t_s": ts, "frame": frame})))
            hk = r["hc_t_s"].tobytes()
            if hk != lt.get("hc"):
                lt["hc"] = hk
                self._log("/pfma/hand", t_s, _dumps(self.t.hand(r, head)))
            bk, lk = self.t.boards_key(r), self.t.links_key(r)
            if bk != self._boards_key:
                self._boards_key = bk
                self._log("/pfma/boards", t_s, _dumps(self.t.boards(r, head)))
            if lk != self._links_key:
                self._links_key = lk
                self._log("/pfma/links", t_s, _dumps(self.t.links(r, head)))
        if c.changed("commands"):
            d = c.read_commands().as_dict()
            self._log("/pfma/commands", float(d.get("t_s") or r["t_s"]), _dumps(d))
        if c.changed("stats"):
            d = c.read_stats().as_dict()
            self._log("/pfma/stats", float(d["t_s"]), _dumps(d))
        for q in ("service", "controller"):
            if self._head(q) == self._msg_seq[q]:
                continue
            for m in c.messages(self._msg_seq[q], q):
                self._msg_seq[q] = max(self._msg_seq[q], int(m.seq))
                self._log("/pfma/messages", float(m.t_s), _dumps({
                    "queue": q, "seq": m.seq, "t_s": m.t_s, "severity": m.severity.name,
                    "code": m.code, "source": m.source, "text": m.text}))
        return sum(self.sent.values()) - n

    def close(self) -> None:
        for ch in self.channels.values():
            ch.close()


def serve(client: Any, *, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, rate_hz: float = DEFAULT_RATE_HZ,
          done: Callable[[], bool], say: Callable[[str], None],
          sleep: Callable[[float], None] = time.sleep) -> LiveChannels:
    """Start the WebSocket server on ``host:port`` and tick the channels at ``rate_hz``
    until ``done()``; returns the channels (their counts) after stopping the server."""
    import foxglove
    ctx = foxglove.Context()
    live = LiveChannels(client, context=ctx)
    server = foxglove.start_server(name=f"pfma {client.buffer.name}", host=host, port=port, context=ctx)
    try:
        say(f"serving {len(live.channels)} channels of buffer {client.buffer.name!r} at {rate_hz:g} Hz on "
            f"ws://{host}:{server.port} (Foxglove: Open connection -> Foxglove WebSocket; Ctrl-C stops)")
        period = 1.0 / rate_hz
        t_next = time.monotonic()
        while not done():
            live.tick()
            t_next += period
            delay = t_next - time.monotonic()
            if delay > 0:
                sleep(delay)
            else:
                t_next = time.monotonic()  # fell behind: no burst to catch up
    finally:
        server.stop()
        live.close()
    return live
