"""The controller process, assembled in one place: :class:`ControllerStack`.

One process of the seven-layer controller is: a world model and a runtime
(:class:`controller.runtime.ControllerRuntime`, or one process's part of a distributed
controller, :class:`controller.distributed.DistributedProcess`), a link to the I/O service
(the Bit3 client, or the whole system simulator with ``sim``), a pacer that locks its minor
frames to the service's (:class:`LivePacer`), the real-time set-up, and a driver that steps it
(:class:`LocalDriver` or :class:`DistributedDriver`). :class:`ControllerStack` opens them in
that order on a :class:`contextlib.ExitStack` and closes them in reverse on every exit path:
first the outputs are left safe (a halted controller's hold released, the SAFE state; a
running one powered down in order, at most 2 s), then the collector is given back, the
runtime closed (its world model removed), the service's buffer let go.

``pfma controller`` (tools/cli/controller) parses its arguments into
:class:`ControllerOptions` and runs the frames; anything else that needs a controller
process in-process uses the same class.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import signal
import time
from dataclasses import dataclass, field
from typing import Any, Callable

from bit3 import futex

log = logging.getLogger(__name__)

#: the process's name in its messages (``pfma controller: ...``)
PROG = "pfma controller"
#: live seconds a process stopping waits for the layers to reach SHUT DOWN
STOP_S = 2.0


class LivePacer:
    """Paces a live controller to the service's frames, by the service's hot-loop rules.

    Where the machine has futexes (``bit3.futex``: Linux on the usual architectures) the
    pacer sleeps on the header's frame word and the service's publish wakes it: one wake-up
    a frame, at the publish. Elsewhere it polls, as follows.
    Absolute deadlines: the service publishes frame k + 1 at about ``t_s(k) + period``
    (``inputs.t_s`` is the service's frame time on the same CLOCK_MONOTONIC host clock), so
    the pacer sleeps to :data:`LEAD_S` before that, then polls ``client.changed("inputs")``
    every :data:`POLL_S` until the frame is there (at most :data:`GIVE_UP_PERIODS` periods
    past it: the runtime's stale-service check then reports a service that stopped). A
    controller that woke late steps at once on the newest frame; the runtime counts the
    frames in between as missed and catches their tasks up. Nothing is allocated per frame
    here (floats only). After start-up :meth:`freeze_gc` moves everything allocated so far
    out of the collector's reach and turns automatic collection off; young generations are
    collected in the slack before a frame (:data:`GC_EVERY_FRAMES`), never a full one.
    """

    #: wake this long before the service's next frame time, then poll (assumed: more than
    #: the host's usual sleep overshoot, less than the service's publish delay)
    LEAD_S = 0.3e-3
    POLL_S = 50e-6
    #: futex waits: how long past the expected publish one wait may last before the pacer
    #: looks again (assumed: longer than the service's usual publish delay, ~0.3 ms here)
    FUTEX_LATE_S = 1e-3
    GIVE_UP_PERIODS = 4
    GC_EVERY_FRAMES = 64
    GC_MIN_SLACK_S = 1.5e-3

    def __init__(self, client, period_s: float) -> None:
        self.client = client
        self.period_s = period_s
        self.t_next = -1.0  # expected time of the next service frame (-1: not known yet)
        self.frames = 0
        self.gave_up = 0  #: waits that ended without a new frame
        self.gc_frozen = False

    def wait(self) -> None:
        c, mono = self.client, time.monotonic
        if c.changed("inputs"):
            return  # already published (we are late): step on the newest frame now
        now = mono()
        t_next = self.t_next if self.t_next > 0 else now
        if now > t_next + self.GIVE_UP_PERIODS * self.period_s:
            # nothing published for longer than a give-up (the service stopped or stalls):
            # wait a whole give-up from now. Without this the deadline stays in the past and
            # the controller spun through frames on the same inputs (~50 % of a core, seen
            # after its service stopped)
            t_next = now
        slack = t_next - self.LEAD_S - now
        if self.gc_frozen and slack > self.GC_MIN_SLACK_S and self.frames % self.GC_EVERY_FRAMES == 0:
            gc.collect(1)  # young generations only, in the slack before the frame
            now = mono()
            slack = t_next - self.LEAD_S - now
        give_up = t_next + self.GIVE_UP_PERIODS * self.period_s
        if futex.AVAILABLE:
            self._futex_wait(t_next, give_up)
            return
        if slack > 0:
            time.sleep(slack)
        while not c.changed("inputs"):
            if mono() > give_up:
                self.gave_up += 1
                break
            time.sleep(self.POLL_S)

    def _futex_wait(self, t_next: float, give_up: float) -> None:
        """One wake-up at the service's publish (bit3.futex): no lead sleep, no polling. The
        first sleep lasts to FUTEX_LATE_S past the frame's expected time, later ones
        FUTEX_LATE_S each: a service that never wakes (an older version) is still looked at
        every millisecond."""
        c, mono = self.client, time.monotonic
        buf = c.buffer
        until = t_next + self.FUTEX_LATE_S
        while True:
            seen = buf.frame_word()
            if c.changed("inputs"):
                return
            now = mono()
            if now >= give_up:
                self.gave_up += 1
                return
            if until <= now:
                until = now + self.FUTEX_LATE_S
            buf.wait_frame(seen, min(until, give_up) - now)

    def stepped(self, t_frame_s: float) -> None:
        """The controller ran on the service frame of time ``t_frame_s``: the next is due a
        period later (absolute, so no drift accumulates)."""
        self.t_next = t_frame_s + self.period_s
        self.frames += 1

    def freeze_gc(self) -> None:
        gc.collect()
        gc.freeze()
        gc.disable()
        self.gc_frozen = True

    def release_gc(self) -> None:
        if self.gc_frozen:
            gc.enable()
            gc.unfreeze()
            self.gc_frozen = False


class OwnClockPacer(LivePacer):
    """The controller's own frame clock, live (``FrameConfig.clock`` "own", ``pfma controller
    --clock own``; the report's board-2 frame interrupt): each wait sleeps to the time the
    runtime's next minor frame is due (absolute: no drift), whatever the service does; a
    frame late by more than a period is the next one (the runtime counts the one missed).
    The collector handling is the live pacer's; a step on the inputs of the step before
    counts as a give-up (the service published nothing in a whole period: its silence is
    said as when locked)."""

    def __init__(self, client, rt) -> None:
        super().__init__(client, rt.frames.period_s)
        self.rt = rt
        self._last_t = -1.0

    def wait(self) -> None:
        due = self.rt.next_frame_due()
        if due is None:
            return  # the first frame: now (its time is the clock's frame 0)
        slack = due - time.monotonic()
        if self.gc_frozen and slack > self.GC_MIN_SLACK_S and self.frames % self.GC_EVERY_FRAMES == 0:
            gc.collect(1)  # young generations only, in the slack before the frame
            slack = due - time.monotonic()
        if slack > 0:
            time.sleep(slack)

    def stepped(self, t_frame_s: float) -> None:
        if t_frame_s == self._last_t:
            self.gave_up += 1
        self._last_t = t_frame_s
        self.frames += 1


class PollPacer(LivePacer):
    """Paces a process whose inputs come over a bridge (``zenoh://``): no futex, and the
    service's frame times are another host's clock, so it polls for a new inputs body (the
    collector handling is the live pacer's)."""

    POLL_S = 100e-6
    GIVE_UP_S = 0.05  #: one wait at most (16 frames): the runtime's stale checks see the rest

    def __init__(self, client) -> None:
        super().__init__(client, period_s=self.GIVE_UP_S)

    def wait(self) -> None:
        end = time.monotonic() + self.GIVE_UP_S
        while not self.client.changed("inputs"):
            if time.monotonic() > end:
                self.gave_up += 1
                return
            time.sleep(self.POLL_S)

    def stepped(self, t_frame_s: float) -> None:
        self.frames += 1


def realtime(flag: bool | None) -> None:
    """The live controller's real-time set-up (by default where permitted; ioservice.loop.
    realtime_start): the service pins itself to the last CPU (pfma serve), the controller
    takes the first, one priority below it. Said in the process's log."""
    from ioservice.loop import realtime_start
    for line in realtime_start(PROG, flag, 0, 49):
        text = line.removeprefix(f"{PROG}: ")
        (log.info if text.startswith("real-time: ") else log.warning)(text)


@dataclass(frozen=True)
class Distribution:
    """Which process of a distributed controller this is (controller.distributed)."""

    config: Any  #: controller.distributed.DistributedConfig
    process: str
    base: str  #: the world models' base name (each process's is BASE.PROCESS)


@dataclass(frozen=True)
class ControllerOptions:
    """What a controller process is made of (``pfma controller``'s options)."""

    profile: str = "layers"  #: rate profile (controller.frames.FrameConfig.profile)
    wm: str | None = "pfma_wm"  #: world-model shared-memory name (None: private memory)
    sim: bool = False  #: the whole system in the simulator instead of a live service
    buffer: str = "pfma"  #: the live service's Bit3 buffer
    require_ft: bool = True  #: a stale F/T link is a fault
    shoulder_roll_deg: int = 0  #: with ``sim``: where the simulated arm's shoulder roll is pinned
    quiet: bool = False  #: do not say state changes, WARNINGs and ERRORs as they happen
    sim_faults: tuple[str, ...] = ()  #: with ``sim``: fault specs injected at ``sim_fault_at_s``
    sim_fault_at_s: float = 0.0
    sim_errors: int = 0  #: with ``sim``: the simulated rack's imperfections (sim/errors.py), 0: none
    realtime: bool | None = None  #: SCHED_FIFO: True asked, False refused, None the default
    trace: bool = False  #: print each frame's trace line
    changes: bool = False  #: ... only of frames in which a status changed
    distributed: Distribution | None = None  #: one process of a distributed controller
    #: service frames it may miss in a row before a servo fault (None: FrameConfig's default, 2)
    max_missed_run: int | None = None
    #: its frame clock: "locked" to the service's frames, or "own" (controller.frames)
    clock: str = "locked"
    say: Callable[[str], None] = field(default=lambda line: print(line, flush=True))  #: where lines go


class Driver:
    """Steps a controller runtime, one minor frame at a time; what both drivers share:
    the live pacing, the messages said as they happen, the trace, the stop on signals."""

    #: live frames run before the garbage collector is frozen (imports, first allocations)
    FREEZE_AFTER_FRAMES = 32
    #: the terminal is told the service went silent after this long without a frame, s
    #: (its layers report it at once, in the controller's message queue: this line is for
    #: whoever watches the terminal)
    SILENT_SAY_S = 0.5
    #: say when the service goes silent and when its frames come again
    SAYS_SILENCE = True

    def __init__(self, rt, options: ControllerOptions, pacer: LivePacer | None = None, sim=None, client=None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.rt = rt
        self.options = options
        self.pacer = pacer
        self.sim = sim
        self.client = client
        self.printed_header = False
        #: says System Up/Down's state changes, WARNINGs and ERRORs as they happen (after the
        #: frame, rate-limited; None when quiet): controller.messages.LivePrinter
        self.say = None
        if not options.quiet:
            from controller.messages import LivePrinter
            self.say = LivePrinter(options.say, clock)
            self.rt.messages.listeners.append(self.say)
        self.stop_signal = 0  #: the SIGTERM or SIGINT that asked for a stop (0: none)
        self.closing = False  #: leaving safe: the power-down's frames run whatever the signals
        self._silent_since: float | None = None  # the first give-up of the pacer in a row
        self._silent_frame = -1
        self._silent_said = False

    @property
    def period_s(self) -> float:
        return self.rt.frames.period_s

    def frame(self) -> None:
        """One minor frame locked to the live service's next frame (a SIGTERM or SIGINT taken
        by :meth:`ControllerStack.stop_on_signals` stops here, between two frames)."""
        if self.stop_signal and not self.closing:
            raise KeyboardInterrupt
        pacer = self.pacer
        assert pacer is not None
        gave_up = pacer.gave_up
        pacer.wait()  # locked to the service: its next frame, on absolute deadlines
        self.rt.tick()  # a minor frame, or the halted hold (pfma controller halt|step|resume)
        snap = self.rt.daq.snapshot
        pacer.stepped(float(snap.t_s))
        if self.say is not None:
            self.say.flush()  # after the frame's work: at most LIVE_PER_FLUSH lines
        if self.SAYS_SILENCE and (pacer.gave_up != gave_up or self._silent_since is not None):
            self._say_silence(pacer.gave_up != gave_up, int(snap.frame))
        if not pacer.gc_frozen and pacer.frames == self.FREEZE_AFTER_FRAMES:
            pacer.freeze_gc()  # start-up allocations done: no collector pauses in frames

    def _say_silence(self, gave_up: bool, frame: int) -> None:
        """One line when the service has published nothing for SILENT_SAY_S, one when its
        frames come again."""
        now = time.monotonic()
        if gave_up:
            if self._silent_since is None:
                self._silent_since, self._silent_frame, self._silent_said = now, frame, False
            elif not self._silent_said and now - self._silent_since >= self.SILENT_SAY_S:
                self._silent_said = True
                log.warning(f"no frame from the service for over {self.SILENT_SAY_S:g} s (last: frame {frame}; "
                            f"stopped or stalled?): the layers report it and the commands are 0; waiting for frames")
        elif frame != self._silent_frame:
            if self._silent_said:
                log.info(f"frames from the service again (frame {frame})")
            self._silent_since = None

    def show(self, rec) -> None:
        """A frame's trace line (an ``rt.on_frame`` hook), with the header before the first."""
        if not self.options.trace or (self.options.changes and not any(lt.changed for lt in rec.layers)):
            return
        if not self.printed_header:
            print(self.rt.header())
            self.printed_header = True
        print(self.rt.format_frame(rec), flush=True)

    def on_signal_handler(self, between_frames: bool) -> Callable:
        """The SIGINT/SIGTERM handler of :meth:`ControllerStack.stop_on_signals`."""
        def on_signal(signum, _frame) -> None:
            if self.stop_signal or not between_frames:
                raise KeyboardInterrupt
            self.stop_signal = signum
        return on_signal

    def leave_safe(self) -> None:
        """Leave the outputs safe before the process lets go (its stack's first close)."""


class LocalDriver(Driver):
    """Steps either a SystemSimulator or a runtime paced by a live service."""

    def __init__(self, rt, options: ControllerOptions, **parts) -> None:
        sim = parts.get("sim")
        super().__init__(rt, options, clock=sim.clock.now if sim is not None else time.monotonic, **parts)
        self.faults = None
        self._fault_frame = 0
        if sim is not None and options.sim_faults:
            from sim.faults import FaultSet
            self.faults = FaultSet(sim.world)
            self._fault_frame = sim.service_frames + int(round(options.sim_fault_at_s / self.period_s))

    @property
    def period_s(self) -> float:
        """What one :meth:`frame` advances: a service frame in the simulator (the controller's
        own period differs on its own clock), else the controller's minor frame."""
        return self.sim.service_period_s if self.sim is not None else self.rt.frames.period_s

    def frame(self) -> None:
        if self.stop_signal and not self.closing:
            raise KeyboardInterrupt  # SIGTERM/SIGINT, acted on between frames (see stop_on_signals)
        if self.sim is None:
            super().frame()
            return
        if self.faults is not None and self.sim.service_frames >= self._fault_frame:
            for spec in self.options.sim_faults:
                f = self.faults.inject(spec)
                print(f"{PROG}: simulated fault injected: {f.spec}", flush=True)
            self.faults = None
        self.sim.step(1)
        if self.say is not None:
            self.say.flush()

    def leave_safe(self) -> None:
        """A halted controller: its outputs are already held safe; the hold is released so
        the service goes SAFE (no re-arm, no power-down). A running live one: powered down
        in order (at most STOP_S) before the buffer is let go."""
        from controller.decision import Status
        self.closing = True
        rt = self.rt
        if rt.halted:
            rt.release_halt()
            log.warning("was halted; outputs left safe (0 V, brakes set)")
        elif self.sim is None and rt.status("updown") not in (Status.SHUT_DOWN, Status.ERROR):
            from controller.layers import Request
            try:
                rt.request(Request.POWER_DOWN)
                t_end = time.monotonic() + STOP_S
                while time.monotonic() < t_end and not rt.all_status(Status.SHUT_DOWN):
                    self.frame()
            except Exception as err:  # noqa: BLE001
                log.error(f"power down on exit: {err}")


class DistributedDriver(Driver):
    """One live process of a distributed controller: its runtime paced by the service."""

    SAYS_SILENCE = False

    def __init__(self, dp, options: ControllerOptions, link=None, **parts) -> None:
        super().__init__(dp.rt, options, **parts)
        assert options.distributed is not None
        self.dp = dp
        self.link = link
        self.config = options.distributed.config
        self.process = options.distributed.process
        self.base = options.distributed.base
        self.spec = self.config.process(self.process)

    def leave_safe(self) -> None:
        """Leave the arm safe before letting go. The process with System Up/Down powers the
        whole system down in order (the others still running); another process, while the
        system is up, stops its own layers (its layers next to another process's fault,
        DistributedProcess.leave) and, with Data Acquisition, waits for the safe stop."""
        from controller.decision import Status
        from controller.layers import Request
        self.closing = True
        rt = self.rt
        t_end = time.monotonic() + STOP_S
        try:
            if "updown" in rt.local_keys:
                if rt.status("updown") in (Status.SHUT_DOWN, Status.ERROR):
                    return
                rt.request(Request.POWER_DOWN)
                while time.monotonic() < t_end and not rt.all_status(Status.SHUT_DOWN):
                    self.frame()
                return
            if self.dp.leave():
                while time.monotonic() < t_end and not self.dp.stopped():
                    self.frame()
        except Exception as e:  # noqa: BLE001
            log.error(f"power down on exit: {e}")


class ControllerStack(contextlib.ExitStack):
    """One controller process, opened in order and closed in reverse on every exit path.

    ``with ControllerStack(options) as stack: stack.driver.frame() ...``; or
    ``stack = ControllerStack(options).open()`` (which closes what it opened when a part
    fails) and then ``with stack:``. Closing leaves the outputs safe first
    (:meth:`Driver.leave_safe`), then lets go of the pacer's collector, the runtime and its
    world model, and the service's buffer (or the simulator), then gives back the signal
    handlers :meth:`stop_on_signals` took.
    """

    def __init__(self, options: ControllerOptions) -> None:
        super().__init__()
        self.options = options
        self.driver: Driver | None = None
        self._old_handlers: dict = {}

    def __enter__(self) -> "ControllerStack":
        super().__enter__()
        if self.driver is None:
            self.open()
        return self

    def open(self) -> "ControllerStack":
        """Assemble the process (idempotent); on a failure what was opened is closed again."""
        if self.driver is not None:
            return self
        try:
            self.callback(self._restore_signals)  # the last thing closed
            from controller.frames import FrameConfig
            run = self.options.max_missed_run
            frames = FrameConfig.profile(self.options.profile, clock=self.options.clock,
                                         **({} if run is None else {"max_missed_run": run}))
            if self.options.distributed is not None:
                driver: Driver = self._open_distributed(frames)
            elif self.options.sim:
                driver = self._open_sim(frames)
            else:
                driver = self._open_live(frames)
            self.callback(driver.leave_safe)  # the first thing closed: the outputs left safe
            self.driver = driver
        except BaseException:
            self.close()
            raise
        return self

    @property
    def rt(self):
        assert self.driver is not None
        return self.driver.rt

    def _open_sim(self, frames) -> Driver:
        from sim.errors import seeded
        from sim.system import SystemSimulator
        o = self.options
        sim = self.enter_context(SystemSimulator(frames=frames, wm_name=o.wm, require_ft=o.require_ft,
                                                 shoulder_roll_deg=o.shoulder_roll_deg, errors=seeded(o.sim_errors)))
        sim.step(10)  # the service's first frames (links open)
        return LocalDriver(sim.rt, o, sim=sim)

    def _open_live(self, frames) -> Driver:
        from bit3.client import Client
        from controller.runtime import ControllerRuntime
        from pfma.clock import MonotonicClock
        o = self.options
        client = Client.attach(o.buffer, writer="commands", owner="pfma-controller")
        self.callback(client.close)
        rt = ControllerRuntime(client, frames=frames, wm_name=o.wm, clock=MonotonicClock(), require_ft=o.require_ft)
        self.callback(rt.close)
        pacer = self._pacer(OwnClockPacer(client, rt) if frames.clock == "own" else LivePacer(client, frames.period_s))
        return LocalDriver(rt, o, pacer=pacer, client=client)

    def _open_distributed(self, frames) -> Driver:
        from bit3.client import Client
        from controller.distributed import DistributedProcess
        from pfma.clock import MonotonicClock
        from tools.attach import attach_reader
        o = self.options
        d = o.distributed
        assert d is not None
        spec = d.config.process(d.process)
        if "daq" in spec.layers:
            client = Client.attach(o.buffer, writer="commands", owner=f"pfma-controller-{d.process}")
        else:
            client = attach_reader(o.buffer)
        self.callback(client.close)
        link, sources = None, None
        if d.config.transport == "zenoh":
            from tools.wm_sections import ZenohLink
            listen, connect = d.config.endpoints(d.process)
            link = ZenohLink(d.config, d.process, d.base, listen=listen, connect=connect)
            self.callback(link.close)
            sources = link.sources
        dp = DistributedProcess(d.config, d.process, client, wm_base=d.base, sources=sources, frames=frames,
                                clock=MonotonicClock(), require_ft=o.require_ft)
        self.callback(dp.close)
        if link is not None:
            dp.rt.on_frame.append(link.publish)
        pacer = self._pacer(LivePacer(client, frames.period_s) if isinstance(client, Client) else PollPacer(client))
        return DistributedDriver(dp, o, link=link, pacer=pacer, client=client)

    def _pacer(self, pacer: LivePacer) -> LivePacer:
        """The live pacer, the real-time set-up, start-up's garbage kept out of the first frames."""
        self.callback(pacer.release_gc)
        realtime(self.options.realtime)
        gc.collect()  # what start-up allocated is not collected inside the first frames
        gc.freeze()
        return pacer

    def stop_on_signals(self, between_frames: bool = True) -> None:
        """SIGTERM and SIGINT stop the controller as Ctrl-C always did (the orderly power-down
        of :meth:`Driver.leave_safe`), acted on between two frames, never inside one; a second
        signal stops at once. Also where the shell started it with SIGINT ignored (a
        background job) and under a process manager's SIGTERM. ``between_frames`` False (the
        keyboard loops, which wait in ``input()``): the signal interrupts at once, as Ctrl-C
        does there. The old handlers come back when the stack closes, after the power-down."""
        assert self.driver is not None
        handler = self.driver.on_signal_handler(between_frames)
        for s in (signal.SIGINT, signal.SIGTERM):
            old = signal.signal(s, handler)
            self._old_handlers.setdefault(s, old)

    def _restore_signals(self) -> None:
        for sig, h in self._old_handlers.items():
            signal.signal(sig, h)
        self._old_handlers.clear()
