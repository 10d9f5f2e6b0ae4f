"""The recorder process (``pfma record FILE.mcap``) assembled in one place: :class:`RecorderStack`.

Built (and torn down in the reverse order, on every exit path, by one
``contextlib.ExitStack``): the signal handlers (Ctrl-C, SIGTERM end the recording cleanly;
restored at the end), the world model (``--wm``, waited for like the service), then one
session per service that comes up on the buffer: its client, its frame ring's capture
thread (:class:`tools.recording.InputsCapture`), the :class:`tools.recording.Recorder`
(made at the first session, attached again at each further one). At the end the recorder's
file is closed with its summary and the counters printed (stdout); a write error or no
service at all is said (logging) with exit status 1.

Through a bridge (``zenoh://HOST:PORT/NAME``) the same stack runs
:func:`tools.recording.remote.record_remote` instead of the local sessions.

Runtime messages go to ``logging`` (the process's root configures it once,
:func:`pfma.log.configure`): what the recorder is doing at INFO (not said when ``quiet``),
why it ends without a recording at ERROR.
"""

from __future__ import annotations

import contextlib
import gc
import json
import logging
import signal
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from pfma.errors import os_error_text

log = logging.getLogger(__name__)

#: no new frame for this long: look whether the service is still there
STALE_S = 1.0
#: sleep between polls when nothing changed, without a frame ring (a 1 kHz frame is 1 ms)
POLL_SLEEP_S = 0.0004
#: with a frame ring the inputs cannot be missed (the capture thread polls the ring every
#: ``RING_POLL_S``); this loop then only looks for commands, stats and messages: every 2 ms
#: catches each command publish of a 320 Hz controller (3.125 ms apart) unless two land
#: within one poll, and costs ~500 wake-ups a second instead of ~2500
COMMANDS_POLL_S = 0.002


@dataclass
class RecorderConfig:
    """What ``pfma record FILE.mcap``'s options say (tools/cli/record.py), checked there."""

    path: str
    buffer: str = "pfma"
    rack: str = "fake"
    duration_s: float | None = None
    json_every: int = 1
    flush_s: float = 0.25
    wait_s: float | None = None
    quiet: bool = False
    wm_name: str | None = None
    #: the ``--var`` patterns (tools.recording.wm.parse_var)
    patterns: list = field(default_factory=list)
    #: ``--realtime``/``--no-realtime`` for the capture thread (None: where permitted)
    realtime: bool | None = None


def _print(line: str) -> None:
    print(line, flush=True)


def ring_of(buffer: str, client):
    """The service's frame ring of this buffer and layout, or None (then the inputs area
    itself is polled, and a reader descheduled for a frame period misses that frame)."""
    from bit3.ring import FrameRing, RingError
    try:
        return FrameRing.attach(buffer, client.layout.hash)
    except RingError:
        return None


class RecorderStack:
    """The recorder process; ``RecorderStack(config).run()`` records and tears down (also
    when left as a context manager).

    :param out: where the summary lines go (default: stdout, flushed)
    """

    def __init__(self, config: RecorderConfig, *, out: Callable[[str], None] = _print) -> None:
        self.config = config
        self.out = out
        self.stopped = False  #: Ctrl-C or SIGTERM came
        self.err_code = 0
        self.rec: Any = None
        self.wm: Any = None
        self.client: Any = None
        self.capture: Any = None
        self.layout: Any = None
        self.rack: Any = None
        self.write_error: OSError | None = None
        self.idle_since = 0.0
        self.warned = False
        self._recording = False
        self._said_realtime = False
        self._t_end: float | None = None
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> RecorderStack:
        return self

    def __exit__(self, *exc) -> bool:
        return bool(self._stack.__exit__(*exc))

    def say(self, text: str) -> None:
        """What the recorder is doing (INFO), unless ``quiet``."""
        if not self.config.quiet:
            log.info("%s", text)

    def done(self) -> bool:
        """The recording ends: Ctrl-C, SIGTERM, or ``duration_s`` over."""
        return self.stopped or (self._t_end is not None and time.monotonic() >= self._t_end)

    def _remaining(self, bounded_by_wait: bool = False) -> float | None:
        """Seconds left of ``duration_s`` (None: no end), also bounded by ``wait_s`` when asked."""
        remaining = None if self._t_end is None else max(0.0, self._t_end - time.monotonic())
        wait_s = self.config.wait_s
        if bounded_by_wait and wait_s is not None:
            remaining = wait_s if remaining is None else min(wait_s, remaining)
        return remaining

    def _handle_signals(self) -> None:
        """Ctrl-C and SIGTERM set :attr:`stopped`; the old handlers come back at the end."""
        def handler(signum, _frame):
            self.stopped = True
        old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
        for s, h in old.items():
            self._stack.callback(signal.signal, s, h)
        self._t_end = None if self.config.duration_s is None else time.monotonic() + self.config.duration_s

    # -- running --------------------------------------------------------------------

    def run(self) -> int:
        """Record until the end (see the module docstring); the exit status."""
        from tools.attach import remote_target
        # the capture thread must get the GIL within a fraction of a frame while this one
        # compresses or encodes (the default switch interval is 5 ms, longer than a frame)
        sys.setswitchinterval(0.0005)
        if remote_target(self.config.buffer) is not None:
            return self._run_remote()
        from bit3.layout import build_layout, default_layout
        from pfma.rack import load_rack
        cfg = self.config
        self.rack = load_rack(cfg.rack)
        self.layout = default_layout() if cfg.rack in ("fake", "default") else build_layout(self.rack)
        with self._stack:
            self._stack.callback(self._finish)  # after the signal handlers are restored
            self._handle_signals()
            if cfg.wm_name is not None and not self._open_wm():
                return self.err_code
            self._recording = True
            try:
                self._sessions()
            except OSError as err:  # writing: the disk full, a file-size limit, the file system gone
                if self.rec is None:
                    self.err_code = 1  # not a recording yet (main() names the file): not "no service came up"
                    raise
                self.write_error = err
        return self.err_code

    def _run_remote(self) -> int:
        """``--buffer zenoh://HOST:PORT/NAME``: the recording through a bridge
        (tools/recording/remote.py)."""
        from tools.recording.remote import record_remote
        cfg = self.config
        with self._stack:
            self._handle_signals()
            return record_remote(cfg.path, cfg.buffer, rack_arg=cfg.rack, json_every=cfg.json_every,
                                 flush_s=cfg.flush_s, wait_s=cfg.wait_s, say=self.say, done=self.done,
                                 summary=summary_line)

    def _open_wm(self) -> bool:
        """The world model to sample, waited for like the service; False (and the exit status
        set) when there is none in time or a pattern matches nothing (a usage mistake: 2)."""
        from tools.recording.wm import WmUsageError, select, wait_for_wm
        cfg, name = self.config, self.config.wm_name or ""
        remaining = self._remaining(bounded_by_wait=True)
        try:
            wm, why = wait_for_wm(name, timeout_s=remaining, say=self.say, stop=self.done)
        except WmUsageError as err:
            return self._no_recording(2, f"{err}; nothing recorded")
        if wm is None:
            limit = f" within {remaining:g} s" if remaining is not None else ""
            return self._no_recording(1, f"no running world model /dev/shm/{cfg.wm_name}{limit} ({why}); "
                                         f"nothing recorded")
        try:
            select(wm.specs, cfg.patterns, wm_name=name)
        except WmUsageError as err:
            wm.close()
            return self._no_recording(2, f"{err}; nothing recorded")
        self.wm = wm
        return True

    def _no_recording(self, code: int, text: str) -> bool:
        log.error("%s", text)
        self.err_code = code
        return False

    def _wait(self, remaining: float | None):
        """(the service's client or None, True when its layout is another recording's)."""
        from bit3.buffer import LayoutMismatchError
        from tools.attach import wait_for_service
        try:
            return wait_for_service(self.config.buffer, self.layout, timeout_s=remaining, say=self.say,
                                    stop=self.done), False
        except LayoutMismatchError as err:
            log.error("%s; this recording ends here (a different rack or layout is a different "
                      "recording)", err)
            return None, True

    def _sessions(self) -> None:
        """One session per service that comes up, until the end."""
        cfg = self.config
        while not self.done():
            client, mismatch = self._wait(self._remaining(bounded_by_wait=self.rec is None))
            if mismatch:
                self.err_code = 1
                return
            if client is None:
                if self.rec is None and not self.stopped and cfg.wait_s is not None:
                    log.error("no service on /dev/shm/%s within %s s; nothing recorded", cfg.buffer,
                              f"{cfg.wait_s:g}")
                    self.err_code = 1
                return
            self._begin(client)
            self._session(client)

    def _begin(self, client) -> None:
        """The recorder at the first session (with the world model's sampler); attached
        again at each further one."""
        from tools.recording import Recorder
        cfg = self.config
        if self.rec is not None:
            self.rec.attach(client)
            self.say(f"service back: recording continues as session {self.rec.counters.sessions}")
            return
        sampler = None
        if self.wm is not None:
            from tools.recording.wm import WmSampler, select
            rate, source = frame_rate_hz(client)
            chosen = select(self.wm.specs, cfg.patterns, wm_name=cfg.wm_name or "", frame_rate_hz=rate)
            sampler = WmSampler(self.wm, chosen, patterns=cfg.patterns, frame_rate_hz=rate, say=self.say)
            self.wm = None  # the sampler (and then the recorder) owns it
            self.say(f"world model /dev/shm/{cfg.wm_name}: {len(chosen)} variables in "
                     f"{len(sampler.topics())} topics (every-frame samples capped at {rate:g} Hz, "
                     f"from {source})")
        self.rec = Recorder(client, cfg.path, rack=self.rack, json_every=cfg.json_every,
                            flush_every_s=cfg.flush_s, meta={"command": " ".join(sys.argv)}, wm=sampler)
        self.say(f"recording /dev/shm/{cfg.buffer} to {cfg.path} (Ctrl-C ends it)")

    def _session(self, client) -> None:
        """Record one service's frames until it stops (or the recording ends)."""
        self.client = client
        gc.collect()
        gc.freeze()  # long-lived objects out of the collector's way: short GC pauses
        self.idle_since = time.monotonic()
        self.warned = False
        self.capture = self._new_capture(client)
        while not self.done() and self._step():
            pass
        self.capture.stop()
        self.capture.drain(self.rec)
        self.rec.messages_captured = False  # the thread has ended: the last look is ours
        self.rec.poll(inputs=False)
        self._say_notes()
        self.rec.client = None
        self.client.close()

    def _new_capture(self, client):
        """The capture thread: every frame (from the frame ring where there is one) and every
        change of the message queues, into a queue this thread writes from."""
        from tools.recording import InputsCapture
        self.rec.messages_captured = True
        cap = InputsCapture(client, ring=ring_of(self.config.buffer, client), messages=True,
                            realtime=self.config.realtime).start()
        if not self._said_realtime:  # once a recording (a restarted capture says nothing new)
            self._said_realtime = True
            for line in cap.realtime_lines:
                self.say(line)
        return cap

    def _say_notes(self) -> None:
        """Say what the recorder noticed going wrong (lost message entries), as it happens."""
        notes = self.rec.notes
        while notes:
            self.say(notes.pop(0))

    def _step(self) -> bool:
        """One pass of a session: the frames captured, the commands, stats and messages; False
        when the session ends (its service stopped or was replaced by none)."""
        from bit3.buffer import SeqLockTimeout
        rec, capture = self.rec, self.capture
        try:
            n = capture.drain(rec)
            rec.poll(inputs=False)
        except SeqLockTimeout as e:  # the service died mid-write
            self.say(f"{e}")
            n = 0
        self._say_notes()
        if capture.replaced_note is not None:
            return self._ring_replaced()
        if capture.error is not None:
            self._restart_capture()
        now = time.monotonic()
        if n:
            self.idle_since = now
            self.warned = False
            return True
        if now - self.idle_since > STALE_S and not self._still_there(now):
            return False
        time.sleep(POLL_SLEEP_S if self.capture.ring is None else COMMANDS_POLL_S)
        return True

    def _ring_replaced(self) -> bool:
        """A restarted service made a new frame ring and the capture moved to it: the new
        service's frames follow in the queue; start their session first."""
        from tools.attach import buffer_replaced
        rec, capture, client = self.rec, self.capture, self.client
        self.say(capture.replaced_note)
        capture.replaced_note = None
        if not buffer_replaced(client) and client.buffer.owner("inputs").alive:
            capture.messages_from(client)
            return True  # this session's client already is the new service's (it made
            # its buffer before its ring, and we attached in between)
        rec.flush()
        new, mismatch = self._wait(self._remaining())
        if mismatch:
            self.err_code = 1
            self.stopped = True
            return False
        if new is None:
            return False
        rec.client = None
        client.close()
        self.client = capture.client = new
        rec.attach(new)
        capture.messages_from(new)
        self.say(f"service restarted: recording continues as session {rec.counters.sessions}")
        self.idle_since = time.monotonic()
        return True

    def _restart_capture(self) -> None:
        """The capture thread ended: a torn read is said and the thread started again; any
        other error ends the recording (raised)."""
        from bit3.buffer import SeqLockTimeout
        error = self.capture.error
        if not isinstance(error, SeqLockTimeout):
            raise error
        self.say(f"{error}")
        self.capture.stop()  # the thread has ended; this closes its ring
        self.capture.drain(self.rec)
        self.capture = self._new_capture(self.client)

    def _still_there(self, now: float) -> bool:
        """No frame for STALE_S: False (said) when the service is gone; said once when it is
        alive but silent."""
        from bit3.layout import ServiceState
        from tools.attach import buffer_replaced
        client = self.client
        gone = buffer_replaced(client) or not client.buffer.owner("inputs").alive \
            or client.service_state == ServiceState.STOPPED
        if gone:
            self.say(f"service on /dev/shm/{self.config.buffer} stopped after frame "
                     f"{self.rec.counters.last_frame}; waiting for it to come back")
            self.rec.flush()
            return False
        if not self.warned:
            self.say(f"service pid {client.buffer.owner('inputs').pid} is alive but has "
                     f"published no frame for {now - self.idle_since:.1f} s")
            self.warned = True
        return True

    # -- tearing down ---------------------------------------------------------------

    def _finish(self) -> None:
        """The recording closed, its summary printed; a write error or no service said."""
        if not self._recording:
            return
        gc.unfreeze()
        if self.wm is not None:  # never handed to a recorder
            self.wm.close()
        rec, path = self.rec, self.config.path
        if rec is None:
            if not self.err_code:
                log.error("no service came up on /dev/shm/%s; nothing recorded", self.config.buffer)
                self.err_code = 1
            return
        try:
            c = rec.close()
        except OSError as err:
            self.write_error = self.write_error or err
            c = None
        if c is not None:
            self.out(summary_line(path, c))
            if rec.wm is not None:
                self.out(wm_line(rec.wm))
        if self.write_error is not None:
            log.error("cannot write %s: %s; the recording ends here and the file keeps what was written "
                      "before: `pfma record recover %s` makes a whole file of it",
                      path, os_error_text(self.write_error), path)
            self.err_code = 1


def record(config: RecorderConfig) -> int:
    """Run the recorder process to its end; its exit status."""
    return RecorderStack(config).run()


def frame_rate_hz(client) -> tuple[float, str]:
    """The service's frame rate (the cap of every-frame world-model samples) and where it
    came from: its statistics area's nominal period, else the schedule's default."""
    try:
        period = float(client.read_stats().as_dict().get("period_s") or 0.0)
    except Exception:  # noqa: BLE001 - no statistics published yet
        period = 0.0
    if period > 0:
        return 1.0 / period, "the service's statistics (period_s)"
    from ioservice.schedule import Schedule
    return Schedule().frame_rate_hz, "the schedule's default (no statistics published yet)"


def wm_line(sampler) -> str:
    """The world model's counters at the end of a recording, one line."""
    c = sampler.counters
    return (f"pfma record: world model {sampler.name!r}: {c.samples} samples of "
            f"{len(sampler.variables)} variables on {len(c.messages)} topics; controller frames not "
            f"seen {c.frames_unseen}, went away {c.went_away}, sessions {c.sessions}")


def summary_line(path: str, c) -> str:
    """The recorder's counters at the end of a recording, one line."""
    tc = json.loads(c.topic_counts)
    return (f"pfma record: {path}: {c.frames_recorded} frames (frames {c.first_frame}..{c.last_frame}), "
            f"{c.messages_total} messages in {len(tc)} topics, {c.wall_s:.1f} s; recorder missed "
            f"{c.recorder_missed}, service skipped {c.service_skipped} (stats window: service ran "
            f"{c.window_service_frames}, recorded {c.window_recorded}, service dropped "
            f"{c.window_service_dropped}); messages missed {c.messages_missed}; sessions "
            f"{c.sessions}; {'LOSSLESS' if c.lossless else 'NOT LOSSLESS'}")
