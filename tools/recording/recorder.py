"""Lossless MCAP recording of the Bit3 buffer, recovery of cut files, reading back.

One recorder attaches **read-only** to the buffer and writes every published frame of
the inputs area into an MCAP file (https://mcap.dev/spec), twice:

- ``/pfma/inputs_raw``: the inputs area body as published, byte for byte, every frame.
  Schema ``pfma.bit3.inputs`` (schema encoding ``pfma-bit3-layout``) carries the field
  table (name, offset in the body, dtype, shape, units) so the bytes decode without this
  program (:func:`decode_raw`); message encoding ``pfma-bit3-v1``. This is the lossless
  stream: it holds every field of every frame, exactly as the buffer held it.
- JSON channels (schema encoding ``jsonschema``, message encoding ``json``) that
  Foxglove's Plot panel plots directly, one per device group, each written when that
  group's sample time changes (its native rate), with raw and engineering values:
  ``/pfma/joints`` (resolvers), ``/pfma/adc``, ``/pfma/dac``, ``/pfma/ft``, ``/pfma/hand``,
  ``/pfma/pio``, ``/pfma/status`` (every frame), ``/pfma/boards`` and ``/pfma/links``
  (when they change), ``/pfma/commands`` (controller area), ``/pfma/stats`` (2 Hz),
  ``/pfma/messages`` (both message queues) and ``/pfma/recorder`` (this recorder's own
  counters, every second and at the end).

Why both (measured, docs/recording.md): JSON for every channel of a frame costs about
0.1 ms of Python per frame; the raw copy costs a few microseconds. Raw alone would not
open in Foxglove (a private encoding needs an extension; packages.md section 4), JSON
alone would lose fields nobody put in a topic. ``json_every`` decimates the JSON channels
on a slow machine; the raw stream is never decimated.

Time: ``log_time`` = ``publish_time`` = the sample's service-clock time (``t_s``, the
monotonic clock of the service host) plus ``epoch_offset_ns`` (Unix time minus monotonic
time, taken when the recording starts), so Foxglove's timeline is wall-clock time
(timestamps near 1970 break its preloading: foxglove/mcap#1296, anchors.md section 5).
The offset is stored in the ``pfma.recording`` metadata.

Counters that prove nothing was lost (``RecorderCounters``):

- every publish bumps the inputs area's sequence counter by 2, so a jump of more than 2
  between two reads is a publish the recorder missed (``recorder_missed``);
- a frame-number jump between two consecutive publishes is a frame the *service*
  skipped (its own overruns; ``service_skipped``);
- the stats area's ``frames`` (frames run before frame ``frame``) gives the service's
  own count between two statistics snapshots; the recorder counts the frames it wrote in
  the same window (``window_recorded`` vs ``window_service_frames``).

Crash safety: the writer's chunk is closed and the stream flushed every
``flush_every_s`` (0.25 s by default), so a recorder killed with SIGKILL loses less than
that; :func:`recover` rewrites such a file (no summary, cut anywhere) whole.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections import defaultdict, deque
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any, Callable, Iterator

import numpy as np
from mcap.writer import CompressionType, Writer

from bit3.client import Client, Snapshot
from bit3.layout import HC_AXES, Layout, ServiceState
from bit3.buffer import MESSAGE_DTYPE  # noqa: F401  (documented message fields)

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
#: recent recorded frame numbers kept to count frames before a stats snapshot
_RING = 4096


def epoch_offset_ns() -> int:
    """Unix time minus monotonic time, in ns (maps the service's monotonic ``t_s`` to wall time)."""
    return time.time_ns() - time.monotonic_ns()


def _ns(t_s: float, offset_ns: int) -> int:
    if not math.isfinite(t_s) or t_s < 0:
        t_s = 0.0
    return offset_ns + int(round(t_s * 1e9))


def _clean(x: Any) -> Any:
    """NaN/inf -> None (JSON has no NaN; Foxglove refuses it)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_clean(v) for v in x]
    return x


def _dumps(obj: dict) -> bytes:
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
    except ValueError:
        return json.dumps(_clean(obj), separators=(",", ":")).encode()


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


# ----------------------------------------------------------------------------------------
# JSON topics: schemas and encoders


def _num(desc: str = "") -> dict:
    return {"type": "number", "description": desc} if desc else {"type": "number"}


def _int(desc: str = "") -> dict:
    return {"type": "integer", "description": desc} if desc else {"type": "integer"}


def _obj(props: dict, desc: str = "") -> dict:
    d = {"type": "object", "properties": props}
    if desc:
        d["description"] = desc
    return d


_HEAD = {"t_s": _num("sample time, service clock (s)"), "frame": _int("service minor frame")}


class _Topics:
    """Builds the JSON messages of one inputs snapshot (index arrays precomputed)."""

    def __init__(self, layout: Layout) -> None:
        self.layout = layout
        ch = [c for c in layout.channels if c.area == "inputs"]

        def group(kind: str) -> tuple[list[str], np.ndarray, list]:
            cs = [c for c in ch if c.kind == kind and not c.spare]
            return [c.name for c in cs], np.array([c.slot for c in cs], dtype=np.intp), cs

        self.g_rtd = group("rtd")
        self.g_adc = group("adc")
        self.g_dac = group("dac")
        self.g_pio = group("pio")
        self.g_board = group("board")
        self.g_link = group("link")
        self.g_hc = group("hc")

    # --- schemas ---
    def schemas(self) -> dict[str, dict]:
        lay = self.layout

        def per(cs, props):
            return {c.name: _obj(props(c), f"{c.label} [{c.units}]" + (f" ({c.board} ch {c.channel})"
                                                                         if c.channel >= 0 else ""))
                    for c in cs}
        s = {}
        s["/pfma/status"] = _obj({**_HEAD, "state": {"type": "string"},
                                  "service_state": _int("ServiceState"), "fault_code": _int(),
                                  "outputs_enabled": _int(), "brakes_released": _int(),
                                  "watchdog_tripped": _int(), "command_heartbeat": _int(),
                                  "command_age_s": _num("s")}, "service state, every frame")
        s["/pfma/joints"] = _obj({**_HEAD, **per(self.g_rtd[2], lambda c: {
            "angle_rad": _num("rad"), "counts": _int("RDC counts, 65536 per turn"),
            "status": _int("bits")})}, "resolvers (RTD), at their sample rate")
        s["/pfma/adc"] = _obj({**_HEAD, **per(self.g_adc[2], lambda c: {
            "counts": _int("raw 12-bit code"), "volts": _num("V"), "value": _num(c.units),
            "status": _int("bits")})}, "ADC channels: raw, volts, engineering value")
        s["/pfma/dac"] = _obj({**_HEAD, **per(self.g_dac[2], lambda c: {
            "counts": _int("12-bit code written"), "volts": _num("V"), "value": _num(c.units),
            "status": _int("bits")})}, "DAC channels as applied")
        xyz = _obj({"x": _num(), "y": _num(), "z": _num()})
        s["/pfma/ft"] = _obj({**_HEAD, "counts": {"type": "array", "items": _int()},
                              "force_n": xyz, "torque_nm": xyz, "status": _int("bits")},
                             "F/T sensor record (sensor frame)")
        s["/pfma/hand"] = _obj({**_HEAD, **{c.name: _obj({
            "axes": _obj({a: _num("-1..1") for a in HC_AXES}), "deadman": _int(), "valid": _int(),
            "fault": _int(), "buttons": _int(), "t_s": _num("s")}) for c in self.g_hc[2]}},
            "hand controllers")
        s["/pfma/pio"] = _obj({**_HEAD, "user_inputs": _int("16 bits"), "matrix_route": _int(),
                               **{c.name: _int("8-bit port") for c in self.g_pio[2]}}, "PIA ports")
        s["/pfma/boards"] = _obj({**_HEAD, **{c.name: _obj({
            "status": _int("bits"), "errors": _int(), "last_error_addr": _int("A16"),
            "last_error_t_s": _num("s")}) for c in self.g_board[2]}}, "board status and errors")
        s["/pfma/links"] = _obj({**_HEAD, **{c.name: _obj({
            "status": _int("bits"), "records": _int(), "bad": _int(), "resyncs": _int(),
            "errors": _int(), "rate_hz": _num("Hz"), "age_s": _num("s")}) for c in self.g_link[2]}},
            "serial/USB link counters")
        cmd = [f for f in lay.fields if f.area == "commands"]
        s["/pfma/commands"] = _obj({f.name: ({"type": "array", "items": _num(f.units)} if f.shape
                                             else _num(f.units)) for f in cmd},
                                   "command area (controller), joint order: " + ", ".join(lay.joint_names))
        st = [f for f in lay.fields if f.area == "stats"]
        s["/pfma/stats"] = _obj({f.name: ({"type": "array", "items": _num(f.units)} if f.shape
                                          else _num(f.units)) for f in st}, "service statistics")
        s["/pfma/messages"] = _obj({"queue": {"type": "string"}, "seq": _int(), "t_s": _num("s"),
                                    "severity": {"type": "string"}, "code": _int(),
                                    "source": _int(), "text": {"type": "string"}}, "message queues")
        s["/pfma/recorder"] = _obj({k: {"type": ["number", "integer", "boolean", "string", "null"]}
                                    for k in RecorderCounters.__dataclass_fields__},
                                   "recorder counters (drops, per-topic counts)")
        return s

    # --- messages ---
    def status(self, r: np.ndarray, head: dict) -> dict:
        st = int(r["service_state"])
        try:
            name = ServiceState(st).name
        except ValueError:
            name = str(st)
        return {**head, "state": name, "service_state": st, "fault_code": int(r["fault_code"]),
                "outputs_enabled": int(r["outputs_enabled"]),
                "brakes_released": int(r["brakes_released"]),
                "watchdog_tripped": int(r["watchdog_tripped"]),
                "command_heartbeat": int(r["command_heartbeat"]),
                "command_age_s": float(r["command_age_s"])}

    @staticmethod
    def _per(names, cols: dict[str, list]) -> dict:
        keys = list(cols)
        vals = list(zip(*cols.values()))
        return {n: dict(zip(keys, v)) for n, v in zip(names, vals)}

    def joints(self, r, head) -> dict:
        n, s, _ = self.g_rtd
        return {**head, **self._per(n, {"angle_rad": r["rtd_angle_rad"][s].tolist(),
                                        "counts": r["rtd_counts"][s].tolist(),
                                        "status": r["rtd_status"][s].tolist()})}

    def adc(self, r, head) -> dict:
        n, s, _ = self.g_adc
        return {**head, **self._per(n, {"counts": r["adc_counts"][s].tolist(),
                                        "volts": r["adc_volts"][s].tolist(),
                                        "value": r["adc_value"][s].tolist(),
                                        "status": r["adc_status"][s].tolist()})}

    def dac(self, r, head) -> dict:
        n, s, _ = self.g_dac
        return {**head, **self._per(n, {"counts": r["dac_counts"][s].tolist(),
                                        "volts": r["dac_volts"][s].tolist(),
                                        "value": r["dac_value"][s].tolist(),
                                        "status": r["dac_status"][s].tolist()})}

    @staticmethod
    def ft(r, head) -> dict:
        f, t = r["ft_force_n"].tolist(), r["ft_torque_nm"].tolist()
        return {**head, "counts": r["ft_counts"].tolist(),
                "force_n": {"x": f[0], "y": f[1], "z": f[2]},
                "torque_nm": {"x": t[0], "y": t[1], "z": t[2]}, "status": int(r["ft_status"])}

    def hand(self, r, head) -> dict:
        n, s, _ = self.g_hc
        out = dict(head)
        axes = r["hc_axes"][s].tolist()
        for i, name in enumerate(n):
            k = int(s[i])
            out[name] = {"axes": dict(zip(HC_AXES, axes[i])), "deadman": int(r["hc_deadman"][k]),
                         "valid": int(r["hc_valid"][k]), "fault": int(r["hc_fault"][k]),
                         "buttons": int(r["hc_buttons"][k]), "t_s": float(r["hc_t_s"][k])}
        return out

    def pio(self, r, head) -> dict:
        n, s, _ = self.g_pio
        return {**head, "user_inputs": int(r["pio_user_inputs"]), "matrix_route": int(r["matrix_route"]),
                **dict(zip(n, r["pio_port_bits"][s].tolist()))}

    def boards(self, r, head) -> dict:
        n, s, _ = self.g_board
        return {**head, **self._per(n, {"status": r["board_status"][s].tolist(),
                                        "errors": r["board_errors"][s].tolist(),
                                        "last_error_addr": r["board_last_error_addr"][s].tolist(),
                                        "last_error_t_s": r["board_last_error_t_s"][s].tolist()})}

    def links(self, r, head) -> dict:
        n, s, _ = self.g_link
        return {**head, **self._per(n, {"status": r["link_status"][s].tolist(),
                                        "records": r["link_records"][s].tolist(),
                                        "bad": r["link_bad"][s].tolist(),
                                        "resyncs": r["link_resyncs"][s].tolist(),
                                        "errors": r["link_errors"][s].tolist(),
                                        "rate_hz": r["link_rate_hz"][s].tolist(),
                                        "age_s": r["link_age_s"][s].tolist()})}

    def links_key(self, r) -> bytes:
        """What makes /pfma/links worth a message (counters and status; not the age)."""
        return (r["link_status"].tobytes() + r["link_records"].tobytes() + r["link_bad"].tobytes()
                + r["link_resyncs"].tobytes() + r["link_errors"].tobytes())

    def boards_key(self, r) -> bytes:
        return (r["board_status"].tobytes() + r["board_errors"].tobytes()
                + r["board_last_error_addr"].tobytes())


# ----------------------------------------------------------------------------------------
# counters


@dataclass
class RecorderCounters:
    """What the recorder saw; written to ``/pfma/recorder`` and the summary metadata."""

    frames_recorded: int = 0          #: inputs frames written (raw stream messages)
    first_frame: int = -1
    last_frame: int = -1
    recorder_missed: int = 0          #: publishes the recorder did not see (sequence jumps)
    service_skipped: int = 0          #: frame numbers the service itself skipped (its overruns)
    frame_gaps: int = 0               #: all missing frame numbers (= skipped + missed frames)
    republished: int = 0              #: publishes repeating the last frame number (e.g. STOPPED)
    sessions: int = 0                 #: service (re)attachments seen
    window_first_frame: int = -1      #: stats window [first, last) (frame numbers)
    window_last_frame: int = -1
    window_service_frames: int = 0    #: frames the service ran in the window (stats.frames)
    window_recorded: int = 0          #: frames recorded in the same window
    window_service_dropped: int = 0   #: stats.dropped_frames over the window
    messages_missed: int = 0          #: message-queue entries overwritten before being read
    messages_total: int = 0           #: MCAP messages written, all topics
    stats_snapshots: int = 0
    commands_recorded: int = 0
    wall_s: float = 0.0
    lossless: bool = True             #: recorder_missed == 0 and the window counts match
    topic_counts: str = "{}"          #: JSON {topic: messages}

    def as_dict(self) -> dict:
        return asdict(self)


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
    """

    def __init__(self, client: Client | None, out: str | Path | IO[bytes], *, rack=None,
                 epoch_offset_ns: int | None = None, json_every: int = 1,
                 flush_every_s: float = FLUSH_EVERY_S, chunk_size: int = CHUNK_SIZE,
                 compression: CompressionType = CompressionType.ZSTD,
                 wall: Callable[[], float] = time.monotonic, layout: Layout | None = None,
                 meta: dict[str, str] | None = None) -> None:
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
        self.w.start(profile=PROFILE, library=LIBRARY)
        self.t = _Topics(self.layout)
        self._ch: dict[str, int] = {}
        self._schema_raw = raw_schema(self.layout)
        self._raw_len = self._schema_raw["stored_bytes"]
        sid = self.w.register_schema(RAW_SCHEMA, RAW_SCHEMA_ENCODING,
                                     json.dumps(self._schema_raw).encode())
        self._ch[RAW_TOPIC] = self.w.register_channel(RAW_TOPIC, RAW_ENCODING, sid,
                                                      {"area": "inputs", "layout_hash": self.layout.hash_hex})
        for topic, schema in self.t.schemas().items():
            schema = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": topic, **schema}
            sid = self.w.register_schema("pfma" + topic.replace("/", ".")[5:], "jsonschema",
                                         json.dumps(schema).encode())
            self._ch[topic] = self.w.register_channel(topic, "json", sid, {})
        self._meta_extra = dict(meta or {})
        self._wrote_meta = False
        self.client: Client | None = None
        self._t0_wall = wall()
        self._last_flush = self._t0_wall
        self._last_counters = self._t0_wall
        self._ring = np.full(_RING, -1, dtype=np.int64)
        self._ring_i = 0
        self._win_acc = (0, 0, 0)
        self._win_new = False
        self._closed = False
        self._log_ns = self.offset_ns
        if client is not None:
            self.attach(client)

    # --- session management ---
    def attach(self, client: Client) -> None:
        """Start recording from a (new) client: a new session (service start or restart)."""
        if client.layout.hash != self.layout.hash:
            raise ValueError(f"recorder: buffer layout {client.layout.hash_hex} differs from the "
                             f"recording's {self.layout.hash_hex}")
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
        cnt = self.counters
        consecutive = self._last_seq < 0 or seq - self._last_seq == 2
        if self._last_seq >= 0 and seq - self._last_seq > 2:
            cnt.recorder_missed += (seq - self._last_seq) // 2 - 1
        self._last_seq = seq
        head = {"t_s": t_s, "frame": frame}
        t_ns = _ns(t_s, self.offset_ns)
        self._log_ns = t_ns
        if frame == self._last_frame:  # the same frame published again (stop: STOPPED state)
            cnt.republished += 1
            self._put("/pfma/status", t_ns, _dumps(self.t.status(r, head)))
            return 0
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
        self._put(RAW_TOPIC, t_ns, self._raw_bytes(snap.record))
        self._put("/pfma/status", t_ns, _dumps(self.t.status(r, head)))
        self._json_n += 1
        if self._json_n % self.json_every:
            return 1
        lt = self._last_t
        for topic, tf, fn in (("/pfma/joints", "t_rtd_s", self.t.joints),
                              ("/pfma/adc", "t_adc_s", self.t.adc),
                              ("/pfma/dac", "t_dac_s", self.t.dac),
                              ("/pfma/ft", "ft_t_s", self.t.ft),
                              ("/pfma/pio", "t_pio_s", self.t.pio)):
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
        return 1

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
        k, frames, dropped = int(d["frame"]), int(d["frames"]), int(d["dropped_frames"])
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
        cnt = self.counters
        self._win_acc = (cnt.window_service_frames, cnt.window_recorded, cnt.window_service_dropped)
        self._win_new = True
        self._stats_first = None
        self._session_first = -1
        self._ring[:] = -1

    def _messages(self) -> None:
        c = self.client
        for q in ("service", "controller"):
            cur = self._msg_cursor[q]
            try:
                head = c.buffer.queue(q + "_messages").head_seq
            except Exception:  # noqa: BLE001
                continue
            if head == cur:
                continue
            if head < cur:  # a new buffer (service restart): start over
                cur = 0
            got = c.messages(cur, q)
            if got and got[0].seq > cur + 1:
                self.counters.messages_missed += got[0].seq - cur - 1
            for m in got:
                self._put("/pfma/messages", _ns(m.t_s, self.offset_ns), _dumps({
                    "queue": q, "seq": m.seq, "t_s": m.t_s, "severity": m.severity.name,
                    "code": m.code, "source": m.source, "text": m.text}))
            self._msg_cursor[q] = got[-1].seq if got else head

    def _finish_counters(self) -> RecorderCounters:
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
            cnt = self.write_counters()
            self.w.flush()
            self.w.add_metadata("pfma.recorder.summary", {k: str(v) for k, v in cnt.as_dict().items()})
            self.w.finish()
        finally:
            self._closed = True
            if self._own_file:
                self._f.close()
            else:
                self._f.flush()
        return self.counters


#: idle polls of the capture thread between two looks whether its frame ring was replaced
#: (one ``stat``; 50 polls of 0.2 ms: about every 10 ms while no frame comes)
RING_CHECK_POLLS = 50


@dataclass(frozen=True)
class RingSwitch:
    """Queued by :class:`InputsCapture` between the last frame of a replaced ring and the
    first of the new one; :meth:`InputsCapture.drain` stops there and sets ``replaced_note``."""

    note: str


class InputsCapture:
    """Copies every inputs publish into a queue from its own thread, so the recorder's
    slow moments (closing and compressing a chunk, flushing the file, encoding JSON; 2-4
    ms measured) no longer make it miss a 3.125 ms frame. With the service's frame ring
    (``bit3.ring``) it reads the ring instead and may itself be descheduled for up
    to n_slots - 1 frames without a loss. The writing thread empties the
    queue with :meth:`drain`. Run the process with a short GIL switch interval
    (``sys.setswitchinterval(0.0005)``) so this thread gets in while the other one works.

    :param client: the recorder's read-only client (this thread is the only one that
        reads its inputs area)
    :param poll_s: sleep between polls when nothing new was published
    :param max_queue: snapshots held at most (about 2.6 s at 320 Hz); beyond it the newest
        are not queued, and the recorder counts them as missed

    A restarted service replaces the ring file (``bit3.ring``): the thread notices it
    (:meth:`check_ring`), takes what the old ring still holds, attaches the new ring and
    reads it from its first frame. The switch is a :class:`RingSwitch` in the queue:
    :meth:`drain` stops there and sets :attr:`replaced_note`, so the recorder can start
    the new session (``Recorder.attach`` with the new service's client) before the new
    ring's frames.
    """

    def __init__(self, client: Client, poll_s: float = 0.0002, max_queue: int = 8192,
                 ring=None) -> None:
        self.client = client
        self.poll_s = poll_s
        self.max_queue = max_queue
        #: an attached ``bit3.ring.FrameRing`` of the same layout: frames are taken
        #: from it (up to n_slots - 1 behind) instead of from the single inputs area;
        #: the capture owns it (``stop`` closes it)
        self.ring = ring
        self._inputs_dtype = client.layout.area("inputs").body_dtype
        self.ring_lost = 0  #: frames overwritten in the ring before this thread read them
        self._ring_k: int | None = None  # next ring frame to take
        self.ring_reattached = 0  #: replaced rings this capture moved on from
        #: set by :meth:`drain` when it reached a ring switch (the caller clears it)
        self.replaced_note: str | None = None
        self.queue: deque = deque()
        self.error: BaseException | None = None  #: what stopped the thread (e.g. SeqLockTimeout)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pfma-record-capture", daemon=True)

    def start(self) -> "InputsCapture":
        self._thread.start()
        return self

    def _run(self) -> None:
        c, q, sleep, stop = self.client, self.queue, time.sleep, self._stop
        try:
            if self.ring is not None:
                self._run_ring()
                return
            while not stop.is_set():
                if c.changed("inputs"):
                    snap = c.read_inputs()
                    if snap.seq and len(q) < self.max_queue:
                        q.append(snap.copy())
                else:
                    sleep(self.poll_s)
        except BaseException as err:  # noqa: BLE001 - handed to the writing thread
            self.error = err

    def _run_ring(self) -> None:
        self._ring_k = self.ring.count()  # frames already in the ring are history
        idle = 0
        while not self._stop.is_set():
            if self.take_from_ring():
                idle = 0
                continue
            idle += 1
            if idle % RING_CHECK_POLLS == 0 and self.check_ring():
                continue
            time.sleep(self.poll_s)

    def check_ring(self) -> bool:
        """If the ring's file was replaced (the service restarted), take what the old ring
        still holds, attach the new ring, queue a :class:`RingSwitch` and read the new ring
        from its first frame; returns True when it switched. A ring that was removed, or
        whose replacement is not there yet or has another layout, is kept: the recorder's
        own checks on the buffer decide what happens then."""
        from bit3.ring import FrameRing, RingError
        old = self.ring
        if old is None or not old.replaced():
            return False
        try:
            new = FrameRing.attach(old.buffer_name, old.layout_hash)
        except RingError:
            return False
        self.take_from_ring()  # the old ring's memory stays valid: finish it
        self.queue.append(RingSwitch(
            f"frame ring {old.path} was replaced (service restarted?): the old ring ended after "
            f"{old.count()} frames; reading the new ring from its first frame"))
        self.ring, self._ring_k = new, 0
        self.ring_reattached += 1
        old.close()
        return True

    def take_from_ring(self) -> int:
        """Queue every whole frame the ring holds beyond the last one taken; returns how
        many were queued (the thread calls it; tests call it in simulated time)."""
        ring, q = self.ring, self.queue
        if self._ring_k is None:
            self._ring_k = ring.count()
        layout, dtype = self.client.layout, self._inputs_dtype
        k, n, taken = self._ring_k, ring.count(), 0
        if n - k >= ring.n_slots:  # fell a whole ring behind: those frames are gone
            self.ring_lost += n - k - (ring.n_slots - 1)
            k = n - (ring.n_slots - 1)
        while k < n:
            data = ring.read(k)
            k += 1
            if data is None or len(q) >= self.max_queue:
                self.ring_lost += 1  # the gap in the sequence numbers counts it as missed
                continue
            # seq: even and +2 per frame, as the buffer's own counter
            q.append(Snapshot(np.ndarray((), dtype, buffer=data), "inputs", layout, 2 * k))
            taken += 1
        self._ring_k = k
        return taken

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self) -> None:
        """End the thread and close the ring (queued snapshots stay for :meth:`drain`)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2.0)
        if self.ring is not None and not self._thread.is_alive():
            self.ring.close()

    def drain(self, rec: "Recorder") -> int:
        """Write every queued snapshot up to a ring switch (then :attr:`replaced_note` is
        set and the rest stays queued for the next call); returns frames written."""
        n = 0
        q = self.queue
        while q:
            snap = q.popleft()
            if type(snap) is RingSwitch:  # the frames after it are the new service's
                self.replaced_note = snap.note
                return n
            n += rec.feed_inputs(snap)
        return n


def epoch_offset_ns_default() -> int:
    return epoch_offset_ns()


# ----------------------------------------------------------------------------------------
# reading back and recovery


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
    return rep


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


# ----------------------------------------------------------------------------------------
# start-up robustness: wait for a live service


def service_status(name: str, layout: Layout | None = None) -> tuple[Client | None, str]:
    """``(client, "")`` when a live service publishes on buffer ``name``, else
    ``(None, why)``. Layout mismatches raise (they do not go away by waiting).

    Live means: the buffer exists, its layout matches, the inputs owner's process is
    running and the service state is not STOPPED.
    """
    from bit3.buffer import Bit3Error, LayoutMismatchError
    try:
        c = Client.attach(name, layout=layout)
    except LayoutMismatchError:
        raise
    except Bit3Error as err:
        return None, f"no buffer ({err})" if "no Bit3 buffer" not in str(err) else "no buffer yet"
    except (OSError, ValueError) as err:
        return None, f"buffer not readable yet ({err})"
    try:
        owner = c.buffer.owner("inputs")
        if owner.pid <= 0:
            why = "buffer exists but no service owns it (not started yet, or stopped)"
        elif not owner.alive:
            why = f"buffer exists but its service (pid {owner.pid}) is not running"
        elif c.service_state == ServiceState.STOPPED:
            why = f"service pid {owner.pid} has stopped"
        else:
            return c, ""
    except Exception as err:  # noqa: BLE001 - half-initialised buffer
        why = f"buffer not ready ({err})"
    c.close()
    return None, why


def wait_for_service(name: str, layout: Layout | None = None, *,
                     timeout_s: float | None = None, poll_s: float = 0.2,
                     say: Callable[[str], None] = print,
                     stop: Callable[[], bool] = lambda: False,
                     remind_every_s: float = 10.0) -> Client | None:
    """Attach to a live service on ``/dev/shm/NAME``, waiting (with a clear message, then a
    reminder every ``remind_every_s``) while there is none. Returns None on time-out or
    when ``stop()`` turns true; raises LayoutMismatchError for a buffer of another layout."""
    t0 = time.monotonic()
    said = ""
    last_say = t0
    while True:
        c, why = service_status(name, layout)
        if c is not None:
            if said:
                say(f"service on /dev/shm/{name} is up (after {time.monotonic() - t0:.1f} s)")
            return c
        now = time.monotonic()
        if why != said:
            say(f"waiting for service on /dev/shm/{name} ... ({why}; Ctrl-C gives up)")
            said, last_say = why, now
        elif now - last_say >= remind_every_s:
            say(f"still waiting for service on /dev/shm/{name} ({now - t0:.0f} s; {why})")
            last_say = now
        if stop() or (timeout_s is not None and now - t0 >= timeout_s):
            return None
        time.sleep(poll_s)


def buffer_replaced(client: Client) -> bool:
    """The name now refers to another segment than the one ``client`` maps (the service
    was restarted and created a new buffer), or the name is gone."""
    try:
        from bit3.buffer import Bit3Buffer
        b = Bit3Buffer.attach(client.buffer.name, readonly=True, layout=client.layout)
    except Exception:  # noqa: BLE001 - gone or different: either way not ours any more
        return True
    try:
        return b.header().created_ns != client.header().created_ns
    finally:
        b.close()
