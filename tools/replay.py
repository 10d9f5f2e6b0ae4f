"""Playing a recording back: re-published into a Bit3 buffer, or through the fakes.

:func:`republish` claims the service role of a buffer the caller created and publishes
the recorded inputs frames (``/pfma/inputs_raw``, byte for byte), the recorded
statistics and messages at the recorded pace (or as fast as possible), so tools run
against a recording as against a live service.

:func:`replay_through_fakes` (regression) builds the simulated rack (FakeWorld) on a
private buffer, runs a real IoService on it in simulated time with the same frame
numbers as the recording, and before each frame sets the fake boards' physical inputs
from the recorded frame: resolver angles (RTD boards), ADC input volts (ADC boards), the
user I/F box bits (PIO). Then it compares what the service publishes with what was
recorded, per channel (RTD counts, ADC counts, PIO bits; exact). The F/T sensor, the CRL
hand controller and the DAC (which follows the controller's commands) are not driven, so
they are not compared. Frames missing from the recording are not compared
(:func:`missing_frames`): one the service skipped is skipped here too (the next frame runs
its tasks, as the service did); one it may have run is run without its inputs. The verb
is ``pfma replay`` (:mod:`tools.cli.replay`).
"""

from __future__ import annotations

import time
import uuid
from collections import defaultdict
from dataclasses import dataclass, field

import numpy as np

from tools.recording.reader import read_frames, read_metadata
from tools.recording.schema import RAW_TOPIC

# ----------------------------------------------------------------------------------------
# re-publish


def republish(path: str, buffer, *, speed: float = 1.0, fast: bool = False,
              sleep=time.sleep, now=time.monotonic, stop=lambda: False) -> int:
    """Publish a recording's frames into ``buffer`` (a Bit3Buffer that the caller created);
    returns the frames published. The service role is claimed here."""
    from bit3.layout import ServiceState
    buffer.claim("service", "pfma-replay")
    w_in = buffer.writer("inputs")
    w_st = buffer.writer("stats")
    q = buffer.queue("service_messages")
    st_names = set(w_st.record.dtype.names)
    n = 0
    t_wall0 = t_rec0 = None
    for topic, t_ns, val in read_frames(path, (RAW_TOPIC, "/pfma/stats", "/pfma/messages")):
        if stop():
            break
        if not fast:
            if t_wall0 is None:
                t_wall0, t_rec0 = now(), t_ns
            due = t_wall0 + (t_ns - t_rec0) / 1e9 / max(speed, 1e-6)
            dt = due - now()
            if dt > 0:
                sleep(dt)
        if topic == RAW_TOPIC:
            raw = val.tobytes()
            w_in.raw[:len(raw)] = raw
            w_in.publish()
            try:
                st = ServiceState(int(val["service_state"]))
            except ValueError:
                st = ServiceState.FAULT
            buffer.set_service_state(st)
            buffer.set_frame(int(val["frame"]), float(val["t_s"]))
            n += 1
        elif topic == "/pfma/stats":
            rec = w_st.record
            for k, v in val.items():
                if k in st_names and v is not None:
                    rec[k] = v
            w_st.publish()
        else:
            q.post(val.get("text", ""), severity=_sev(val.get("severity")), code=int(val.get("code", 0)),
                   source=int(val.get("source", 0)), t_s=float(val.get("t_s", 0.0)))
    return n


def _sev(name) -> int:
    from bit3.layout import Severity
    try:
        return int(Severity[name]) if isinstance(name, str) else int(name or 1)
    except (KeyError, ValueError):
        return int(Severity.INFO)


# ----------------------------------------------------------------------------------------
# through the fakes


@dataclass
class ChannelDiff:
    compared: int = 0
    mismatched: int = 0
    max_abs: float = 0.0
    first_frame: int = -1


@dataclass
class FakeReplayReport:
    frames_recorded: int = 0
    frames_compared: int = 0
    channels: dict[str, ChannelDiff] = field(default_factory=dict)
    #: frame numbers missing from the recording that the service skipped (its own dropped
    #: frames: ``service_skipped`` of ``pfma record info``): not run in the replay either
    skipped_frames: list[int] = field(default_factory=list)
    #: frame numbers missing from the recording that the service may have run (the recorder
    #: or the link lost them, or the file cannot tell): run without their inputs
    lost_frames: list[int] = field(default_factory=list)
    #: why ``lost_frames`` are missing, for :meth:`describe`
    lost_why: str = ""

    @property
    def mismatches(self) -> dict[str, ChannelDiff]:
        return {k: v for k, v in self.channels.items() if v.mismatched}

    def describe(self) -> str:
        bad = self.mismatches
        lines = [f"replay through the fakes: {self.frames_compared} of {self.frames_recorded} recorded "
                 f"frames compared, {len(self.channels)} channels, {len(bad)} with mismatches"]
        if self.skipped_frames:
            lines.append(f"  {len(self.skipped_frames)} frames the service skipped ({_ranges(self.skipped_frames)}): "
                         f"not compared, and skipped here too (as the service did)")
        if self.lost_frames:
            lines.append(f"  {len(self.lost_frames)} frames missing from the recording "
                         f"({_ranges(self.lost_frames)}; {self.lost_why}): not compared; run without "
                         f"their inputs")
        for name, d in sorted(bad.items()):
            lines.append(f"  MISMATCH {name}: {d.mismatched}/{d.compared} frames, max |diff| "
                         f"{d.max_abs:g}, first at frame {d.first_frame}")
        return "\n".join(lines)


def _ranges(frames: list[int], most: int = 4) -> str:
    """``101-102, 340`` for sorted frame numbers (the first ``most`` runs, then ``...``)."""
    runs: list[list[int]] = []
    for f in frames:
        if runs and f == runs[-1][1] + 1:
            runs[-1][1] = f
        else:
            runs.append([f, f])
    text = [f"{a}" if a == b else f"{a}-{b}" for a, b in runs[:most]]
    return ", ".join(text) + (", ..." if len(runs) > most else "")


def missing_frames(order: list[int], meta: dict[str, dict[str, str]]) -> tuple[list[int], list[int], str]:
    """The frame numbers missing between a recording's frames ``order`` (sorted), split into
    (skipped by the service, lost or not known which, why the second are missing), from
    what the recording says of its gaps (``pfma record info``): a remote recording's
    ``pfma.link`` lists the frames the link lost (any other gap is the service's); a local
    one's ``pfma.recorder.summary`` counts the publishes the recorder missed: none, and
    every gap is a frame the service skipped (its sequence numbers were consecutive across
    the gap); no skipped frame, and every gap is the recorder's. A file without either (a
    recovered one) or with both kinds cannot say which gap is which."""
    gaps = [f for a, b in zip(order, order[1:]) for f in range(a + 1, b)]
    if not gaps:
        return [], [], ""
    link = meta.get("pfma.link")
    if link is not None:
        import json
        lost_ranges = json.loads(link.get("lost_ranges", "[]"))
        lost = {f for f in gaps if any(a <= f <= b for a, b in lost_ranges)}
        return [f for f in gaps if f not in lost], sorted(lost), "the link lost them"
    summ = meta.get("pfma.recorder.summary")
    if summ is not None:
        if int(summ.get("recorder_missed", -1)) == 0:
            return gaps, [], ""
        if int(summ.get("service_skipped", -1)) == 0:
            return [], gaps, "the recorder missed them"
    return [], gaps, "recorder missed or service skipped: the file cannot tell"


def _recorded_frames(path: str, max_frames: int | None) -> dict[int, np.ndarray]:
    """The recording's raw inputs frames by frame number (the first ``max_frames``)."""
    frames: dict[int, np.ndarray] = {}
    for _, _, rec in read_frames(path, (RAW_TOPIC,)):
        frames[int(rec["frame"])] = rec
        if max_frames is not None and len(frames) >= max_frames:
            break
    return frames


def _missed_before(order: list[int], skipped: set[int]) -> dict[int, int]:
    """Frame -> how many frames the service skipped just before it (a frame after frames
    the service skipped ran their tasks too: IoService.frame, its ``info.missed``)."""
    missed: dict[int, int] = {}
    for f in order:
        n = 0
        while f - n - 1 in skipped:
            n += 1
        if n:
            missed[f] = n
    return missed


class _ReplayChannels:
    """The recorded channels the replay drives into the fake boards (resolver counts, ADC
    volts, the user I/F box bits) and compares with what the service publishes."""

    def __init__(self, layout) -> None:
        chans = [c for c in layout.channels if c.area == "inputs" and not c.spare]
        self.rtd = [(c.name, c.slot, c.board, c.channel) for c in chans if c.kind == "rtd"]
        self.adc_boards: dict[str, list[tuple[int, int]]] = defaultdict(list)
        for c in chans:
            if c.kind == "adc":
                self.adc_boards[c.board].append((c.channel, c.slot))
        pio = [(c.name, c.slot) for c in chans if c.kind == "pio" and c.name.startswith("user_if_box")]
        #: (channel name, field, slot) compared, in report order
        self.compared = [(n, "rtd_counts", s) for n, s, *_ in self.rtd]
        self.compared += [(c.name, "adc_counts", c.slot) for c in chans if c.kind == "adc"]
        self.compared += [(n, "pio_port_bits", s) for n, s in pio]

    def drive(self, world, rec: np.ndarray) -> None:
        """Set the fake boards' physical inputs from recorded frame ``rec``."""
        for _, slot, board, ch in self.rtd:
            world.bus[board].set_counts(ch, int(rec["rtd_counts"][slot]))
        for board, pairs in self.adc_boards.items():
            fake = world.bus[board]
            v = np.array(fake.input_volts if hasattr(fake, "input_volts") else np.zeros(32), dtype=float)
            for ch, slot in pairs:
                v[ch] = float(rec["adc_volts"][slot])
            fake.set_inputs_volts(v)
        world.set_user_inputs(int(rec["pio_user_inputs"]))

    def compare(self, rep: FakeReplayReport, out: np.ndarray, rec: np.ndarray, frame: int) -> None:
        """Count the channels of published record ``out`` that differ from ``rec``."""
        rep.frames_compared += 1
        for name_, fld, slot in self.compared:
            a, b = float(out[fld][slot]), float(rec[fld][slot])
            d = rep.channels.setdefault(f"{name_}.{fld}", ChannelDiff())
            d.compared += 1
            if a != b:
                d.mismatched += 1
                d.max_abs = max(d.max_abs, abs(a - b))
                if d.first_frame < 0:
                    d.first_frame = frame


def _run_replay(rack, layout, buf, frames: dict[int, np.ndarray], rep: FakeReplayReport) -> None:
    """The real IoService on ``buf`` over the simulated rack, frame numbers as recorded,
    each recorded frame's inputs driven before it and compared after it."""
    from fakes.world import FakeWorld
    from ioservice.service import IoService
    from ioservice.ticking import TickingClock
    from pfma.clock import SimClock
    order = sorted(frames)
    first, last = order[0], order[-1]
    skipped = set(rep.skipped_frames)
    # the replay's loop drops nothing, so it is told of the frames the service skipped
    missed_before = _missed_before(order, skipped)
    clock = SimClock()
    world = FakeWorld(rack, clock=clock)
    tclock = TickingClock(clock)
    tclock.hooks.append(world.tick)
    svc = IoService(rack, world.bus, buf, tclock, schedule=None)
    tclock.hooks.append(svc.serial_tick)
    channels = _ReplayChannels(layout)
    body = svc.frame

    def frame_body(info) -> None:
        if info.index in skipped:  # the service did not run this frame: nor does the replay
            return
        if info.index in missed_before:
            info.missed = missed_before[info.index]
        rec = frames.get(info.index)
        if rec is not None:
            channels.drive(world, rec)
        body(info)
        if rec is not None and info.index >= first + 8:  # one major frame to settle
            channels.compare(rep, svc.inputs.record, rec, info.index)

    svc.loop.body = frame_body
    svc.loop.t0 = clock.now() - first * svc.schedule.period_s
    svc.loop.k = first
    svc.loop.run(frames=last - first + 1, freeze_gc=False)
    svc.stop()


def replay_through_fakes(path: str, *, rack=None, max_frames: int | None = None) -> FakeReplayReport:
    """Drive a simulated rack from a recording and compare the service's output (see module doc)."""
    from bit3.buffer import Bit3Buffer
    from bit3.layout import build_layout, default_layout
    from pfma.errors import ConfigError
    from pfma.rack import load_rack
    rack = rack or load_rack()
    layout = default_layout() if rack.source.endswith("rack_default.toml") else build_layout(rack)
    frames = _recorded_frames(path, max_frames)
    meta_all = read_metadata(path)
    meta = meta_all.get("pfma.layout", {})
    if meta.get("hash") and meta["hash"] != layout.hash_hex:
        raise ConfigError(f"the recording's layout {meta['hash']} is not this rack's "
                         f"{layout.hash_hex}; give --rack")
    rep = FakeReplayReport(frames_recorded=len(frames))
    if not frames:
        return rep
    rep.skipped_frames, rep.lost_frames, rep.lost_why = missing_frames(sorted(frames), meta_all)
    name = "pfma-replay-" + uuid.uuid4().hex[:8]
    buf = Bit3Buffer.create(name, layout)
    try:
        _run_replay(rack, layout, buf, frames, rep)
    finally:
        buf.close()
        Bit3Buffer.unlink(name)
    return rep
