"""The controller runtime: the seven layers, the minor frame, halt/single step, the
per-frame trace and the message queues.

One minor frame (:meth:`ControllerRuntime.step`), locked to the I/O service's frame
(it runs right after each service frame has published its inputs):

1. **acquire** - Data Acquisition reads the service's input snapshot and posts it
   (IRSS: the I/O data arrive in the world model at the frame interrupt);
2. **communications segment** - ``wm.communications_segment()``: every output queued
   since the last segment (tasks, tables, the inputs of step 1, user writes) is
   applied at once (report 2.2.3, 2.3.6);
3. **decision tables** - all seven, highest layer first; each reads only its command,
   its status and its subordinate's status from the world model (report 2.2.4) and
   posts its status and the command to the layer below (applied next frame);
4. **output** - Data Acquisition writes the rate and current-limit commands to the
   Bit3 buffer with a new heartbeat (rates forced 0 unless it is START UP COMPLETE);
5. **tasks** - the sequence tasks the tables created, then the periodic tasks due in
   this frame by the scheduling table (:mod:`controller.frames`), indexed by the
   service's frame number so that the servo runs in the frames with fresh resolver
   data.

A status change therefore climbs one layer per minor frame (report 2.2.4), except an
ERROR: it climbs every layer in the frame it is decided (:meth:`ControllerRuntime._climb_errors`),
so an error seen by Data Acquisition in frame k is System Up/Down's ERROR in frame k.

Missed frames (docs/controller.md, "Missed frames and command freshness"): when the
service frame jumped by more than 1 since the last step, the frames in between were
missed. They are counted (:attr:`missed_frames`, :attr:`missed_events`,
:attr:`longest_missed_run`, :attr:`missed_task_slots`), a WARNING names them (at most one
message per :data:`MISSED_MESSAGE_INTERVAL_S`, with a count of the others), and the
periodic tasks due in them run once in this frame (catch-up; a task due both in a missed
frame and in this one runs once). More than ``FrameConfig.max_missed_run`` in a row while
the servo is running (START UP COMPLETE: its rates reach the arm; while it starts up, Data
Acquisition sends rates of 0 whatever happens) is a fault of the Servo Control layer (code 12), raised
before the tables so its table goes to ERROR in this frame. :attr:`servo_oldest_frame` and
:attr:`servo_catch_up` tell Data Acquisition's output which servo outputs it may send.

Timing: each step records its wake latency (clock time at the start of the step minus the
service's frame time ``inputs.t_s``, the same host clock), its work (host time of the
step) and overruns (work ended after the next service frame was due or had been
published) in preallocated rings, and about every :data:`STATS_PUBLISH_S` publishes them
(percentiles) into ``runtime.*`` world-model variables and the Bit3 ``controller_stats``
area (when this controller holds the command area).

A distributed controller (``local_layers``, :mod:`controller.distributed`): this runtime is
one process's and runs only its layers' tables and tasks; :attr:`before_segment` imports the
other processes' sections right before the first communications segment; without Data
Acquisition the frame number comes from the inputs read-only and nothing is written to the
Bit3 buffer; the other layers appear in the trace and :attr:`status_changes` as their
sections bring them; halt and single step are refused. Without ``local_layers`` (one
process) nothing of this runs.

Visibility: :attr:`trace` keeps a record of every frame (each layer's command,
status, deciding row and mailbox; :func:`format_trace`), :attr:`messages` the layers'
messages (50 per source, the last 100 merged by time).

Halt, single step, resume on a running system (docs/console.md): the controller's process
calls :meth:`tick` once per service frame. Running, a tick is :meth:`step`. Halted (a
``Request.HALT`` through the world model's request protocol, answered by System Up/Down),
a tick is :meth:`hold`: no decision tables, no tasks, the world model keeps the halted
frame's values, controller time stands still, and Data Acquisition writes the halted safe
command (0 rates, 0 current limits, ``mode`` HALTED) with a new heartbeat, so the service
holds HALTED (0 V, brakes set) and its watchdog never trips. ``Request.STEP`` with N runs
exactly N whole minor frames (one per service frame, outputs still held safe) and
publishes their trace in ``runtime.step_trace``. ``Request.RESUME`` needs the re-arm
argument (1): the outputs are re-armed with a new arm request (0 rates) and the frames
go on at the next servo slot; without it the resume is refused with a message.
``pfma controller --halt`` (at launch) still single-steps from the keyboard.
"""

from __future__ import annotations

import math
import gc
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from controller.cartesian import CartesianLayer
from controller.daq_layer import DataAcquisitionLayer
from controller.decision import SHORT, SHORT_CMD, Command, Status, TaskState
from controller.frames import MINOR_FRAMES_PER_MAJOR, FrameConfig, ScheduleError
from controller.gripper import GRIP
from controller.layers import (
    ERR_INVALID_VALUE, ERR_TASK_RAISED, JOINT, UI, JointPlannerLayer, Layer, Request, Response, UpDownLayer, find_answer,
)
from controller.messages import Level, Message, MessageBoard
from controller.neighbours import read_rules
from controller.paths import MultiSegmentLayer
from controller.relays import wire as wire_relays
from controller.trajectory import TrajectoryLayer
from controller.servo import ERR_MISSED, ServoLayer
from controller.worldmodel import VarSpec, WorldModel, WorldModelValueError
from controller.worldmodel.var import Var, VarGroup, var
from controller.variables import DAQ
from bit3.layout import ServiceState, Severity

#: frames kept in the trace by default (about 6 s at 320 Hz)
TRACE_FRAMES = 2048
#: a layer's message level -> its severity in the Bit3 controller message queue (the same
#: four names; a DEBUG line stays DEBUG there, where tools may leave it out)
_SEVERITY = {Level.DEBUG: Severity.DEBUG, Level.INFO: Severity.INFO, Level.WARNING: Severity.WARNING,
             Level.ERROR: Severity.ERROR}
#: at most one missed-frame WARNING per this many seconds; the others are counted into the next
MISSED_MESSAGE_INTERVAL_S = 1.0
#: controller statistics are published (world model, Bit3 controller_stats) this often
STATS_PUBLISH_S = 0.5
#: frames of wake-latency and work samples kept for the percentiles (3.2 s at 320 Hz)
TIMING_RING = 1024
#: the servo's periodic task (its slot defines the servo period)
SERVO_TASK = "servo_control"
#: bytes of ``runtime.first_cause`` (the root message of the current ERROR episode, UTF-8):
#: "LAYER: text", cut to this many bytes (assumed enough for a layer's fault sentence; the
#: whole text stays in :attr:`ControllerRuntime.first_cause`)
FIRST_CAUSE_BYTES = 240
#: an ERROR message is the root of the ERROR a layer enters if it was posted at most this
#: many minor frames before (a fault is posted in one frame and its layer's table decides
#: ERROR in the next; a sequence task's failure likewise). Assumed: 64 frames (0.2 s at
#: 320 Hz) covers every such path with room; an older ERROR message from the same layer
#: that did not lead to ERROR is not taken for the root.
FIRST_CAUSE_WINDOW_FRAMES = 64


def first_cause_text(wm) -> str:
    """A world model's ``runtime.first_cause`` as text ("" without an ERROR episode, or a
    world model without the variable)."""
    try:
        raw = wm.get(RUNTIME.first_cause)
    except Exception:  # noqa: BLE001 - an older world model, or one without the runtime's variables
        return ""
    return bytes(np.asarray(raw, dtype=np.uint8)).rstrip(b"\0").decode(errors="replace")


@dataclass(frozen=True)
class FirstCause:
    """The root message of an ERROR episode (the first of the cascade, not its last)."""
    source: str  #: layer key (or "runtime")
    code: int  #: the layer's error code when it entered ERROR (0: none)
    text: str
    t_s: float  #: seconds since the runtime started
    frame: int  #: minor frame of the message

    def format(self) -> str:
        c = f" (code {self.code})" if self.code else ""
        return f"{self.source}: {self.text}{c}  [frame {self.frame}, t {self.t_s:.3f} s]"


#: bytes of ``runtime.step_trace`` (the trace of the last single-step run, UTF-8): the
#: header and about 45 frame lines; a longer run keeps its last lines
STEP_TRACE_BYTES = 8192
#: most frames one SINGLE STEP request may run (assumed: 10 s at 320 Hz; longer is a resume)
MAX_STEP_FRAMES = 3200
#: service frames a resume waits for the service to arm before it fails (0.2 s at 320 Hz,
#: as Data Acquisition's start-up waits ARM_TIMEOUT_S)
RESUME_ARM_FRAMES = 64
#: servo faults that are events (a missed period, an output too old): cleared by an error reset
SERVO_EVENT_FAULTS = (ERR_MISSED,)
#: distinct per-layer trace records kept for reuse (they repeat frame after frame; a
#: LayerTrace is immutable, so one object serves every frame with the same values)
LAYER_TRACE_CACHE = 4096


class FrameTiming:
    """Preallocated rings of the controller's per-frame wake latency and work (us)."""

    def __init__(self, n: int = TIMING_RING) -> None:
        self.wake_us = np.zeros(n)
        self.work_us = np.zeros(n)
        self.n = 0
        self._i = 0
        self._size = n
        # numpy's first percentile call costs ~10 ms (lazy set-up): made here, not in a frame
        # (live, it fell in the first statistics publish 0.5 s after start: 3 missed frames)
        np.percentile(self.wake_us[:8], (50, 99))

    def add(self, wake_us: float, work_us: float) -> None:
        i = self._i
        self.wake_us[i] = wake_us
        self.work_us[i] = work_us
        self._i = (i + 1) % self._size
        if self.n < self._size:
            self.n += 1

    def summary(self) -> tuple[float, float, float, float, float, float]:
        """wake p50, p99, max, work p50, p99, max (us) over the ring (zeros while empty)."""
        if not self.n:
            return (0.0,) * 6
        w, k = self.wake_us[:self.n], self.work_us[:self.n]
        wp, kp = np.percentile(w, (50, 99)), np.percentile(k, (50, 99))
        return (float(wp[0]), float(wp[1]), float(w.max()), float(kp[0]), float(kp[1]), float(k.max()))


class RuntimeVars(VarGroup, prefix="runtime", writer="runtime"):
    """The runtime's own world-model variables (frame timing, missed frames, halt and
    single step, the first cause of an ERROR episode)."""

    frames: Var[int] = var("task_status", "i8", (), 0, doc="controller frames run")
    missed_frames: Var[int] = var("task_status", "i8", (), 0,
                                  doc="service frames the controller did not run (their tasks caught up)")
    missed_events: Var[int] = var("task_status", "i8", (), 0, doc="times one or more frames were missed")
    longest_missed_run: Var[int] = var("task_status", "i4", (), 0, doc="most frames missed in a row")
    missed_task_slots: Var[int] = var(
        "task_status", "i8", (), 0,
        doc="periodic task slots that fell in missed frames (caught up once in the next frame)")
    overruns: Var[int] = var("task_status", "i8", (), 0, doc="frames whose work ended after the next service frame")
    rate_hz: Var[float] = var("task_status", "f8", (), 0.0, "Hz", doc="measured controller frame rate")
    wake_latency_us: Var[np.ndarray] = var("task_status", "f8", (3,), [0.0] * 3, "us",
                                           doc="wake latency after the service's frame time: p50 p99 max")
    work_us: Var[np.ndarray] = var("task_status", "f8", (3,), [0.0] * 3, "us",
                                   doc="controller frame work (host time): p50 p99 max")
    halted: Var[bool] = var("status_output", "b1", (), False,
                            doc="halted (IRSS halt): no frames run, outputs held in the service's HALTED state")
    steps_left: Var[int] = var("status_output", "i4", (), 0, doc="single-step frames still to run")
    step_frames: Var[int] = var("status_output", "i8", (), 0, doc="frames run by single steps since the start")
    step_trace: Var[np.ndarray] = var("response_output", "u1", (STEP_TRACE_BYTES,), [0] * STEP_TRACE_BYTES,
                                      doc="trace of the last single-step run (UTF-8 text, zero-padded)")
    first_cause: Var[np.ndarray] = var(
        "error_reports", "u1", (FIRST_CAUSE_BYTES,), [0] * FIRST_CAUSE_BYTES,
        doc="the first cause of the current ERROR episode: the root message that started it "
            "(\"LAYER: text\", UTF-8, zero-padded; empty: no episode); kept until an ERROR RESET "
            "completes (docs/controller.md \"First cause\")")
    first_cause_code: Var[int] = var("error_reports", "i4", (), 0,
                                     doc="the first cause's layer error code (0: none, or a message without a code)")
    first_cause_frame: Var[int] = var("error_reports", "i8", (), -1,
                                      doc="the minor frame of the first cause's message (-1: no episode)")


RUNTIME = RuntimeVars


def runtime_specs() -> list[VarSpec]:
    """The runtime's own world-model variables (:class:`RuntimeVars`)."""
    return RUNTIME.specs()


@dataclass(frozen=True)
class LayerTrace:
    command: int
    status: int  #: the status the table decided this frame
    rid: int  #: the deciding row
    task: int  #: mailbox 10 x kind + state, after the frame's tasks
    changed: bool  #: status changed this frame


@dataclass(frozen=True)
class FrameTrace:
    frame: int
    t_s: float  #: seconds since the runtime started
    layers: tuple[LayerTrace, ...]
    fault_bits: int
    tasks: tuple[str, ...]  #: periodic tasks run
    cost_s: float  #: host time the controller frame took (not deterministic)


#: the layer keys, highest first (what a distributed controller's configuration names)
LAYER_KEYS = ("updown", "msp", "trajectory", "cartesian", "joint", "servo", "daq")


class _InputsOnly:
    """A read-only Bit3 client as the Data Acquisition layer of a process that does not run
    it sees it (a distributed controller, controller/distributed.py): the layout and a
    private copy of the command record, no writer role (the layer is built for its
    world-model variables only; it never acquires or writes there)."""

    role = None

    def __init__(self, client) -> None:
        self._client = client
        self.layout = client.layout
        self.command = client.read_commands().record.copy()

    def __getattr__(self, name: str):
        return getattr(self._client, name)


def build_layers(client, require_ft: bool = True) -> list[Layer]:
    """The seven layers, highest first, linked superior/subordinate."""
    layers: list[Layer] = [
        UpDownLayer(),
        MultiSegmentLayer(),
        TrajectoryLayer(),
        CartesianLayer(),
        JointPlannerLayer(),
        ServoLayer(),
        DataAcquisitionLayer(client, require_ft=require_ft),
    ]
    for up, down in zip(layers, layers[1:]):
        up.subordinate, down.superior = down, up
    return layers


def _stats_writer(client):
    """The writer of the Bit3 ``controller_stats`` area when ``client`` is the controller's
    writer and its buffer has the area (None: the statistics go to the world model only)."""
    if getattr(client, "role", None) != "controller":
        return None
    try:
        return client.buffer.writer("controller_stats")
    except Exception:  # noqa: BLE001 - an older buffer without the area: world model only
        return None


def _local_keys(local_layers: Sequence[str] | None) -> frozenset[str]:
    """The keys of the layers a process runs: all seven when ``local_layers`` is None.

    :raises ValueError: an unknown key, or none
    """
    if local_layers is None:
        return frozenset(LAYER_KEYS)
    unknown = [k for k in local_layers if k not in LAYER_KEYS]
    if unknown or not local_layers:
        raise ValueError(f"local_layers {list(local_layers)}: layer keys are {', '.join(LAYER_KEYS)}")
    return frozenset(local_layers)


class ControllerRuntime:
    """The controller: seven layers over a world model, driven one minor frame at a time.

    :param client: a :class:`bit3.client.Client` attached as the command writer
    :param frames: frame rate and scheduling table (validated here)
    :param wm_name: shared-memory name of the world model (None: private, in-process)
    :param clock: time source for stamps and sequence-task timeouts (the service's)
    :param access_key: the world model's key for user writes (default: its default)
    :param require_ft: a stale F/T link is a hardware fault
    :param trace_frames: frames kept in :attr:`trace`
    :param forward_messages: copy WARNING and ERROR messages to the Bit3 controller queue
    :param local_layers: a distributed controller's process (controller/distributed.py):
        the keys of the layers this process runs (their tables, sequence and periodic
        tasks); the others' variables are in the world model but written by other
        processes. Without ``daq`` the client may be read-only: the frame comes from its
        inputs, nothing is written to the Bit3 buffer. None (default): all seven, one process.
    """

    def __init__(self, client, *, frames: FrameConfig | None = None, wm_name: str | None = None,
                 clock=None, access_key: str | None = None, require_ft: bool = True,
                 trace_frames: int = TRACE_FRAMES, forward_messages: bool = True,
                 local_layers: Sequence[str] | None = None) -> None:
        self.frames = (frames or FrameConfig()).validate()
        self.client = client
        self.clock = clock
        local_keys = _local_keys(local_layers)
        #: a distributed controller's process (``local_layers`` given)
        self.distributed = local_layers is not None
        self.local_keys = local_keys
        self._init_layers(client, require_ft)
        self._init_world_model(wm_name, clock, access_key)
        self.messages = MessageBoard()
        self.trace: deque[FrameTrace] = deque(maxlen=trace_frames)
        self.frame = -1
        self.frames_run = 0
        self.now = clock.now() if clock is not None else time.monotonic()
        self.t0 = self.now  #: trace and message times are seconds since the runtime started
        self.last_rid: dict[str, int] = {}
        self.status_changes: list[tuple[int, str, int, int]] = []  #: (frame, layer, old, new)
        #: the root message of the current ERROR episode (None: no episode); kept until an
        #: ERROR RESET completes (System Up/Down leaves ERROR RESET)
        self.first_cause: FirstCause | None = None
        self.error_episodes = 0  #: ERROR episodes begun since the start
        self._err_cand: dict[str, Message] = {}  # per source: the first recent ERROR message
        self.on_frame: list[Callable[[FrameTrace], None]] = []
        self._goal_seq = 0
        self._gripper_seq = 0
        # halt, single step, resume (docs/console.md)
        self.halted = False
        self.steps_left = 0
        self.step_frames = 0  #: frames run by single steps
        self.holds = 0  #: ticks spent halted (halted safe command written, no frame run)
        self.halt_offset_s = 0.0  #: clock time spent halted (controller time stands still)
        self._raw_now = self.now  # clock time of the latest tick
        self._step_seq = 0  # request being served by single steps (0: none)
        self._step_lines: list[str] = []
        self._resume_seq = 0  # resume request being served (0: none)
        self._resume_ticks = 0
        self._changed: set[str] = set()
        # missed frames
        self.prev_frame = -1  #: minor frame of the previous step (-1: none yet): the service's frame when locked
        #: the controller's own frame clock (FrameConfig.clock "own"): its frame 0's clock time
        #: (None until the first step) and, per minor frame of the last major frame, the
        #: service frame of the inputs it ran on (the servo's freshness check is in those)
        self._own_clock = self.frames.clock == "own"
        self.minor_frame = -1  #: this step's minor frame (the service's frame number when locked)
        self._epoch: float | None = None
        self._tick_frames = [-1] * MINOR_FRAMES_PER_MAJOR
        self._prev_t_s = -math.inf  # service time of that frame (for the stalls between it and the next)
        #: of the missed frames, those the service dropped itself in a host stall (not the controller's)
        self.service_dropped_frames = 0
        self.missed_frames = 0
        self.missed_events = 0
        self.missed_run = 0  #: frames missed just before the latest step
        self.longest_missed_run = 0
        self.missed_task_slots = 0
        self.caught_up: tuple[str, ...] = ()  #: tasks caught up in the latest step
        #: oldest inputs frame a servo output sent this frame may be computed from: this frame
        #: minus the servo's divider (its latest slot before this frame)
        self.servo_oldest_frame = -1
        #: this frame catches up the servo slot of a missed frame (Data Acquisition sends 0
        #: rates for this one frame rather than an output from the period before)
        self.servo_catch_up = False
        self._miss_msg_t = -float("inf")
        self._miss_quiet = [0, 0]  # missed events, frames not reported since the last message
        # timing
        self.timing = FrameTiming()
        self.overruns = 0
        self._pub_t = self.now
        self._pub_frames = 0
        self._pub_cpu = time.process_time()
        self._pub_host = time.perf_counter()
        self.stats_published = 0
        self._stats_w = _stats_writer(client)
        self._build_schedule()
        if forward_messages:
            self.messages.listeners.append(self._forward)
        self.post("runtime", Level.INFO, f"controller ready: {self.frames.frame_rate_hz:g} Hz minor frames, "
                                         f"profile {self.frames.profile_name}, world model "
                                         f"{wm_name or '(private)'}")

    def _init_layers(self, client, require_ft: bool) -> None:
        """The seven layers, those this process runs and the others (``local_keys`` set)."""
        self._has_daq = "daq" in self.local_keys
        self.layers = build_layers(client if self._has_daq else _InputsOnly(client), require_ft)
        # what the layers between pass on to a layer further away (controller/relays.py)
        wire_relays(self.layers, [s for l in self.layers for s in l.specs()])
        #: the layers this process runs (all seven in one process), highest first
        self.run_layers = tuple(l for l in self.layers if l.key in self.local_keys)
        #: the others (a distributed controller): their state is read from the world model
        self.remote_layers = tuple(l for l in self.layers if l.key not in self.local_keys)
        self._remote_status: dict[str, int] = {l.key: int(Status.SHUT_DOWN) for l in self.remote_layers}
        #: called right before each step's first communications segment (a distributed
        #: controller's import of the other processes' sections)
        self.before_segment: Callable[[], None] | None = None
        self.by_key = {l.key: l for l in self.layers}
        self.daq: DataAcquisitionLayer = self.by_key["daq"]  # type: ignore[assignment]
        self.servo: ServoLayer = self.by_key["servo"]  # type: ignore[assignment]
        self.updown: UpDownLayer = self.by_key["updown"]  # type: ignore[assignment]

    def _init_world_model(self, wm_name: str | None, clock, access_key: str | None) -> None:
        """The world model of every layer's variables and the runtime's (``layers`` set)."""
        specs = [s for l in self.layers for s in l.all_specs()] + runtime_specs()
        self.wm = WorldModel.create(specs, name=wm_name, clock=clock, access_key=access_key, owner="controller")
        try:  # data between neighbours: each layer's declared reads checked, then enforced
            self.wm.set_read_rules(read_rules(self.layers, specs))
        except BaseException:
            self.wm.close()
            raise
        if "updown" in self.local_keys:
            self.wm.keep_user_writes(UI.request)  # each write is a request (UpDownLayer)
        self._key = self.wm.access_key

    # --- set-up ----------------------------------------------------------------------------
    def _build_schedule(self) -> None:
        impl: dict[str, Callable] = {}
        for l in self.run_layers:
            impl.update(l.periodic)
        self._check_schedule(impl)
        self._table = tuple(tuple((t.name, impl[t.name]) for t in frame if t.name in impl)
                            for frame in self.frames.table())
        self._table_names = tuple(tuple(n for n, _ in frame) for frame in self._table)
        self._lt_cache: dict[tuple, LayerTrace] = {}
        self._impl = impl
        #: the layer of each task (its reads are checked against that layer's rule; it runs
        #: while its layer's table has it: ``Layer.running``)
        self._task_layer = {n: l.key for l in self.run_layers for n in l.periodic}
        self._task_owner = {n: l for l in self.run_layers for n in l.periodic}
        self._order = tuple(t.name for t in self.frames.tasks if t.name in impl)  # catch-up: schedule order
        self._per_major = sum(len(fr) for fr in self._table)
        self._has_servo = any(t.name == SERVO_TASK for t in self.frames.tasks) and SERVO_TASK in impl
        self._servo_div = self.frames.divider(self.frames.task(SERVO_TASK)) if self._has_servo else 1

    def _check_schedule(self, impl: dict[str, Callable]) -> None:
        """Every scheduled task has an implementation (here or, distributed, in another
        process) and every task of the layers run here (``impl``) is scheduled.

        :raises ScheduleError: listing every such problem
        """
        remote = {n for l in self.remote_layers for n in l.periodic}  # another process runs them
        problems = [f"task {t.name} has no implementation in layer {t.layer}"
                    for t in self.frames.tasks if t.name not in impl and t.name not in remote]
        for l in self.run_layers:  # a layer's tasks are its table's to create and delete
            declared = {n for n, _ in l.table.table.tasks}
            if l.table.table.key:
                problems += [f"task {n} of layer {l.key} is not in its decision table (controller/tables)"
                             for n in l.periodic if n not in declared]
            else:  # a stand-in layer on the shared rows alone: its tasks always exist
                l.running = l._next_running = l.running | frozenset(l.periodic)
        problems += [f"task {n} of a layer is not in the schedule" for n in impl
                     if n not in {t.name for t in self.frames.tasks}]
        if problems:
            raise ScheduleError("controller schedule: " + "; ".join(problems))

    def task_period_s(self, name: str) -> float:
        for t in self.frames.tasks:
            if t.name == name:
                return self.frames.divider(t) * self.frames.period_s
        raise KeyError(name)

    # --- messages ----------------------------------------------------------------------------
    def post(self, source: str, level: Level | int, text: str) -> Message:
        m = self.messages.post(source, level, text, self.now - self.t0, self.frame)
        if level >= Level.ERROR and self.first_cause is None:
            c = self._err_cand.get(source)
            if c is None or m.frame - c.frame > FIRST_CAUSE_WINDOW_FRAMES:
                self._err_cand[source] = m  # the first of a run of this source's ERROR messages
        return m

    def _episode_begins(self, layer: Layer) -> None:
        """``layer`` entered ERROR and no episode is active: its root message (its first
        ERROR message of the last FIRST_CAUSE_WINDOW_FRAMES, e.g. "fault 18: ...") is the
        episode's first cause."""
        m = self._err_cand.get(layer.key)
        if m is None or self.frame - m.frame > FIRST_CAUSE_WINDOW_FRAMES:
            m = self.messages.post(layer.key, Level.ERROR, "entered ERROR", self.now - self.t0, self.frame)
        self.first_cause = FirstCause(layer.key, int(layer.error_code), m.text, m.t_s, m.frame)
        self.error_episodes += 1
        self._err_cand.clear()
        self._publish_first_cause()
        self.post("runtime", Level.WARNING, f"first cause: {self.first_cause.format()}")

    def _reset_done(self, old: int, new: int) -> None:
        """System Up/Down (this process's or, distributed, another's) left ERROR RESET for a
        status that is not ERROR: the episode is over, its first cause cleared."""
        if old == Status.ERROR_RESET and new not in (Status.ERROR, Status.ERROR_RESET) \
                and self.first_cause is not None:
            self.post("runtime", Level.INFO, "ERROR RESET done: first cause cleared")
            self.first_cause = None
            self._err_cand.clear()
            self._publish_first_cause()

    def _publish_first_cause(self) -> None:
        fc = self.first_cause
        raw = b"" if fc is None else f"{fc.source}: {fc.text}".encode()[:FIRST_CAUSE_BYTES]
        words = np.zeros(FIRST_CAUSE_BYTES, dtype=np.uint8)
        words[:len(raw)] = np.frombuffer(raw, dtype=np.uint8)
        self.wm.post_task_outputs("runtime", {
            RUNTIME.first_cause: words, RUNTIME.first_cause_code: 0 if fc is None else fc.code,
            RUNTIME.first_cause_frame: -1 if fc is None else fc.frame})

    def _forward(self, m: Message) -> None:
        """Every layer's message, whole, into the Bit3 controller message queue (a long text
        takes several entries: ``bit3.buffer.MessageQueue``), where tools and the console
        read it."""
        if getattr(self.client, "role", None) == "controller":
            try:
                self.client.post_message(f"{m.source}: {m.text}", _SEVERITY[m.level])
            except Exception:  # noqa: BLE001 - messages never stop the controller
                pass

    def on_status_change(self, layer: Layer, old: int, new: int) -> None:
        self.status_changes.append((self.frame, layer.key, old, new))
        self._changed.add(layer.key)
        if layer is self.updown:
            self.wm.powered_up = new != Status.SHUT_DOWN  # protected variables locked until down again
            self._reset_done(old, new)
        if new == Status.ERROR and self.first_cause is None:
            self._episode_begins(layer)

    # --- the minor frame ---------------------------------------------------------------------
    def step(self) -> FrameTrace:
        """Run one minor frame (also the single step while halted)."""
        try:
            return self._step()
        finally:
            self.wm.read_as(None)  # whatever happened, the runtime and its callers read as nobody

    def _step(self) -> FrameTrace:
        read_as = self.wm.read_as  # each layer's table and tasks read under its rule
        t0 = time.perf_counter()
        self._raw_now = raw = self._clock_now()
        self.now = raw - self.halt_offset_s
        self._changed.clear()
        if self._has_daq:
            read_as("daq")
            self.frame = f = self.daq.acquire(self)
            read_as(None)
        else:
            self.frame = f = self._inputs_frame()
        self.minor_frame = k = self.minor_frame_at(raw, f)
        catch = self._frame_begins(f, k)
        if self.before_segment is not None:
            self.before_segment()
        self.wm.communications_segment()
        if self.remote_layers:
            self._observe_remote()
        if "updown" in self.local_keys:
            read_as("updown")
            self.updown.receive_requests(self)
            read_as(None)
        if self.servo.fault and self.servo.error_code in SERVO_EVENT_FAULTS:
            self._reset_servo_event()
        for l in self.run_layers:
            read_as(l.key)
            l.run_table(self)
            if l.relay_pairs:  # what passes this layer on its way further (controller/relays.py)
                self.wm.relay(l.key, l.relay_pairs)
        if self._changed:
            self._climb_errors()
        daq_status = self._decided(self.daq)
        for l in self.run_layers:
            read_as(l.key)
            l.run_sequence(self)
        slot = k % MINOR_FRAMES_PER_MAJOR
        due = self._table[slot]
        ran = self._table_names[slot]  # every due task runs (one that raises has run too)
        if catch:
            names = set(catch).union(n for n, _ in due)
            due = tuple((n, self._impl[n]) for n in self._order if n in names)
            ran = tuple(n for n, _ in due)
        ran = self._run_periodic(due, ran)
        # output last, after a second communications segment: the rates leave in the frame
        # whose inputs they were computed from (the service sees them 1-2 frames old, not 2-3)
        read_as(None)
        self.wm.communications_segment()
        if self._has_daq:
            read_as("daq")
            self.daq.output(self, daq_status)
            read_as(None)
        self.frames_run += 1
        cost = time.perf_counter() - t0
        self._time_frame(cost)
        bits = self.daq.fault_bits if self._has_daq else int(self.wm.get(DAQ.fault_bits))
        rec = FrameTrace(self.frame, self.now - self.t0, self._layer_traces(), bits, ran, cost)
        self.trace.append(rec)
        for fn in self.on_frame:
            fn(rec)
        return rec

    def _run_periodic(self, due, ran: tuple[str, ...]) -> tuple[str, ...]:
        """Run the periodic tasks due this frame that exist (their layer's table created
        them); returns the names of those that ran."""
        read_as = self.wm.read_as
        task_owner = self._task_owner
        skipped: tuple[str, ...] = ()
        for name, fn in due:
            owner = task_owner[name]
            if name not in owner.running:  # its table has not created it (or has deleted it)
                skipped += (name,)
                continue
            read_as(owner.key)
            try:
                fn(self)
            except Exception as err:  # noqa: BLE001 - a task error is its layer's fault
                if isinstance(err, WorldModelValueError):  # rule 4: refused, the variable keeps its value
                    owner.set_fault(self, ERR_INVALID_VALUE, f"task {name} posted an invalid value: {err}")
                else:
                    owner.set_fault(self, ERR_TASK_RAISED, f"task {name} raised {type(err).__name__}: {err}")
        return tuple(n for n in ran if n not in skipped) if skipped else ran

    def _climb_errors(self) -> None:
        """An ERROR decided this frame reaches System Up/Down in the same frame (issue 33
        item 4; docs/controller.md "Error response"). The report's tables see a neighbour's
        status one communications segment later, so an error climbs one layer a minor frame
        (its 2.2.4: the top "notified within 6 minor frames"); with the one or two frames a
        fault takes to be detected, that is 7-8 frames from the event. Here, when a layer's
        table has just decided ERROR and its superior (run by this process) has not, a
        communications segment carries the status up and the superior's table decides again,
        bottom up, so every layer above decides in the frame the fault was detected. Other
        status changes (power-up, shut-down, resets) climb one layer a frame as the report
        draws it. A superior in another process (a distributed controller) sees it at its
        next frame, as before."""
        changed, local = self._changed, self.local_keys
        for l in reversed(self.run_layers):  # bottom up: each re-run may carry it one further
            up = l.superior
            if l.key in changed and l.decided == Status.ERROR and up is not None and up.key in local \
                    and up.decided != Status.ERROR:
                self.wm.communications_segment()
                self.wm.read_as(up.key)
                up.run_table(self)

    # --- a distributed controller's process (controller/distributed.py) ---------------------
    def _inputs_frame(self) -> int:
        """A process without Data Acquisition: the service frame of the newest inputs (read
        only; the ``daq.*`` variables arrive with the Data Acquisition process's section)."""
        snap = self.client.read_inputs()
        self.daq.snapshot = snap  # the frame's time for the timing statistics
        self.frame = int(snap.frame)
        return self.frame

    def _observe_remote(self) -> None:
        """After the communications segment that imported the other processes' sections:
        their layers' status changes (as this process sees them) go into
        :attr:`status_changes` and the trace, and the protected variables follow System
        Up/Down's status when another process runs it."""
        wm = self.wm
        for l in self.remote_layers:
            new = wm.get_state_variable(l.v_status)
            old = self._remote_status[l.key]
            if new != old:
                self._remote_status[l.key] = new
                self.status_changes.append((self.frame, l.key, old, new))
                self._changed.add(l.key)
                if l is self.updown:
                    self._reset_done(old, new)
        if "updown" not in self.local_keys:
            up = self._remote_status["updown"] != Status.SHUT_DOWN
            if up != wm.powered_up:
                wm.powered_up = up

    def _layer_traces(self) -> tuple[LayerTrace, ...]:
        """Each layer's trace record of this frame (reused from earlier frames with the same values)."""
        cache, changed = self._lt_cache, self._changed
        out = []
        remote = self._remote_trace() if self.remote_layers else None
        for l in self.layers:
            if remote is not None and l.key in remote:
                key = remote[l.key] + (l.key in changed,)
            else:
                last = l.last
                key = (l.key, last[0], l.decided, last[5], int(l.task_kind) * 10 + int(l.task_state),
                       l.key in changed)
            lt = cache.get(key)
            if lt is None:
                if len(cache) >= LAYER_TRACE_CACHE:
                    cache.clear()
                lt = cache[key] = LayerTrace(*key[1:])
            out.append(lt)
        return tuple(out)

    def _remote_trace(self) -> dict[str, tuple]:
        """The other processes' layers in the trace: command, status, row and mailbox as
        their sections brought them (the frame before, as a status climbs in one process)."""
        names = self._remote_trace_names
        if names is None:
            names = self._remote_trace_names = tuple(f"{l.key}.{v}" for l in self.remote_layers
                                                     for v in ("command", "status", "row", "task"))
        v = self.wm.get_task_inputs(names)
        return {l.key: (l.key, int(v[f"{l.key}.command"]), int(v[f"{l.key}.status"]), int(v[f"{l.key}.row"]),
                        int(v[f"{l.key}.task"])) for l in self.remote_layers}

    _remote_trace_names: tuple[str, ...] | None = None

    def _clock_now(self) -> float:
        return self.clock.now() if self.clock is not None else time.monotonic()

    def _reset_servo_event(self) -> None:
        """A missed servo period (ERR_MISSED, raised here) is an event, not a condition that
        lasts (Data Acquisition's "no servo output" is the same, latched there): nothing
        would ever clear the flag, and the decision tables run an error reset only once the
        fault is gone, so ERROR RESET hung with the servo in ERROR. The flag is cleared when
        the servo's command is ERROR RESET (the table then resets it like any layer)."""
        if self.wm.get_state_variable(f"{self.servo.key}.command") == Command.ERROR_RESET:
            self.post(self.servo.key, Level.INFO, f"error reset: fault {self.servo.error_code} was an event; cleared")
            self.servo.clear_fault(self)

    # --- the minor frame's number, missed frames ---------------------------------------------
    def minor_frame_at(self, raw: float, f: int) -> int:
        """The minor frame a step at clock time ``raw`` on the service's inputs frame ``f`` is:
        ``f`` when locked to the service (the default); with the controller's own clock, the
        number of its periods since its first step (a step late by more than a period is the
        next frame: the one it was late for is missed)."""
        if not self._own_clock:
            return f
        if self._epoch is None:
            self._epoch = raw
        return int(math.floor((raw - self._epoch) / self.frames.period_s + 1e-6))

    def next_frame_due(self) -> float | None:
        """With the controller's own clock: the clock time its next minor frame is due (what
        a live pacer sleeps until); None when locked to the service or before the first step."""
        if not self._own_clock or self._epoch is None:
            return None
        return self._epoch + (max(self.prev_frame, 0) + 1) * self.frames.period_s

    def _frame_begins(self, f: int, k: int) -> frozenset[str]:
        """Minor frame ``k`` on the inputs of service frame ``f`` begins: count the frames
        missed since the last step, set the servo's freshness bounds; returns the tasks to
        catch up. A repeated frame (no new inputs when locked, two steps in one period on
        the own clock) keeps the servo period it had."""
        prev = self.prev_frame
        t_f = float(self.daq.snapshot.t_s) if self._has_daq and self.daq.snapshot is not None else self.now
        if k == prev:
            self.servo_catch_up = False
            return frozenset()
        catch: frozenset[str] = frozenset()
        missed = k - prev - 1 if 0 <= prev < k else 0
        self.missed_run = missed
        if missed:
            # frames the service dropped itself (a host stall it measured) are not the
            # controller's: it could not run frames that were never published (locked only:
            # on its own clock the controller's frames do not wait for the service's)
            own = missed
            if self._has_daq and not self._own_clock:
                own = max(0, missed - self.daq.service_dropped(self._prev_t_s, t_f, self.frames.period_s))
            catch = self._missed(prev, k, missed, own)
        else:
            self.caught_up = ()
        if self._own_clock:  # the missed frames' slots run now, on these inputs
            for g in range(max(prev + 1, k - MINOR_FRAMES_PER_MAJOR + 1), k + 1):
                self._tick_frames[g % MINOR_FRAMES_PER_MAJOR] = f
        if self._has_servo:
            d = self._servo_div
            if not self._own_clock:
                self.servo_oldest_frame = f - d
            else:  # the inputs frame of minor frame k - d (-1: before the first)
                self.servo_oldest_frame = self._tick_frames[(k - d) % MINOR_FRAMES_PER_MAJOR] if k >= d else -1
            # the latest servo slot before this frame fell in the missed frames: it is
            # caught up in this frame, its output is sent from the next
            self.servo_catch_up = 0 < missed <= self.frames.max_missed_run and \
                self.frames.last_slot(SERVO_TASK, k - 1) > prev
        self.prev_frame = max(prev, k)
        self._prev_t_s = t_f
        return catch

    def _missed(self, prev: int, f: int, missed: int, own: int | None = None) -> frozenset[str]:
        """Minor frames prev+1 .. f-1 were not run (service frames when locked, the
        controller's own when on its own clock): count them, say so, return the tasks
        to catch up, and fault the servo if the run is longer than allowed. ``own``: how many
        of them the service did publish (the rest it dropped in a host stall: caught up, said,
        but never the controller's fault); default all."""
        own = missed if own is None else own
        self.service_dropped_frames += missed - own
        first, last = prev + 1, f - 1
        span = min(missed, MINOR_FRAMES_PER_MAJOR)  # the table repeats every major frame
        names = frozenset(n for g in range(first, first + span) for n, _ in self._table[g % MINOR_FRAMES_PER_MAJOR])
        slots = (missed // MINOR_FRAMES_PER_MAJOR) * self._per_major + sum(
            len(self._table[g % MINOR_FRAMES_PER_MAJOR]) for g in range(first, first + missed % MINOR_FRAMES_PER_MAJOR))
        self.missed_frames += missed
        self.missed_events += 1
        self.longest_missed_run = max(self.longest_missed_run, missed)
        self.missed_task_slots += slots
        self.caught_up = tuple(n for n in self._order if n in names)
        where = f"frame {first}" if missed == 1 else f"frames {first}..{last}"
        where = f"own {where}" if self._own_clock else f"service {where}"
        self.wm.post_task_outputs("runtime", {
            RUNTIME.missed_frames: self.missed_frames, RUNTIME.missed_events: self.missed_events,
            RUNTIME.longest_missed_run: self.longest_missed_run, RUNTIME.missed_task_slots: self.missed_task_slots})
        if self.now - self._miss_msg_t >= MISSED_MESSAGE_INTERVAL_S:
            more = ""
            if self._miss_quiet[0]:
                more = f" (+{self._miss_quiet[0]} more events, {self._miss_quiet[1]} frames, since the last message)"
            whose = "" if own == missed else f"; {missed - own} dropped by the service's own host stall"
            self.post("runtime", Level.WARNING, f"missed {where} ({missed}{whose}): caught up "
                                                f"{', '.join(self.caught_up) or 'no tasks'} in frame {f}{more}")
            self._miss_msg_t = self.now
            self._miss_quiet = [0, 0]
        else:
            self._miss_quiet[0] += 1
            self._miss_quiet[1] += missed
        m = self.frames.max_missed_run
        if own > m and self._has_servo and not self.servo.fault and \
                self.wm.get_state_variable(self.servo.v_status) == Status.START_UP_COMPLETE:
            lost = [g for g in range(first, first + span) if any(n == SERVO_TASK for n, _ in
                                                                 self._table[g % MINOR_FRAMES_PER_MAJOR])]
            lost_s = ", ".join(str(g) for g in lost[:4]) + (" ..." if len(lost) > 4 or missed > span else "")
            self.servo.set_fault(self, ERR_MISSED, f"controller missed {where} ({missed} in a row > "
                                                   f"max_missed_run {m}): servo slot(s) {lost_s or 'none'} "
                                                   f"did not run in their period")
        return names

    # --- timing and statistics -------------------------------------------------------------
    def _time_frame(self, cost_s: float) -> None:
        """Record this step's wake latency, work and overrun; publish the statistics when due."""
        snap = self.daq.snapshot
        raw = self._raw_now  # clock time (not controller time, which stands still while halted)
        # no frame time before the service's first published frame (its record reads t_s 0
        # then): no wake latency to record (it read as the host's uptime, past its valid range)
        t_frame = float(snap.t_s) if snap is not None and snap.t_s > 0 else raw
        period = self.frames.period_s
        own = self._own_clock and self._epoch is not None
        if own:  # on its own clock: the frame was due at its own tick
            t_frame = self._epoch + self.minor_frame * period
        end = self._clock_now()
        wake_us = (raw - t_frame) * 1e6
        self.timing.add(wake_us, cost_s * 1e6)
        # overrun: the work ended after the next frame was due (locked: or the service's next
        # frame was already published)
        if end > t_frame + period or (not own and self.client.changed("inputs")):
            self.overruns += 1
        if self.now - self._pub_t >= STATS_PUBLISH_S:
            self.publish_stats()

    def stats(self) -> dict:
        """The controller's frame statistics (what :meth:`publish_stats` publishes)."""
        w50, w99, wmax, k50, k99, kmax = self.timing.summary()
        dt = self.now - self._pub_t
        host = time.perf_counter() - self._pub_host
        return {
            "frame": max(self.frame, 0), "t_s": self.now, "frames": self.frames_run,
            "missed_frames": self.missed_frames, "missed_events": self.missed_events,
            "missed_run": self.missed_run, "longest_missed_run": self.longest_missed_run,
            "max_missed_run": self.frames.max_missed_run, "missed_task_slots": self.missed_task_slots,
            "overruns": self.overruns, "period_s": self.frames.period_s,
            "rate_hz": (self.frames_run - self._pub_frames) / dt if dt > 0 else 0.0,
            "wake_latency_p50_us": w50, "wake_latency_p99_us": w99, "wake_latency_max_us": wmax,
            "work_p50_us": k50, "work_p99_us": k99, "work_max_us": kmax,
            "cpu_percent": 100.0 * (time.process_time() - self._pub_cpu) / host if host > 0 else 0.0,
            "gc_gen2": gc.get_stats()[2]["collections"],
        }

    def publish_stats(self) -> dict:
        """Publish :meth:`stats` into ``runtime.*`` and the Bit3 ``controller_stats`` area."""
        st = self.stats()
        self.wm.post_task_outputs("runtime", {
            RUNTIME.frames: st["frames"], RUNTIME.missed_frames: st["missed_frames"],
            RUNTIME.missed_events: st["missed_events"], RUNTIME.longest_missed_run: st["longest_missed_run"],
            RUNTIME.missed_task_slots: st["missed_task_slots"], RUNTIME.overruns: st["overruns"],
            RUNTIME.rate_hz: st["rate_hz"],
            RUNTIME.wake_latency_us: (st["wake_latency_p50_us"], st["wake_latency_p99_us"],
                                        st["wake_latency_max_us"]),
            RUNTIME.work_us: (st["work_p50_us"], st["work_p99_us"], st["work_max_us"])})
        w = self._stats_w
        if w is not None:
            rec = w.record
            for k, v in st.items():
                rec[k] = v
            w.publish()
        self._pub_t, self._pub_frames = self.now, self.frames_run
        self._pub_cpu, self._pub_host = time.process_time(), time.perf_counter()
        self.stats_published += 1
        return st

    @staticmethod
    def _decided(layer: Layer) -> int:
        """The status the layer's table decided this frame (posted, visible next frame)."""
        return layer.decided

    # --- halt, single step, resume (IRSS debug window; docs/console.md) ---------------------
    def tick(self) -> "FrameTrace | None":
        """What the controller does after each service frame: a minor frame (:meth:`step`)
        while running or single-stepping, else :meth:`hold`. Returns the frame's trace
        record (None for a hold)."""
        if not self.halted:
            return self.step()
        if self.steps_left > 0 and not self._resume_seq:
            self.steps_left -= 1
            rec = self.step()
            self.step_frames += 1
            self._step_lines.append(format_frame(rec))
            if self.steps_left == 0:
                self._finish_steps()
            return rec
        return self.hold()

    def hold(self) -> "FrameTrace | None":
        """One halted tick: apply user requests (a SINGLE STEP or RESUME arrives this way),
        note the service's frame (frames while halted are neither missed nor stale) and write
        the halted safe command with a new heartbeat. While a resume re-arms, write its
        command instead, and run the first frame once the service is ARMED at a servo slot."""
        raw = self._clock_now()
        snap = self.daq.hold_acquire(self)
        f = int(snap.frame)
        self.frame = f
        k = self.minor_frame_at(raw, f)
        self.prev_frame = max(self.prev_frame, k)
        self._prev_t_s = float(snap.t_s)
        self.wm.communications_segment()
        self.updown.receive_requests(self)
        self.servo.gripper.halted(self)  # a gripper request is refused while halted
        if self._resume_seq and self._resume_tick(snap, f, k):
            return self.step()  # resumed: this tick is the first frame again (controller time goes on)
        if not self._resume_seq:
            self.daq.hold_output(f)
        self.holds += 1
        self.halt_offset_s += raw - self._raw_now
        self._raw_now = raw
        return None

    def debug_request(self, kind: int, arg: int, seq: int) -> tuple[int, str]:
        """Act on a HALT / SINGLE STEP / RESUME request (System Up/Down passes them here);
        returns the answer (Response code, text)."""
        if self.distributed and kind in Request.DEBUG:
            return Response.REFUSED, ("halt and single step are for a controller in one process; this one is "
                                      "distributed (docs/controller.md, \"Distributing the layers\")")
        if kind == Request.HALT:
            if self.halted:
                return Response.COMPLETE, f"already halted (frame {self.frame})"
            self.halted = self.daq.halted = True
            self._post_halt_state()
            self.post("runtime", Level.INFO, f"halted after frame {self.frame}: outputs held safe (0 V, brakes set)")
            return Response.COMPLETE, f"halted after frame {self.frame}: outputs 0 V, brakes set (service HALTED)"
        if kind == Request.STEP:
            n = arg if arg else 1
            if not self.halted:
                return Response.REFUSED, "not halted: halt first"
            if self._resume_seq:
                return Response.REFUSED, "a resume is in progress"
            if self._step_seq:
                return Response.REFUSED, f"{self.steps_left} frame(s) of request {self._step_seq} still to run"
            if not 1 <= n <= MAX_STEP_FRAMES:
                return Response.REFUSED, f"{n} frames: 1..{MAX_STEP_FRAMES} per request"
            self.steps_left, self._step_seq, self._step_lines = n, seq, []
            self._post_halt_state()
            return Response.IN_PROGRESS, f"{n} frame(s) from the next service frame"
        if kind == Request.RESUME:
            if not self.halted:
                return Response.REFUSED, "not halted"
            if self._step_seq:
                return Response.REFUSED, f"{self.steps_left} single-step frame(s) still to run"
            if arg != 1:
                return Response.REFUSED, ("resume needs an explicit re-arm (pfma controller resume --rearm; "
                                          "console: a, then r)")
            if self._resume_seq:
                return Response.IN_PROGRESS, f"already resuming (request {self._resume_seq})"
            if self.daq.arm_request:
                self.daq.rearm_counter += 1  # a new arm request: the service arms only on a new number
            self._resume_seq, self._resume_ticks = seq, 0
            return Response.IN_PROGRESS, "re-arming the outputs" if self.daq.arm_request else "leaving halt"
        return Response.REFUSED, f"not a frame-control request: {kind}"

    def _resume_tick(self, snap, f: int, k: int) -> bool:
        """Write the resume's command; True when the frames may go on (the service armed,
        if this controller had armed it, and minor frame ``k`` is a servo slot; ``f``: the
        service frame)."""
        armed = int(snap.service_state) == ServiceState.ARMED
        need_arm = bool(self.daq.arm_request)
        seen = self._resume_ticks > 0  # the service has had a frame with the resume's command
        if seen and (armed or not need_arm) and (
                not self._has_servo or not need_arm or self.frames.last_slot(SERVO_TASK, k) == k):
            seq, self._resume_seq = self._resume_seq, 0
            self.halted = self.daq.halted = False
            self._post_halt_state()
            what = "outputs re-armed" if need_arm else "outputs were not armed"
            self.updown.answer(self, seq, Response.COMPLETE, f"RESUME: resumed at frame {f} ({what})")
            self.post("runtime", Level.INFO, f"resumed at frame {f} ({what})")
            return True
        if self._resume_ticks > RESUME_ARM_FRAMES:
            seq, self._resume_seq = self._resume_seq, 0
            st = int(snap.service_state)
            why = ServiceState(st).name if st in ServiceState._value2member_map_ else str(st)
            self.updown.answer(self, seq, Response.FAILED, f"RESUME: the service did not arm within "
                                                           f"{RESUME_ARM_FRAMES} frames (state {why}); still halted")
            self.post("runtime", Level.WARNING, f"resume failed: service {why} after {RESUME_ARM_FRAMES} frames")
            self.daq.hold_output(f)
            return False
        self._resume_ticks += 1
        self.daq.hold_output(f, resume=True)
        return False

    def _finish_steps(self) -> None:
        seq, self._step_seq = self._step_seq, 0
        lines = self._step_lines
        text = self.header() + "\n" + "\n".join(lines)
        raw = text.encode()
        if len(raw) > STEP_TRACE_BYTES:  # keep the last lines that fit, say so
            keep = list(lines)
            while keep and len((self.header() + f"\n({len(lines) - len(keep)} earlier lines not kept)\n"
                                + "\n".join(keep)).encode()) > STEP_TRACE_BYTES:
                keep.pop(0)
            raw = (self.header() + f"\n({len(lines) - len(keep)} earlier lines not kept)\n"
                   + "\n".join(keep)).encode()
        buf = np.zeros(STEP_TRACE_BYTES, dtype=np.uint8)
        buf[:len(raw)] = np.frombuffer(raw, dtype=np.uint8)
        self.wm.post_task_outputs("runtime", {RUNTIME.step_trace: buf})
        self._post_halt_state()
        self.updown.answer(self, seq, Response.COMPLETE, f"SINGLE STEP: {len(lines)} frame(s) run, last {self.frame}")

    def _post_halt_state(self) -> None:
        self.wm.post_task_outputs("runtime", {RUNTIME.halted: self.halted, RUNTIME.steps_left: self.steps_left,
                                              RUNTIME.step_frames: self.step_frames})

    def release_halt(self) -> None:
        """Leave a halt without re-arming (the process is ending): the mode is cleared and
        no arm request is made, so the service goes from HALTED to SAFE (0 V, brakes set)."""
        if not self.halted:
            return
        self.daq.arm_request = 0
        self.daq.hold_output(max(self.frame, 0), resume=True)
        self.halted = self.daq.halted = False
        self.steps_left, self._step_seq, self._resume_seq = 0, 0, 0

    # --- user requests (asynchronous, request/response) -------------------------------------
    def request(self, kind: int, arg: int = 0) -> int:
        """Post a user request to System Up/Down (``Request.POWER_UP`` ...; ``arg``: SINGLE
        STEP's frames, RESUME's re-arm, CAMERA ROUTE's monitor * 16 + camera): one keyed
        write of ``ui.request``; returns its number (the write's request id). Its answers
        appear in the answer log (:meth:`answer`) and, while it is the newest request
        answered, in ``ui.response`` / ``ui.response_seq`` / ``ui.response_text``."""
        return int(self.wm.set_user(UI.request, [int(kind), int(arg)], self._key))

    def response(self) -> tuple[int, int]:
        """(request number answered, Response code) of ``ui.response``."""
        v = self.wm.get_task_inputs((UI.response_seq, UI.response))
        return int(v[UI.response_seq]), int(v[UI.response])

    def gripper_request(self, kind: int, force_n: float = 0.0) -> int:
        """Post a gripper request (``pfma.gripper.GripperRequest``: 1 OPEN 2 CLOSE 3 STOP 4 FORCE;
        ``force_n`` > 0 sets the grip force) to Servo Control; returns its number. The answer
        appears in ``gripper.response`` / ``gripper.response_seq`` / ``gripper.response_text``."""
        self._gripper_seq = max(self._gripper_seq, int(self.wm.get(GRIP.request_seq))) + 1
        self.wm.set_user(GRIP.request_force_n, float(force_n), self._key)
        self.wm.set_user(GRIP.request, int(kind), self._key)
        self.wm.set_user(GRIP.request_seq, self._gripper_seq, self._key)
        return self._gripper_seq

    def answer(self, seq: int) -> tuple[int, str] | None:
        """The newest answer to request ``seq`` (Response code, text); None before one."""
        return find_answer(self.wm, seq)

    def set_joint_goal(self, q_rad: Sequence[float]) -> int:
        """Command joint positions (command-area order) through the Joint Planner."""
        self._goal_seq = max(self._goal_seq, int(self.wm.get(JOINT.goal_seq))) + 1
        self.wm.set_user(JOINT.goal_rad, np.asarray(q_rad, dtype=float), self._key)
        self.wm.set_user(JOINT.goal_seq, self._goal_seq, self._key)
        return self._goal_seq

    def set_shoulder_roll(self, deg: int) -> int:
        """Set the shoulder-roll index ``joint.shoulder_roll_deg`` (one of -90, -45, 0, 45, 90;
        only while powered down; the next power-up takes it). A user write like ``pfma wm set``:
        returns its request id. :raises WorldModelError: another value, or powered up"""
        return int(self.wm.set_user(JOINT.shoulder_roll_deg, float(deg), self._key))

    # --- queries -------------------------------------------------------------------------
    def status(self, key: str = "updown") -> Status:
        return Status(self.wm.get_state_variable(f"{key}.status"))

    def statuses(self) -> dict[str, Status]:
        v = self.wm.get_task_inputs([f"{l.key}.status" for l in self.layers])
        return {l.key: Status(int(v[f"{l.key}.status"])) for l in self.layers}

    def all_status(self, status: Status) -> bool:
        return all(s == status for s in self.statuses().values())

    def first_change(self, key: str, to: Status, since_frame: int = -1) -> int | None:
        """Frame in which layer ``key``'s table first decided status ``to`` (after ``since_frame``)."""
        for fr, k, _, new in self.status_changes:
            if k == key and new == to and fr > since_frame:
                return fr
        return None

    def close(self) -> None:
        self.wm.close()

    # --- trace formatting ----------------------------------------------------------------
    def header(self) -> str:
        return format_header(self.layers)

    def format_frame(self, rec: FrameTrace) -> str:
        return format_frame(rec)


def format_header(layers: Sequence[Layer]) -> str:
    cells = " | ".join(f"{l.short:<19}" for l in layers)
    return f"{'frame':>7} {'t ms':>9}  {cells}  hw"


def format_frame(rec: FrameTrace) -> str:
    """One trace line: per layer ``COMMAND>STATUS`` (``*`` marks a change) and the row.

    Example: ``START>START.. r50`` = command START UP, status START UP (in progress),
    decided by row 50 of the table."""
    cells = []
    for lt in rec.layers:
        st = SHORT.get(Status(lt.status), str(lt.status)) if 0 <= lt.status <= 9 else str(lt.status)
        cmd = SHORT_CMD.get(Command(lt.command), str(lt.command)) if 0 <= lt.command <= 4 else str(lt.command)
        cell = f"{'*' if lt.changed else ' '}{cmd}>{st} r{lt.rid}"
        cells.append(f"{cell:<19}")
    return f"{rec.frame:>7} {rec.t_s * 1e3:>9.3f}  {' | '.join(cells)}  {rec.fault_bits:#04x}"


def format_trace(records, layers: Sequence[Layer], only_changes: bool = False) -> str:
    lines = [format_header(layers)]
    for r in records:
        if only_changes and not any(lt.changed for lt in r.layers):
            continue
        lines.append(format_frame(r))
    return "\n".join(lines)


__all__ = ["ControllerRuntime", "FrameTrace", "LayerTrace", "Request", "Response", "format_trace",
           "format_frame", "format_header", "build_layers", "TaskState"]
