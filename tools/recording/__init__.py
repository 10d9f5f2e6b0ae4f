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

Modules: :mod:`.schema` (constants, time stamps, the raw stream's schema and decoding),
:mod:`.topics` (the JSON channels' schemas and encoders, :class:`RecorderCounters`),
:mod:`.writer` (:class:`Recorder`), :mod:`.capture` (:class:`InputsCapture`, the
capture thread), :mod:`.reader` (reading a recording back), :mod:`.recover` (rewriting
a cut file), :mod:`.spool` (the MCAP writer's chunk indexes kept on disk until the
summary, so the recorder's memory does not grow with the recording). Waiting for a live
service and noticing its restart is :mod:`tools.attach`, shared by every tool.
"""

from tools.recording.capture import RING_CHECK_POLLS, InputsCapture, RingSwitch
from tools.recording.reader import iter_records_tolerant, read_frames, read_metadata
from tools.recording.recover import RecoverReport, recover
from tools.recording.schema import (
    CHUNK_SIZE, COUNTERS_EVERY_S, FLUSH_EVERY_S, LIBRARY, PROFILE, RAW_ENCODING, RAW_SCHEMA, RAW_SCHEMA_ENCODING,
    RAW_TOPIC, decode_raw, epoch_offset_ns, raw_dtype, raw_schema,
)
from tools.recording.topics import RecorderCounters
from tools.recording.writer import Recorder

__all__ = [
    "CHUNK_SIZE", "COUNTERS_EVERY_S", "FLUSH_EVERY_S", "LIBRARY", "PROFILE", "RAW_ENCODING", "RAW_SCHEMA",
    "RAW_SCHEMA_ENCODING", "RAW_TOPIC", "RING_CHECK_POLLS", "InputsCapture", "Recorder", "RecorderCounters",
    "RecoverReport", "RingSwitch", "decode_raw", "epoch_offset_ns", "iter_records_tolerant", "raw_dtype",
    "raw_schema", "read_frames", "read_metadata", "recover",
]
