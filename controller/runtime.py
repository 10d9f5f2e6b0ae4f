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

A status change therefore climbs one layer per minor frame: an error seen by Data
Acquisition in frame k is System Up/Down's ERROR in frame k + 6 (report 2.2.4: "within
6 minor frames").

Visibility: :attr:`trace` keeps a record of every frame (each layer's command,
status, deciding row and mailbox; :func:`format_trace`), :attr:`messages` the layers'
messages (50 per source, the last 100 merged by time). IRSS's halt is simply not
calling :meth:`step` (no frame interrupts); a single step is one call (the simulator's
``step(1)`` runs one service frame and one controller frame; ``pfma controller --halt``
single-steps from the keyboard).
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from controller.cartesian import CartesianLayer
from controller.daq_layer import DataAcquisitionLayer
from controller.decision import SHORT, SHORT_CMD, Command, Status, TaskState
from controller.frames import MINOR_FRAMES_PER_MAJOR, FrameConfig, ScheduleError
from controller.layers import JointPlannerLayer, Layer, PlaceholderLayer, Request, Response, UpDownLayer
from controller.messages import Level, Message, MessageBoard
from controller.paths import MultiSegmentLayer
from controller.trajectory import TrajectoryLayer
from controller.servo import ServoLayer
from controller.worldmodel import WorldModel
from ioservice.layout import Severity

#: frames kept in the trace by default (about 6 s at 320 Hz)
TRACE_FRAMES = 2048


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


class ControllerRuntime:
    """The controller: seven layers over a world model, driven one minor frame at a time.

    :param client: a :class:`ioservice.client.Client` attached as the command writer
    :param frames: frame rate and scheduling table (validated here)
    :param wm_name: shared-memory name of the world model (None: private, in-process)
    :param clock: time source for stamps and sequence-task timeouts (the service's)
    :param access_key: the world model's key for user writes (default: its default)
    :param require_ft: a stale F/T link is a hardware fault
    :param trace_frames: frames kept in :attr:`trace`
    :param forward_messages: copy WARNING and ERROR messages to the Bit3 controller queue
    """

    def __init__(self, client, *, frames: FrameConfig | None = None, wm_name: str | None = None,
                 clock=None, access_key: str | None = None, require_ft: bool = True,
                 trace_frames: int = TRACE_FRAMES, forward_messages: bool = True) -> None:
        self.frames = (frames or FrameConfig()).validate()
        self.client = client
        self.clock = clock
        self.layers = build_layers(client, require_ft)
        self.by_key = {l.key: l for l in self.layers}
        self.daq: DataAcquisitionLayer = self.by_key["daq"]  # type: ignore[assignment]
        self.servo: ServoLayer = self.by_key["servo"]  # type: ignore[assignment]
        self.updown: UpDownLayer = self.by_key["updown"]  # type: ignore[assignment]
        specs = [s for l in self.layers for s in l.specs()]
        self.wm = WorldModel.create(specs, name=wm_name, clock=clock, access_key=access_key, owner="controller")
        self._key = self.wm.access_key
        self.messages = MessageBoard()
        self.trace: deque[FrameTrace] = deque(maxlen=trace_frames)
        self.frame = -1
        self.frames_run = 0
        self.now = clock.now() if clock is not None else time.monotonic()
        self.t0 = self.now  #: trace and message times are seconds since the runtime started
        self.last_rid: dict[str, int] = {}
        self.status_changes: list[tuple[int, str, int, int]] = []  #: (frame, layer, old, new)
        self.on_frame: list[Callable[[FrameTrace], None]] = []
        self._request_seq = 0
        self._goal_seq = 0
        self._changed: set[str] = set()
        self._build_schedule()
        if forward_messages:
            self.messages.listeners.append(self._forward)
        self.post("runtime", Level.INFO, f"controller ready: {self.frames.frame_rate_hz:g} Hz minor frames, "
                                         f"profile {self.frames.profile_name}, world model "
                                         f"{wm_name or '(private)'}")

    # --- set-up ----------------------------------------------------------------------------
    def _build_schedule(self) -> None:
        impl: dict[str, Callable] = {}
        for l in self.layers:
            impl.update(l.periodic)
        problems = [f"task {t.name} has no implementation in layer {t.layer}"
                    for t in self.frames.tasks if t.name not in impl]
        problems += [f"task {n} of a layer is not in the schedule" for n in impl
                     if n not in {t.name for t in self.frames.tasks}]
        if problems:
            raise ScheduleError("controller schedule: " + "; ".join(problems))
        self._table = tuple(tuple((t.name, impl[t.name]) for t in frame) for frame in self.frames.table())

    def task_period_s(self, name: str) -> float:
        for t in self.frames.tasks:
            if t.name == name:
                return self.frames.divider(t) * self.frames.period_s
        raise KeyError(name)

    # --- messages ----------------------------------------------------------------------------
    def post(self, source: str, level: Level | int, text: str) -> Message:
        return self.messages.post(source, level, text, self.now - self.t0, self.frame)

    def _forward(self, m: Message) -> None:
        if m.level >= Level.WARNING and getattr(self.client, "role", None) == "controller":
            try:
                self.client.post_message(f"{m.source}: {m.text}"[:56],
                                         Severity.ERROR if m.level >= Level.ERROR else Severity.WARNING)
            except Exception:  # noqa: BLE001 - messages never stop the controller
                pass

    def on_status_change(self, layer: Layer, old: int, new: int) -> None:
        self.status_changes.append((self.frame, layer.key, old, new))
        self._changed.add(layer.key)
        if layer is self.updown:
            self.wm.powered_up = new != Status.SHUT_DOWN  # protected variables locked until down again

    # --- the minor frame ---------------------------------------------------------------------
    def step(self) -> FrameTrace:
        """Run one minor frame (also the single step while halted)."""
        t0 = time.perf_counter()
        self.now = self.clock.now() if self.clock is not None else time.monotonic()
        self._changed.clear()
        self.frame = self.daq.acquire(self)
        self.wm.communications_segment()
        for l in self.layers:
            l.run_table(self)
        daq_status = self._decided(self.daq)
        self.daq.output(self, daq_status)
        for l in self.layers:
            l.run_sequence(self)
        ran = []
        for name, fn in self._table[self.frame % MINOR_FRAMES_PER_MAJOR]:
            try:
                fn(self)
            except Exception as err:  # noqa: BLE001 - a task error is its layer's fault
                layer = next(l for l in self.layers if name in l.periodic)
                layer.set_fault(self, 90, f"task {name} raised {type(err).__name__}: {err}")
            ran.append(name)
        self.frames_run += 1
        rec = FrameTrace(self.frame, self.now - self.t0, tuple(
            LayerTrace(l.last[0], self._decided(l), l.last[5], int(l.task_kind) * 10 + int(l.task_state),
                       l.key in self._changed) for l in self.layers),
            self.daq.fault_bits, tuple(ran), time.perf_counter() - t0)
        self.trace.append(rec)
        for fn in self.on_frame:
            fn(rec)
        return rec

    @staticmethod
    def _decided(layer: Layer) -> int:
        """The status the layer's table decided this frame (posted, visible next frame)."""
        return layer.decided

    # --- user requests (asynchronous, request/response) -------------------------------------
    def request(self, kind: int) -> int:
        """Post a user request to System Up/Down (``Request.POWER_UP`` ...); returns its
        number. The answer appears in ``ui.response`` / ``ui.response_seq``."""
        self._request_seq = max(self._request_seq, int(self.wm.get("ui.request_seq"))) + 1
        self.wm.set_user("ui.request", int(kind), self._key)
        self.wm.set_user("ui.request_seq", self._request_seq, self._key)
        return self._request_seq

    def response(self) -> tuple[int, int]:
        """(request number answered, Response code)."""
        v = self.wm.get_task_inputs(("ui.response_seq", "ui.response"))
        return int(v["ui.response_seq"]), int(v["ui.response"])

    def set_joint_goal(self, q_rad: Sequence[float]) -> int:
        """Command joint positions (command-area order) through the Joint Planner."""
        self._goal_seq = max(self._goal_seq, int(self.wm.get("joint.goal_seq"))) + 1
        self.wm.set_user("joint.goal_rad", np.asarray(q_rad, dtype=float), self._key)
        self.wm.set_user("joint.goal_seq", self._goal_seq, self._key)
        return self._goal_seq

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
