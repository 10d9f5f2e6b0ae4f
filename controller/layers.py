"""The seven IRSS layers: a decision table, sequence tasks and periodic tasks each.

IRSS report 2.2.1 lists the layers, highest first: System Up/Down, Multi-Segment Path
Planner, Trajectory Path Planner, Cartesian Engine, Joint Planner, Servo Control, Data
Acquisition. Every layer here has

* world-model state variables ``<key>.command`` (written by the layer above; for
  System Up/Down by its request task), ``<key>.status`` (written by the layer),
  ``<key>.row`` (the table row that decided last), ``<key>.task`` (its sequence-task
  mailbox) and ``<key>.error`` (error report code);
* a decision table (:mod:`controller.decision`) run once per minor frame right after
  the communications segment: it reads only its command, its own status and the status
  of the layer below, checks the subordinate for errors, and posts its status and the
  command to the layer below;
* **sequence tasks** the table creates - init, start-up, shut-down, safe (error) and
  error-reset - each run once per minor frame until it reports DONE or FAILED in the
  layer's mailbox, which the table reads in the next frame;
* **periodic tasks** run by the scheduling table (:mod:`controller.frames`) while they
  exist: the layer's own decision table (:mod:`controller.tables`) creates and deletes
  them (a task runs only in the statuses its table gives it, from the minor frame after
  the row that created it; :meth:`Layer.task_deleted` is what a layer does when one of
  its tasks is deleted).

The layers above the Joint Planner are in their own modules (:mod:`controller.cartesian`,
:mod:`controller.trajectory`, :mod:`controller.paths`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Callable

import numpy as np

from controller.decision import (
    LAYER_STATUSES, Action, Command, CompiledTable, KEEP, Status, TaskState, compile_table, command_text, status_text,
)
from controller.tables import table_for
from controller.messages import Level
from controller.params import (
    JOINTS, N_JOINTS, SHOULDER_ROLL_STEPS_DEG, check_shoulder_roll_deg, shoulder_roll_text,
)
from controller.quat import q_angle
from controller.relays import at
from controller.worldmodel import VarSpec
from controller.worldmodel.var import UNIT_QUATERNION, Var, VarGroup, var
from controller.routes import camera_name, decode_matrix_route, parse_route_request, route_text
from controller.variables import CART, DAQ

if TYPE_CHECKING:  # pragma: no cover
    from controller.context import LayerContext

#: user requests to System Up/Down (``ui.request``), report 2.2.8 request/response protocol;
#: what each kind does is its row of :data:`REQUEST_KINDS`
class Request:
    NONE = 0
    POWER_UP = 1
    POWER_DOWN = 2
    ERROR_RESET = 3
    #: the debug window's frame control (report 2.2.8, docs/console.md): acted on by the
    #: runtime between frames, answered by System Up/Down like the others; the argument
    #: is STEP's frame count and RESUME's re-arm (1 = re-arm the outputs)
    HALT = 4
    STEP = 5
    RESUME = 6
    #: camera routing (docs/cameras.md): the argument = monitor * 16 + camera (0 = blank);
    #: System Up/Down hands it to Data Acquisition, the one writer of ``commands.matrix_route``
    ROUTE = 7
    #: kind -> name, and the frame-control kinds: filled from REQUEST_KINDS
    NAMES: dict[int, str] = {}
    DEBUG: tuple[int, ...] = ()


class Response:
    NONE = 0
    IN_PROGRESS = 1
    COMPLETE = 2
    REFUSED = 3
    FAILED = 4
    #: waiting its turn in System Up/Down's queue (halted: until a frame runs)
    QUEUED = 5
    #: taken out of the queue unrun: a later HALT or POWER DOWN, or the system's ERROR,
    #: came first (or a POWER DOWN superseded a POWER UP in progress); never run later
    CANCELLED = 6
    NAMES = {0: "NONE", 1: "IN PROGRESS", 2: "COMPLETE", 3: "REFUSED", 4: "FAILED", 5: "QUEUED", 6: "CANCELLED"}
    #: the final answers (a request gets exactly one; QUEUED and IN PROGRESS come before it)
    FINAL = (2, 3, 4, 6)


#: how a request kind is taken: by the runtime's frame control, on arrival (halted or not)
FRAME = "frame"


@dataclass(frozen=True)
class RequestKind:
    """One kind of user request: a row of :data:`REQUEST_KINDS`.

    :param take: :data:`FRAME` (the runtime's frame control acts on it on arrival, between
        frames, halted or not), or the :class:`UpDownLayer` method that takes it from the
        queue in order, ``(rt, seq, arg, status) -> bool``, in the request task (in frames
        that run: while halted, single steps); it answers the request and returns True, or
        returns False to leave it at the head of the queue until a later frame
    :param follow: the :class:`UpDownLayer` method ``(rt, status)`` that follows it once
        taken, every frame, until it answers; such a request is *the active one* and the
        system's sequence: one at a time
    :param waits: at the head of the queue it waits while an active request is followed
    :param cancels: on arrival every request queued before it is answered CANCELLED
    :param arg: what its argument means ("" none)
    """

    code: int
    name: str
    take: str
    follow: str = ""
    waits: bool = False
    cancels: bool = False
    arg: str = ""


#: every request kind System Up/Down takes (docs/controller.md "User requests"). A new kind
#: is one row here (its constant in :class:`Request`, its take/follow methods in UpDownLayer)
REQUEST_KINDS: dict[int, RequestKind] = {k.code: k for k in (
    RequestKind(Request.POWER_UP, "POWER UP", "_take_power_up", "_follow_power_up", waits=True),
    RequestKind(Request.POWER_DOWN, "POWER DOWN", "_take_power_down", "_follow_to_shut_down", cancels=True),
    RequestKind(Request.ERROR_RESET, "ERROR RESET", "_take_error_reset", "_follow_to_shut_down", waits=True),
    RequestKind(Request.HALT, "HALT", FRAME, cancels=True),
    RequestKind(Request.STEP, "SINGLE STEP", FRAME, arg="frames to run (0: 1)"),
    RequestKind(Request.RESUME, "RESUME", FRAME, arg="1: re-arm the outputs (required)"),
    RequestKind(Request.ROUTE, "CAMERA ROUTE", "_take_route", arg="monitor * 16 + camera (0 = blank)"),
)}
Request.NAMES = {Request.NONE: "NONE", **{c: k.name for c, k in REQUEST_KINDS.items()}}
Request.DEBUG = tuple(c for c, k in REQUEST_KINDS.items() if k.take == FRAME)

#: requests waiting in System Up/Down's queue at most; one more is REFUSED "queue full"
#: (assumed: an operator queues a few requests ahead, e.g. POWER UP and a route while halted)
QUEUE_SLOTS = 8
#: answers kept in the world model's answer log (``ui.answer_*``), so that each request's
#: answer is found by its number even when others were answered since (assumed: a client
#: polls every few ms; 16 answers is several frames of answers even with cancellations)
ANSWER_SLOTS = 16
#: bytes of ``ui.response_text`` (the answer in words)
RESPONSE_TEXT_BYTES = 160
_KINDS = " ".join(f"{c} {k.name}" for c, k in REQUEST_KINDS.items())
_ARGS = "; ".join(f"{k.name}: {k.arg}" for k in REQUEST_KINDS.values() if k.arg)


class UiVars(VarGroup, prefix="ui", writer="updown_requests"):
    """System Up/Down's request/response variables (:class:`UpDownLayer`): the user's
    requests, the queue, the answers and the answer log; with the CAMERA ROUTE request it
    hands Data Acquisition (``updown.route_request*``)."""

    request: Var[np.ndarray] = var(
        "command_input", "i4", (2,), [0, 0], writer="user",
        doc=f"a user request to System Up/Down: (kind, argument); each write is one request, "
            f"its number the write's request id. Kinds: {_KINDS}. Arguments: {_ARGS}")
    request_seq: Var[int] = var("status_output", "i4", (), 0,
                                doc="the newest request System Up/Down received (its number)")
    queue: Var[np.ndarray] = var(
        "status_output", "i4", (QUEUE_SLOTS, 3), [[0, 0, 0]] * QUEUE_SLOTS,
        doc="the requests waiting in System Up/Down's queue, oldest first: (number, kind, "
            "argument) rows, 0 after the last")
    active: Var[np.ndarray] = var(
        "status_output", "i4", (2,), [0, 0],
        doc="the request in progress (POWER UP, POWER DOWN, ERROR RESET): (number, kind); 0 none")
    route_request: Var[int] = var(
        "task_io", "i4", (), 0, name="updown.route_request",
        doc="the newest CAMERA ROUTE request for Data Acquisition: monitor * 16 + camera")
    route_request_seq: Var[int] = var(
        "task_io", "i4", (), 0, name="updown.route_request_seq",
        doc="its request number (Data Acquisition applies it when this changes)")
    response_text: Var[np.ndarray] = var("response_output", "u1", (RESPONSE_TEXT_BYTES,), [0] * RESPONSE_TEXT_BYTES,
                                         doc="the answer in words (UTF-8, zero-padded)")
    response: Var[int] = var("response_output", "i2", (), 0,
                             doc="answer to the request ui.response_seq (the newest request answered)",
                             enum=Response.NAMES)
    response_seq: Var[int] = var("response_output", "i4", (), 0, doc="the request number ui.response answers")
    answer_count: Var[int] = var(
        "response_output", "i8", (), 0,
        doc=f"answers given so far; the answer log's newest entry is slot (count - 1) % {ANSWER_SLOTS}")
    answer_seq: Var[np.ndarray] = var("response_output", "i4", (ANSWER_SLOTS,), [0] * ANSWER_SLOTS,
                                      doc="answer log: the request number each entry answers")
    answer_code: Var[np.ndarray] = var("response_output", "i2", (ANSWER_SLOTS,), [0] * ANSWER_SLOTS,
                                       doc="answer log: each entry's answer (as ui.response)")
    answer_text: Var[np.ndarray] = var(
        "response_output", "u1", (ANSWER_SLOTS, RESPONSE_TEXT_BYTES), [[0] * RESPONSE_TEXT_BYTES] * ANSWER_SLOTS,
        doc="answer log: each entry's answer in words (UTF-8, zero-padded)")


UI = UiVars
#: what a client reads of the answer log, the active request and the queue (:func:`find_answer`)
ANSWER_VARS = (UI.answer_count, UI.answer_seq, UI.answer_code, UI.answer_text, UI.active, UI.queue)


def find_answer(wm, seq: int) -> tuple[int, str] | None:
    """The newest answer to request ``seq`` in world model ``wm``: its newest entry in the
    answer log, else (its entry already overwritten by ANSWER_SLOTS later answers) IN
    PROGRESS while it is the active request or QUEUED while it waits in the queue; None
    when it has none (not received yet, or finished more than ANSWER_SLOTS answers ago).
    Returns (Response code, text)."""
    v = wm.get_task_inputs(ANSWER_VARS)
    n, seqs = int(v[UI.answer_count]), v[UI.answer_seq]
    for j in range(n - 1, max(n - ANSWER_SLOTS, 0) - 1, -1):  # newest first
        k = j % ANSWER_SLOTS
        if int(seqs[k]) == seq:
            return int(v[UI.answer_code][k]), bytes(v[UI.answer_text][k]).rstrip(b"\0").decode(errors="replace")
    active, kind = (int(x) for x in v[UI.active])
    if seq and active == seq:
        return Response.IN_PROGRESS, f"{Request.NAMES.get(kind, kind)}: in progress"
    for i, (q, kind, _arg) in enumerate(v[UI.queue]):
        if seq and int(q) == seq:
            return Response.QUEUED, f"{Request.NAMES.get(int(kind), kind)}: queued ({i} ahead)"
    return None


_NO_SUBORDINATE = int(Status.NO_SUBORDINATE)
#: time a CAMERA ROUTE request waits for the service to report the route applied before its
#: answer is FAILED (assumed: the service writes the route at its 40 Hz PIO rate, 25 ms; ten of those)
ROUTE_TIMEOUT_S = 0.25

SEQ_ACTIONS = {Action.INIT: "init", Action.STARTUP: "startup", Action.SHUTDOWN: "shutdown",
               Action.SAFE: "safe", Action.RESET: "reset"}
#: ``<key>.task``, the sequence-task mailbox, by name: 10 x kind + state (0 IDLE)
TASK_NAMES = {int(k) * 10 + int(t): ("IDLE" if k == Action.NONE and t == TaskState.IDLE else
                                      f"{SEQ_ACTIONS.get(k, k.name.lower()).upper()} {t.name}")
              for k in Action if k != Action.CLEAR for t in TaskState}
#: error report codes any layer may post in ``<key>.error`` (docs/controller.md): a task of
#: the layer raised; a neighbour's process is lost, or this process stops while the system
#: is up (controller.distributed). Each layer adds its own (``Layer.error_names``).
#: A task that posts a value outside its variable's type or valid range (report 2.2.2 rule 4)
#: has its post refused (the variable keeps its last valid value) and its layer in ERROR.
ERR_TASK_RAISED, ERR_SECTION_LOST, ERR_PROCESS_STOPPING, ERR_INVALID_VALUE = 90, 91, 92, 93
ERROR_NAMES = {0: "none", ERR_TASK_RAISED: "a task raised", ERR_SECTION_LOST: "neighbour process lost",
               ERR_PROCESS_STOPPING: "this process stopping", ERR_INVALID_VALUE: "a task posted an invalid value"}


class Layer:
    """One layer. Subclasses add variables, sequence-task bodies and periodic tasks.

    :param key: short name used in variable names and traces (``servo``)
    :param title: the report's name (``Servo Control``)
    """

    key = "layer"
    title = "Layer"
    #: the codes this layer posts in ``<key>.error``, by name (the variable's enumeration:
    #: any other code is refused when posted)
    error_names: dict[int, str] = ERROR_NAMES
    short = "LAYR"  #: four letters for the trace
    #: the variables of other layers this layer's table and tasks read (its own need no
    #: entry): checked against the neighbours rule when the runtime is wired, and the world
    #: model refuses any read the layer did not declare (controller/neighbours.py)
    reads: tuple[str, ...] = ()
    #: the variables this layer passes on to a layer further away, and (its copy, what it
    #: copies) of each: set by ``controller.relays.wire``
    relay_specs: tuple[VarSpec, ...] = ()
    relay_pairs: tuple[tuple[str, str], ...] = ()

    def __init__(self) -> None:
        self.superior: Layer | None = None
        self.subordinate: Layer | None = None
        self.table: CompiledTable = compile_table(table_for(self.key))
        #: the periodic tasks that exist (run when due), and those the table's last
        #: decision leaves existing from the next minor frame
        self.running: frozenset[str] = self.table.table.running_in(Status.SHUT_DOWN)
        self._next_running = self.running
        # mailbox (local to the layer, IRSS task mail boxes)
        self.task_kind = Action.NONE
        self.task_state = TaskState.IDLE
        self.task_t0 = 0.0
        self.task_frames = 0
        self.fault = False
        self.fault_text = ""
        self.error_code = 0
        # what the table read and decided this frame (for the trace)
        self.last = (0, 0, 0, 0, False, 0)  # command, status, sub, task, fault, rid
        self.decided = int(Status.SHUT_DOWN)  # the status the table decided last
        self.periodic: dict[str, Callable[["LayerContext"], None]] = {}
        # the state variables' names, built once (the table reads them every minor frame)
        self._v_command, self._v_status = f"{self.key}.command", f"{self.key}.status"
        self._v_row, self._v_task = f"{self.key}.row", f"{self.key}.task"

    # --- names ---------------------------------------------------------------------------
    @property
    def v_command(self) -> str:
        return self._v_command

    @property
    def v_status(self) -> str:
        return self._v_status

    def command_writer(self) -> str:
        """Who writes this layer's command: the layer above."""
        return self.superior.key if self.superior is not None else "updown_requests"

    def state_specs(self) -> list[VarSpec]:
        """The layer's state variables (commands, status, row, mailbox, error report)."""
        k = self.key
        return [
            VarSpec(f"{k}.command", "command_input", "i2", (), self.command_writer(), 0,
                    doc=f"command to {self.title} (controller.decision.Command)", enum=Command),
            VarSpec(f"{k}.status", "status_output", "i2", (), k, int(Status.SHUT_DOWN),
                    doc=f"{self.title} status (controller.decision.Status)", enum=LAYER_STATUSES),
            VarSpec(f"{k}.row", "task_status", "i2", (), k, 0,
                    doc=f"the {self.title} decision-table row that decided last"),
            VarSpec(f"{k}.task", "task_status", "i2", (), k, 0,
                    doc="sequence-task mailbox: 10 x kind (1 init 2 startup 3 shutdown 4 safe 5 reset) "
                        "+ state (0 idle 1 running 2 done 3 failed)", enum=TASK_NAMES),
            VarSpec(f"{k}.error", "error_reports", "i4", (), k, 0,
                    doc=f"{self.title} error report code (0 none; see docs/controller.md)",
                    enum=self.error_names),
        ]

    def specs(self) -> list[VarSpec]:
        """Every variable this layer owns or is the declared writer of (override to add)."""
        return self.state_specs()

    def all_specs(self) -> list[VarSpec]:
        """:meth:`specs` and the copies of what it passes on (``relay_specs``)."""
        return [*self.specs(), *self.relay_specs]

    # --- decision table ------------------------------------------------------------------
    def run_table(self, rt: "LayerContext") -> None:
        """Read command, own status and the subordinate's status; decide; post."""
        wm = rt.wm
        if self._next_running is not self.running:  # the tasks the last decision created or deleted
            self._apply_tasks(rt)
        get = wm.get_state_variable
        sub = self.subordinate
        c = get(self._v_command)
        s = get(self._v_status)
        b = get(sub._v_status) if sub is not None else _NO_SUBORDINATE
        t = int(self.task_state)
        f = self.fault
        out = self.table.decide(c, s, b, t, f)
        self.last = (c, s, b, t, f, out.rid)
        self.decided = int(out.next_status)
        if out.next_status != s:
            wm.post_state_variable(self.key, self._v_status, int(out.next_status))
            lvl = Level.ERROR if out.next_status == Status.ERROR else Level.INFO
            why = out.note
            if out.next_status == Status.ERROR and f and self.fault_text:
                why = f"{why}: {self.fault_text}"
            elif out.next_status == Status.ERROR and out.rid == 1 and self.subordinate is not None:
                why = f"{why} ({self.subordinate.title})"
            rt.post(self.key, lvl, f"{status_text(s)} -> {status_text(out.next_status)} "
                                   f"(row {out.rid}: {why})")
            rt.on_status_change(self, s, int(out.next_status))
        if out.command_down != KEEP and self.subordinate is not None:
            cur = wm.get_state_variable(self.subordinate.v_command)
            if cur != out.command_down:
                wm.post_state_variable(self.key, self.subordinate.v_command, out.command_down)
                rt.post(self.key, Level.DEBUG, f"command {self.subordinate.title}: "
                                               f"{command_text(out.command_down)}")
        if out.rid != rt.last_rid.get(self.key):
            wm.post_state_variable(self.key, self._v_row, out.rid)
            rt.last_rid[self.key] = out.rid
        if out.action != Action.NONE:
            self._act(rt, out.action)
        if out.create or out.delete:
            self._next_running = (self._next_running | out.create) - out.delete

    def _apply_tasks(self, rt: "LayerContext") -> None:
        """The periodic tasks the table's last decision created and deleted exist (or not)
        from this minor frame on."""
        gone = self.running - self._next_running
        new = self._next_running - self.running
        self.running = self._next_running
        for name in sorted(new):
            rt.post(self.key, Level.DEBUG, f"task {name} created")
        for name in sorted(gone):
            rt.post(self.key, Level.DEBUG, f"task {name} deleted")
            self.task_deleted(rt, name)

    def task_deleted(self, rt: "LayerContext", name: str) -> None:
        """One of this layer's periodic tasks was deleted by its table (override: what the
        task leaves behind, e.g. a segment in progress)."""

    def _act(self, rt: "LayerContext", action: Action) -> None:
        if action == Action.CLEAR:
            self.task_kind, self.task_state = Action.NONE, TaskState.IDLE
        else:
            self.task_kind, self.task_state = action, TaskState.RUNNING
            self.task_t0 = rt.now
            self.task_frames = 0
            rt.post(self.key, Level.DEBUG, f"{SEQ_ACTIONS[action]} task scheduled")
        self._post_mailbox(rt)

    def _post_mailbox(self, rt: "LayerContext") -> None:
        rt.wm.post_state_variable(self.key, self._v_task, int(self.task_kind) * 10 + int(self.task_state))

    # --- sequence tasks ------------------------------------------------------------------
    def run_sequence(self, rt: "LayerContext") -> None:
        """Run the current sequence task once, if it is running."""
        if self.task_state != TaskState.RUNNING:
            return
        body = getattr(self, "seq_" + SEQ_ACTIONS[self.task_kind])
        try:
            state = body(rt)
        except Exception as err:  # noqa: BLE001 - a task failure is a layer error, never a crash
            rt.post(self.key, Level.ERROR, f"{SEQ_ACTIONS[self.task_kind]} task raised "
                                           f"{type(err).__name__}: {err}")
            state = TaskState.FAILED
        self.task_frames += 1
        if state != TaskState.RUNNING:
            self.task_state = TaskState(state)
            self._post_mailbox(rt)
            if state == TaskState.FAILED:
                rt.post(self.key, Level.ERROR, f"{SEQ_ACTIONS[self.task_kind]} task FAILED")

    def set_fault(self, rt: "LayerContext", code: int, text: str) -> None:
        """Raise this layer's fault flag (read by its table next frame) and report it."""
        if not self.fault or code != self.error_code:
            rt.post(self.key, Level.ERROR, f"fault {code}: {text}")
            rt.wm.post_task_outputs(self.key, {f"{self.key}.error": code})
        self.fault, self.fault_text, self.error_code = True, text, code

    def clear_fault(self, rt: "LayerContext") -> None:
        if self.fault or self.error_code:
            rt.wm.post_task_outputs(self.key, {f"{self.key}.error": 0})
        self.fault, self.fault_text, self.error_code = False, "", 0

    def seq_init(self, rt: "LayerContext") -> TaskState:
        return TaskState.DONE

    def seq_startup(self, rt: "LayerContext") -> TaskState:
        return TaskState.DONE

    def seq_shutdown(self, rt: "LayerContext") -> TaskState:
        return TaskState.DONE

    def seq_safe(self, rt: "LayerContext") -> TaskState:
        return self.seq_shutdown(rt)

    def seq_reset(self, rt: "LayerContext") -> TaskState:
        self.clear_fault(rt)
        return TaskState.DONE

    def status(self, rt: "LayerContext") -> Status:
        return Status(rt.wm.get_state_variable(self.v_status))


class UpDownLayer(Layer):
    """System Up/Down: master control; user requests arrive here (request/response).

    A request is one keyed user write of ``ui.request`` = (kind, argument); the world
    model's user-request ring carries it, and its request id there is the request's number
    (``ControllerRuntime.request``, ``ControllerLink.submit``). The world model keeps every
    such write in order (:meth:`WorldModel.keep_user_writes`), so two requests applied in
    one communications segment are two requests, never the last one alone.

    Every tick, halted or not, :meth:`receive_requests` takes the new ones in order: a
    frame-control request (HALT, SINGLE STEP, RESUME) goes to the runtime at once; the
    others join the queue (at most QUEUE_SLOTS; one more is REFUSED). A request whose kind
    ``cancels`` (HALT, POWER DOWN) first answers CANCELLED every request queued before it,
    and so does the system's ERROR (its table deciding ERROR). The request task
    (``updown_requests``, every minor frame: while halted only in single-stepped frames) is
    the report's "real time task running in the system up/down layer": it follows the
    active request (POWER UP: INIT TO START, then START UP once INITIALIZATION COMPLETE;
    POWER DOWN and ERROR RESET: until SHUT DOWN) and takes queued requests in order (the
    table :data:`REQUEST_KINDS` says how). Each request is answered with its number in the
    answer log ``ui.answer_*`` (QUEUED and IN PROGRESS first if it waits, then exactly one
    final answer); ``ui.response`` / ``ui.response_seq`` / ``ui.response_text`` keep the
    answer to the newest request answered.
    """

    key = "updown"
    title = "System Up/Down"
    short = "UPDN"
    #: other layers' variables read (controller/neighbours.py; the far ones are listed there)
    reads = (
        "daq.camera_route_applied", "joint.shoulder_roll_deg",
    )

    def __init__(self) -> None:
        super().__init__()
        self._answered_seq = 0  # newest request answered in ui.response
        self._received_seq = 0  # newest request received (ui.request_seq)
        self._queue: deque[tuple[int, int, int]] = deque()  # (seq, kind, arg) waiting, oldest first
        self._active = Request.NONE  # the request being followed (a kind with a follow method)
        self._active_seq = 0
        self._cmd = Command.NONE
        self._route: tuple[int, int, int, float] | None = None  # (seq, monitor, camera, t0) being followed
        self._in_error = False  # the table decided ERROR last frame
        # the answer log (preallocated; posted whole when an answer is added)
        self._ans_count = 0
        self._ans_seq = np.zeros(ANSWER_SLOTS, dtype=np.int32)
        self._ans_code = np.zeros(ANSWER_SLOTS, dtype=np.int16)
        self._ans_text = np.zeros((ANSWER_SLOTS, RESPONSE_TEXT_BYTES), dtype=np.uint8)
        self._queue_rows = np.zeros((QUEUE_SLOTS, 3), dtype=np.int32)
        self.periodic["updown_requests"] = self.requests_task

    def specs(self) -> list[VarSpec]:
        return self.state_specs() + UI.specs()

    # --- answers -------------------------------------------------------------------------
    def _respond(self, rt, seq: int, code: int, text: str) -> None:
        lvl = Level.WARNING if code in (Response.REFUSED, Response.FAILED) else Level.INFO
        raw = text.encode()[:RESPONSE_TEXT_BYTES]
        k = self._ans_count % ANSWER_SLOTS
        self._ans_count += 1
        self._ans_seq[k], self._ans_code[k] = seq, code
        self._ans_text[k, :] = 0
        self._ans_text[k, :len(raw)] = np.frombuffer(raw, dtype=np.uint8)
        out: dict = {UI.answer_count: self._ans_count, UI.answer_seq: self._ans_seq,
                     UI.answer_code: self._ans_code, UI.answer_text: self._ans_text}
        if seq >= self._answered_seq:  # ui.response keeps the newest request's answer
            self._answered_seq = seq
            out.update({UI.response: code, UI.response_seq: seq, UI.response_text: self._ans_text[k]})
        rt.wm.post_task_outputs("updown_requests", out)
        rt.post(self.key, lvl, f"request {seq}: {text} -> {Response.NAMES[code]}")

    def _roll_note(self, rt) -> str:
        """What POWER UP's first answer says of the shoulder-roll index (no sensor: the
        operator's parameter, shown so that it is confirmed; docs/controller.md)."""
        if JOINT.shoulder_roll_deg not in rt.wm.names():
            return ""
        deg = float(rt.wm.get(JOINT.shoulder_roll_deg))
        return f" (shoulder-roll index {shoulder_roll_text(deg)}: no sensor, as set in joint.shoulder_roll_deg)"

    def answer(self, rt, seq: int, code: int, text: str) -> None:
        """A later answer to request ``seq`` (a step run finished, a re-arm armed or not)."""
        self._respond(rt, seq, code, text)

    def _command(self, rt, cmd: Command) -> None:
        if cmd != self._cmd:
            self._cmd = cmd
            rt.wm.post_task_outputs("updown_requests", {"updown.command": int(cmd)})

    # --- arrival (every tick, halted or not) -----------------------------------------------
    def receive_requests(self, rt) -> None:
        """The requests applied since the last tick, in order: frame control to the runtime
        (``rt.debug_request``) and answered here; the others queued. Called by the runtime
        after each tick's first communications segment, halted or not."""
        new = rt.wm.take_user_writes()
        if not new:
            return
        for seq, _name, value in new:
            kind, arg = int(value[0]), int(value[1])
            self._received_seq = seq
            k = REQUEST_KINDS.get(kind)
            if k is None:
                self._respond(rt, seq, Response.REFUSED, f"unknown request {kind} (kinds: "
                                                         f"{', '.join(f'{c} {n.name}' for c, n in REQUEST_KINDS.items())})")
                continue
            if k.take == FRAME:
                code, text = rt.debug_request(kind, arg, seq)
                if k.cancels and code != Response.REFUSED:
                    self._cancel_queued(rt, f"{k.name} (request {seq}) came after it")
                self._respond(rt, seq, code, f"{k.name}: {text}")
                continue
            if k.cancels:
                self._cancel_queued(rt, f"{k.name} (request {seq}) came after it")
            if len(self._queue) >= QUEUE_SLOTS:
                waiting = ", ".join(f"{Request.NAMES.get(q[1], q[1])} {q[0]}" for q in self._queue)
                self._respond(rt, seq, Response.REFUSED, f"{k.name}: request queue full ({QUEUE_SLOTS} waiting: "
                                                         f"{waiting})")
            else:
                self._queue.append((seq, kind, arg))
                why = [f"{len(self._queue) - 1} ahead"] if len(self._queue) > 1 else []
                if k.waits and self._active != Request.NONE:
                    why.append(f"{Request.NAMES[self._active]} {self._active_seq} in progress")
                if rt.halted:
                    why.append("halted: taken at the next frame run, a step or the resume")
                if why:  # else the request task takes it in this frame: no need to say it waits
                    self._respond(rt, seq, Response.QUEUED, f"{k.name}: queued ({'; '.join(why)})")
        rt.wm.post_task_outputs("updown_requests", {UI.request_seq: self._received_seq})
        self._post_queue(rt)

    def _cancel_queued(self, rt, why: str) -> None:
        while self._queue:
            seq, kind, _arg = self._queue.popleft()
            self._respond(rt, seq, Response.CANCELLED, f"{Request.NAMES[kind]}: cancelled, never run: {why}")
        self._post_queue(rt)

    def _post_queue(self, rt) -> None:
        rows = self._queue_rows
        rows[:] = 0
        for i, item in enumerate(self._queue):
            rows[i] = item
        rt.wm.post_task_outputs("updown_requests", {UI.queue: rows})

    def queued(self) -> tuple[tuple[int, int, int], ...]:
        """The requests waiting, oldest first: (number, kind, argument)."""
        return tuple(self._queue)

    # --- the decision table: the system's ERROR cancels the queue ---------------------------
    def run_table(self, rt: "LayerContext") -> None:
        super().run_table(rt)
        err = self.decided == Status.ERROR
        if err and not self._in_error and self._queue:
            self._cancel_queued(rt, "System Up/Down entered ERROR")
        self._in_error = err

    # --- the request task (every minor frame that runs) --------------------------------------
    def requests_task(self, rt: "LayerContext") -> None:
        if self._active == Request.NONE and not self._queue and self._route is None:
            return  # nothing to follow or take (the frame's common case: nothing read)
        st = Status(rt.wm.get_state_variable("updown.status"))
        if self._route is not None:
            self._follow_route(rt)
        if self._active != Request.NONE:
            a = REQUEST_KINDS[self._active]
            if st == Status.ERROR and self._active != Request.ERROR_RESET:
                self._finish(rt, Response.FAILED, f"{a.name}: System Up/Down in ERROR")
            else:
                getattr(self, a.follow)(rt, st)
        changed = False
        while self._queue:
            seq, kind, arg = self._queue[0]
            k = REQUEST_KINDS[kind]
            if k.waits and self._active != Request.NONE:
                break  # its turn comes when the active request is answered
            if not getattr(self, k.take)(rt, seq, arg, st):
                break  # not yet: it stays at the head
            self._queue.popleft()
            changed = True
        if changed:
            self._post_queue(rt)

    def _start(self, rt, kind: int, seq: int, cmd: Command, note: str = "") -> None:
        self._active, self._active_seq = kind, seq
        self._command(rt, cmd)
        rt.wm.post_task_outputs("updown_requests", {UI.active: (seq, kind)})
        self._respond(rt, seq, Response.IN_PROGRESS, Request.NAMES[kind] + note)

    def _finish(self, rt, code: int, text: str) -> None:
        seq, self._active, self._active_seq = self._active_seq, Request.NONE, 0
        rt.wm.post_task_outputs("updown_requests", {UI.active: (0, 0)})
        self._respond(rt, seq, code, text)

    # --- the kinds (REQUEST_KINDS) ------------------------------------------------------------
    def _take_power_up(self, rt, seq: int, arg: int, st: Status) -> bool:
        if st == Status.SHUT_DOWN:
            self._start(rt, Request.POWER_UP, seq, Command.INIT_TO_START, self._roll_note(rt))
        else:
            self._respond(rt, seq, Response.REFUSED, f"POWER UP: system is {status_text(st)}")
        return True

    def _follow_power_up(self, rt, st: Status) -> None:
        if st == Status.INITIALIZATION_COMPLETE:
            self._command(rt, Command.START_UP)
        elif st == Status.START_UP_COMPLETE:
            self._finish(rt, Response.COMPLETE, "POWER UP: START UP COMPLETE")

    def _take_power_down(self, rt, seq: int, arg: int, st: Status) -> bool:
        """Taken at once (it does not wait): it supersedes a POWER UP in progress (answered
        CANCELLED) wherever SHUT DOWN is accepted."""
        name = "POWER DOWN"
        busy = f"{Request.NAMES[self._active]} (request {self._active_seq}) in progress"
        if st in (Status.INITIALIZATION_COMPLETE, Status.START_UP, Status.START_UP_COMPLETE):
            if self._active == Request.POWER_UP:
                self._finish(rt, Response.CANCELLED, f"POWER UP: cancelled at {status_text(st)}: "
                                                     f"POWER DOWN (request {seq}) supersedes it")
            if self._active == Request.NONE:
                self._start(rt, Request.POWER_DOWN, seq, Command.SHUT_DOWN)
            else:
                self._respond(rt, seq, Response.REFUSED, f"{name}: {busy}")
        elif st in (Status.INITIALIZATION_IN_PROGRESS, Status.WAITING_FOR_SUBORDINATE_TO_INIT) or \
                (st == Status.SHUT_DOWN and self._active == Request.POWER_UP):
            self._respond(rt, seq, Response.REFUSED, f"{name}: no SHUT DOWN before INITIALIZATION "
                                                     f"COMPLETE (report 2.2.6)")
        elif self._active != Request.NONE:
            self._respond(rt, seq, Response.REFUSED, f"{name}: {busy}, system {status_text(st)}")
        elif st == Status.SHUT_DOWN:
            self._respond(rt, seq, Response.COMPLETE, f"{name}: already SHUT DOWN")
        else:
            self._respond(rt, seq, Response.REFUSED, f"{name}: system is {status_text(st)}")
        return True

    def _take_error_reset(self, rt, seq: int, arg: int, st: Status) -> bool:
        if st == Status.ERROR:
            self._start(rt, Request.ERROR_RESET, seq, Command.ERROR_RESET)
        else:
            self._respond(rt, seq, Response.REFUSED, f"ERROR RESET: system is {status_text(st)}, not ERROR")
        return True

    def _follow_to_shut_down(self, rt, st: Status) -> None:
        if st == Status.SHUT_DOWN:
            self._finish(rt, Response.COMPLETE, f"{Request.NAMES[self._active]}: SHUT DOWN")

    def _take_route(self, rt, seq: int, arg: int, st: Status) -> bool:
        """A CAMERA ROUTE request: any system state (the cameras are not the arm). Handed to
        Data Acquisition through ``updown.route_request``; answered COMPLETE once the service
        reports the monitor's new source applied, FAILED after ROUTE_TIMEOUT_S. One route at a
        time: the next waits at the head of the queue until this one is answered."""
        if self._route is not None:
            return False
        name = Request.NAMES[Request.ROUTE]
        try:
            monitor, camera = parse_route_request(arg)
        except ValueError as err:
            self._respond(rt, seq, Response.REFUSED, f"{name}: {err}")
            return True
        rt.wm.post_task_outputs("updown_requests", {UI.route_request: arg, UI.route_request_seq: seq})
        self._route = (seq, monitor, camera, rt.now)
        self._respond(rt, seq, Response.IN_PROGRESS, f"{name}: monitor {monitor} <- {camera_name(camera)}")
        return True

    def _follow_route(self, rt) -> None:
        assert self._route is not None
        seq, monitor, camera, t0 = self._route
        name = Request.NAMES[Request.ROUTE]
        applied = int(rt.wm.get(DAQ.camera_route_applied))
        if applied >= 0 and decode_matrix_route(applied)[monitor - 1] == camera:
            self._route = None
            self._respond(rt, seq, Response.COMPLETE, f"{name}: applied by the service: {route_text(applied)}")
        elif rt.now - t0 > ROUTE_TIMEOUT_S:
            self._route = None
            self._respond(rt, seq, Response.FAILED, f"{name}: monitor {monitor} <- {camera_name(camera)} not "
                                                    f"applied by the service within {ROUTE_TIMEOUT_S} s (its "
                                                    f"messages say why)")


#: Joint Planner: a Cartesian command that stays blocked at a soft limit (pose error above
#: these) for STUCK_S with the command unchanged triggers the joint-space recovery (assumed)
STUCK_S = 0.5
STUCK_POS_M = 1e-4
STUCK_ROT_RAD = 1e-3
#: a joint move (``msp.jmove_*``) accelerates to its speed in this time (assumed, this project:
#: as the trajectory caps reach full coarse speed in 1 s, controller.trajectory)
JMOVE_ACCEL_S = 1.0
#: ``joint.jmove_done_code`` (the values of ``traj.done_code``)
JMOVE_REACHED, JMOVE_STOPPED, JMOVE_REFUSED = 0, 1, 2


#: ``joint.mode`` by name (``JointPlannerLayer.MODE_JOINT``, ``MODE_CARTESIAN``)
JOINT_MODE_NAMES = {0: "JOINT GOAL", 1: "CARTESIAN"}
_Z6 = [0.0] * N_JOINTS


#: a joint move's speed: the fraction of each joint's software rate limit (msp.jmove_speed's
#: initial value; the Path Planner scales it by msp.speed_scale)
JMOVE_SPEED = 0.25


class JointMoveVars(VarGroup, prefix="msp", writer="msp"):
    """The joint-move hand-over: posted by the Multi-Segment Path Planner (writer ``msp``),
    read by the Joint Planner (declared here, where it is read)."""

    jmove_seq: Var[int] = var("task_io", "i4", (), 0,
                              doc="joint move number: a new value is a new joint move for the Joint Planner")
    jmove_goal_rad: Var[np.ndarray] = var("task_io", "f8", (6,), [0.0] * 6, "rad",
                                          doc="joint move goal (command-area order; a straight line in joint space)")
    jmove_speed: Var[float] = var("task_io", "f8", (), JMOVE_SPEED, "1", valid=(0.0, 1.0),
                                  doc="joint move speed: fraction of the software rate limits (0..1)")
    jmove_stop: Var[bool] = var("task_io", "b1", (), False, doc="stop: decelerate the running joint move to rest")


JMOVE = JointMoveVars
#: a joint move's request as the Joint Planner reads it: the Cartesian engine's copy (controller/relays.py)
_JM = {n: at("joint", n) for n in JMOVE.all()}


class JointVars(VarGroup, prefix="joint", writer="joint"):
    """The Joint Planner's variables: the user's joint goal, the joint command for Servo
    Control (named ``servo.*``), the measured tool pose, its statuses, the shoulder-roll
    index (its initial value is the layer's parameter: ``JointPlannerLayer.specs``)."""

    goal_rad: Var[np.ndarray] = var(
        "command_input", "f8", (N_JOINTS,), _Z6, "rad", writer="user",
        doc="user joint goal (command-area joint order); acted on when joint.goal_seq changes")
    goal_seq: Var[int] = var("command_input", "i4", (), 0, writer="user",
                             doc="increment to command joint.goal_rad (refused while a Cartesian command is valid)")
    q_cmd_rad: Var[np.ndarray] = var("task_io", "f8", (N_JOINTS,), _Z6, "rad", name="servo.q_cmd_rad",
                                     doc="commanded joint positions for Servo Control")
    q_cmd_valid: Var[bool] = var("task_io", "b1", (), False, name="servo.q_cmd_valid",
                                 doc="servo.q_cmd_rad is a command (else the servo holds where it started)")
    tool_pos_m: Var[np.ndarray] = var("task_io", "f8", (3,), [0.0] * 3, "m",
                                      doc="measured tool point, world: fk(daq.joint_angle_rad), every 80 Hz run")
    tool_quat: Var[np.ndarray] = var("task_io", "f8", (4,), [0.0] * 4, "1", valid=UNIT_QUATERNION,
                                     doc="measured tool orientation (w x y z), world; all zero until first computed")
    singular: Var[bool] = var("task_status", "b1", (), False,
                              doc="the joint command is near a singular set (wrist yaw +-90, full stretch, "
                                  "wrist centre on the shoulder-yaw axis) or the step was damped")
    limited: Var[bool] = var("task_status", "b1", (), False,
                             doc="a joint is held at a soft limit (Cartesian mode) or a goal was clipped")
    mode: Var[int] = var("task_status", "i2", (), 0,
                         doc="what the Joint Planner follows: the joint goal, or the Cartesian command "
                             "(cart.cmd_valid)", enum=JOINT_MODE_NAMES)
    cart_err_m: Var[float] = var(
        "task_status", "f8", (), 0.0, "m",
        doc="Cartesian mode: tool-point distance from the commanded pose to fk(servo.q_cmd_rad)")
    cart_err_rad: Var[float] = var(
        "task_status", "f8", (), 0.0, "rad",
        doc="Cartesian mode: orientation angle from the commanded pose to fk(servo.q_cmd_rad)")
    shoulder_roll_deg: Var[float] = var(
        "control_flags", "f8", (), 0.0, "deg", writer="user", choices=SHOULDER_ROLL_STEPS_DEG,
        doc="the shoulder roll's index position, set by hand on the arm (no sensor): -90 -45 0 45 90 "
            "(pfma-model 8.1); set it where the joint is pinned, while powered down; power-up takes it")
    shoulder_roll_rad: Var[float] = var(
        "status_output", "f8", (), 0.0, "rad",
        doc="the shoulder-roll index the kinematics use: joint.shoulder_roll_deg as the last "
            "power-up took it (pfma-model 8.1: world = base rotated about x by it)")
    jmove_active: Var[bool] = var("task_io", "b1", (), False, doc="a joint move (msp.jmove_*) commands the joints")
    jmove_done_seq: Var[int] = var("task_io", "i4", (), 0, doc="the last joint move finished (msp.jmove_seq)")
    jmove_done_code: Var[int] = var("task_io", "i2", (), 0,
                                    doc="how joint.jmove_done_seq ended: 0 REACHED 1 STOPPED 2 REFUSED")


JOINT = JointVars


class JointPlannerLayer(Layer):
    """Joint Planner (80 Hz): produces the commanded joint positions for the servo layer.

    Two modes (docs/controller.md, "Kinematics and the Joint Planner"):

    * **Cartesian** while the Cartesian Engine's ``cart.cmd_valid`` is set: every run it
      moves ``servo.q_cmd_rad`` one rate-limited damped-least-squares step
      (:func:`controller.kinematics.ik_step_ex`) toward the pose ``cart.pos_cmd_m`` /
      ``cart.quat_cmd``: no joint moves more than its software rate limit times the task
      period, soft limits are respected, singular sets are passed without a jump. If
      the step stays blocked at a soft limit for STUCK_S with an unchanged command, and
      the pose has a closed-form solution inside the limits (the least squares went
      round a singular set onto the other wrist branch), it moves there on a
      rate-limited straight line in joint space.
    * **joint goal**: a user joint goal (``joint.goal_rad`` with a new ``joint.goal_seq``),
      clipped to the soft limits, goes to ``servo.q_cmd_rad`` (a position step into the
      servo layer, which rate-limits it). A new goal takes precedence over a valid
      Cartesian command: the planner stays in joint-goal mode until the Cartesian
      command's pose changes (the Cartesian Engine holding a pose does not undo a goal),
      then continues in Cartesian mode from the goal (``joint.mode`` says which).

    * **joint move** (the Multi-Segment Path Planner's ``msp.jmove_*``, a checked move-to
      request): the joint command moves on the straight line in joint space from where it
      is to ``msp.jmove_goal_rad``, one normalised parameter on a rest-to-rest trapezoid
      (every joint within ``msp.jmove_speed`` times its rate limit, reaching it in
      JMOVE_ACCEL_S); ``msp.jmove_stop`` decelerates it to rest. It takes precedence over
      the Cartesian command while it runs and answers ``joint.jmove_done_seq`` /
      ``joint.jmove_done_code``; the Cartesian Engine then holds the pose it reached
      (no jump back when Cartesian mode resumes).

    Every run from INITIALIZATION COMPLETE on it also posts the measured tool pose
    ``joint.tool_pos_m`` / ``joint.tool_quat`` = fk(``daq.joint_angle_rad``). Its start-up
    task commands the current joint angles so that nothing moves when the loop closes.

    The manually indexed shoulder roll (pfma-model 8.1) has no sensor: its index is the
    user parameter ``joint.shoulder_roll_deg`` (one of -90, -45, 0, +45, +90; set only while
    powered down), which the initialisation task takes for the kinematics and publishes as
    ``joint.shoulder_roll_rad`` (docs/controller.md "The shoulder-roll index").

    :param shoulder_roll_deg: the parameter's initial value (default 0)
    """

    key = "joint"
    title = "Joint Planner"
    short = "JNTP"
    #: other layers' variables read (controller/neighbours.py; the far ones are listed there)
    reads = (
        "cart.cmd_seq", "cart.cmd_valid", "cart.msp_jmove_goal_rad", "cart.msp_jmove_seq", "cart.msp_jmove_speed",
        "cart.msp_jmove_stop", "cart.pos_cmd_m", "cart.quat_cmd", "daq.joint_angle_rad",
    )
    #: the Cartesian Engine's command (writer "cartesian"); without them only joint goals work
    CART_VARS = (CART.pos_cmd_m, CART.quat_cmd, CART.cmd_valid, CART.cmd_seq)
    #: the Multi-Segment Path Planner's joint moves (writer "msp"); without them none
    JMOVE_VARS = tuple(_JM.values())
    MODE_JOINT, MODE_CARTESIAN = 0, 1
    #: ``joint.mode`` by name
    MODE_NAMES = JOINT_MODE_NAMES

    def __init__(self, shoulder_roll_deg: int = 0) -> None:
        super().__init__()
        self._seen_goal = 0
        self.periodic["joint_planner"] = self.plan_task
        self.lo = np.array([j.soft_lo_rad for j in JOINTS])
        self.hi = np.array([j.soft_hi_rad for j in JOINTS])
        #: the initial value of the parameter joint.shoulder_roll_deg
        self.shoulder_roll_deg = check_shoulder_roll_deg(shoulder_roll_deg)
        #: the index the kinematics use: joint.shoulder_roll_deg as the initialisation took it
        self.shoulder_roll_rad = math.radians(self.shoulder_roll_deg)
        self.q_cmd = np.zeros(N_JOINTS)  #: the last joint command posted (rad)
        self.mode = self.MODE_JOINT
        self._have_cart: bool | None = None
        self._dt_s = 0.0
        self._flags = (False, False)  # (singular, limited) last posted
        self._bad_cmd = False
        self._cart_at_goal: tuple[np.ndarray, np.ndarray] | None = None  # cart pose when a goal won
        self._last_pose: tuple[np.ndarray, np.ndarray] | None = None  # the Cartesian command last run
        self._stuck_runs = 0  # runs blocked at a soft limit with a static command
        self._recover: np.ndarray | None = None  # joint-space goal that leaves a soft limit
        self.last_step = None  #: the last kinematics.StepResult (tests, trace)
        self._have_jmove: bool | None = None
        self._inputs: tuple[str, ...] | None = None  # the names plan_task reads (built at its first run)
        self._jm_seen = 0  # the last msp.jmove_seq taken
        self._jm: "_JointMove | None" = None  # the joint move running

    def specs(self) -> list[VarSpec]:
        # the shoulder-roll rows start from this layer's parameter (its initial index)
        start = {JOINT.shoulder_roll_deg: float(self.shoulder_roll_deg), JOINT.shoulder_roll_rad: self.shoulder_roll_rad}
        return self.state_specs() + [replace(s, initial=start[s.name]) if s.name in start else s
                                     for s in JOINT.specs()]

    def _cart_available(self, rt: "LayerContext") -> bool:
        if self._have_cart is None:
            names = set(rt.wm.names())
            self._have_cart = all(n in names for n in self.CART_VARS)
        return self._have_cart

    def _jmove_available(self, rt: "LayerContext") -> bool:
        if self._have_jmove is None:
            names = set(rt.wm.names())
            self._have_jmove = all(n in names for n in self.JMOVE_VARS)
        return self._have_jmove

    def seq_init(self, rt: "LayerContext") -> TaskState:
        self._cart_available(rt)
        self._dt_s = rt.task_period_s("joint_planner")
        # the shoulder-roll index: a parameter (no sensor), fixed from here to the power-down
        deg = check_shoulder_roll_deg(float(rt.wm.get(JOINT.shoulder_roll_deg)))
        self.shoulder_roll_rad = math.radians(deg)
        rt.wm.post_task_outputs("joint", {JOINT.shoulder_roll_rad: self.shoulder_roll_rad})
        rt.post(self.key, Level.INFO, f"shoulder-roll index {shoulder_roll_text(deg)} (joint.shoulder_roll_deg; "
                                      f"no sensor: as the operator set it): the kinematics use it until power-down")
        return TaskState.DONE

    def seq_startup(self, rt: "LayerContext") -> TaskState:
        v = rt.wm.get_task_inputs((DAQ.joint_angle_rad, JOINT.goal_seq))
        self._seen_goal = int(v[JOINT.goal_seq])  # goals set while powered down do not jump
        self.q_cmd = np.asarray(v[DAQ.joint_angle_rad], dtype=float).copy()
        self.mode = self.MODE_JOINT
        self._bad_cmd = False
        self._cart_at_goal = None
        self._last_pose, self._stuck_runs, self._recover = None, 0, None
        self._jm = None
        if self._jmove_available(rt):  # a joint move sent before this start-up is not run
            self._jm_seen = int(rt.wm.get_task_inputs((_JM[JMOVE.jmove_seq],))[_JM[JMOVE.jmove_seq]])
        rt.wm.post_task_outputs("joint", {JOINT.q_cmd_rad: self.q_cmd, JOINT.q_cmd_valid: True,
                                          JOINT.mode: self.mode, JOINT.jmove_active: False})
        return TaskState.DONE

    def seq_shutdown(self, rt: "LayerContext") -> TaskState:
        out: dict = {JOINT.q_cmd_valid: False}
        if self._jm is not None:
            self._jmove_end(rt, JMOVE_STOPPED, "shut down", out)
        rt.wm.post_task_outputs("joint", out)
        return TaskState.DONE

    def plan_task(self, rt: "LayerContext") -> None:
        from controller import kinematics as kin  # (import here: layers.py stays light)

        # (it exists from INITIALIZATION COMPLETE to START UP COMPLETE: controller/tables/joint.py)
        status = rt.wm.get_state_variable(self.v_status)
        cart = self._cart_available(rt)
        jm = self._jmove_available(rt)
        names = self._inputs
        if names is None:  # built once: what this model has of the planner's inputs
            names = self._inputs = ((DAQ.joint_angle_rad, JOINT.goal_rad, JOINT.goal_seq)
                                    + (self.CART_VARS if cart else ()) + (self.JMOVE_VARS if jm else ()))
        v = rt.wm.get_task_inputs(names)
        p, quat = kin.fk(v[DAQ.joint_angle_rad], self.shoulder_roll_rad)
        out: dict = {JOINT.tool_pos_m: p, JOINT.tool_quat: quat}
        if status == Status.START_UP_COMPLETE:
            valid = cart and bool(v[CART.cmd_valid])
            if int(v[JOINT.goal_seq]) != self._seen_goal:
                if self._jm is not None:
                    self._jmove_end(rt, JMOVE_STOPPED, "a user joint goal took over", out)
                self._set_mode(rt, self.MODE_JOINT, out)
                self._joint_goal(rt, v, out)
                self._cart_at_goal = (np.array(v[CART.pos_cmd_m], dtype=float),
                                      np.array(v[CART.quat_cmd], dtype=float)) if valid else None
            elif jm and (self._jm is not None or int(v[_JM[JMOVE.jmove_seq]]) != self._jm_seen):
                self._joint_move(rt, v, out)
                if valid and self._jm is None:  # ended: joint mode until the Cartesian command changes
                    self._cart_at_goal = (np.array(v[CART.pos_cmd_m], dtype=float),
                                          np.array(v[CART.quat_cmd], dtype=float))
            elif valid and (self.mode == self.MODE_CARTESIAN or self._cart_moved(v)):
                self._cart_at_goal = None
                self._cartesian(rt, kin, v, out)
            else:
                self._set_mode(rt, self.MODE_JOINT, out)
        rt.wm.post_task_outputs("joint", out)

    def _cart_moved(self, v: dict) -> bool:
        """The Cartesian command differs from the one in force when a joint goal won."""
        if self._cart_at_goal is None:
            return True
        p, q = self._cart_at_goal
        return not (np.array_equal(p, np.asarray(v[CART.pos_cmd_m], dtype=float))
                    and np.array_equal(q, np.asarray(v[CART.quat_cmd], dtype=float)))

    def _set_mode(self, rt: "LayerContext", mode: int, out: dict) -> None:
        if mode != self.mode:
            self.mode = mode
            out[JOINT.mode] = mode
            rt.post(self.key, Level.INFO, "Cartesian mode (cart.cmd_valid)" if mode == self.MODE_CARTESIAN
                    else "joint-goal mode: holding the last command")
            if mode == self.MODE_JOINT:
                self._post_flags(rt, False, False, out)

    def _post_flags(self, rt: "LayerContext", singular: bool, limited: bool, out: dict) -> None:
        if (singular, limited) == self._flags:
            return
        if singular != self._flags[0]:
            out[JOINT.singular] = singular
            if singular:
                rt.post(self.key, Level.INFO, "near a singular set: damped steps")
        if limited != self._flags[1]:
            out[JOINT.limited] = limited
            if limited:
                rt.post(self.key, Level.WARNING, "a joint is held at its soft limit")
        self._flags = (singular, limited)

    def _cartesian(self, rt: "LayerContext", kin, v: dict, out: dict) -> None:
        if self.mode != self.MODE_CARTESIAN:
            # continue from the command in force (a joint goal, or the start-up angles): no jump
            self._set_mode(rt, self.MODE_CARTESIAN, out)
        pos = np.asarray(v[CART.pos_cmd_m], dtype=float)
        q4 = np.asarray(v[CART.quat_cmd], dtype=float)
        n = float(np.dot(q4, q4)) if np.all(np.isfinite(q4)) else 0.0
        if not (np.all(np.isfinite(pos)) and 0.5 < n < 2.0):
            if not self._bad_cmd:
                rt.post(self.key, Level.ERROR, f"Cartesian command {int(v['cart.cmd_seq'])} is not a pose "
                                               f"(position {pos.tolist()}, quaternion {q4.tolist()}): holding")
            self._bad_cmd = True
            return
        self._bad_cmd = False
        dt = self._dt_s or rt.task_period_s("joint_planner")
        moved = self._last_pose is None or not (np.array_equal(pos, self._last_pose[0])
                                                and np.array_equal(q4, self._last_pose[1]))
        self._last_pose = (pos.copy(), q4.copy())
        if moved:
            self._stuck_runs, self._recover = 0, None
        if self._recover is not None:  # leaving a soft limit on a joint-space line (static command)
            self.q_cmd = kin.joint_step_toward(self.q_cmd, self._recover, dt)
            if np.array_equal(self.q_cmd, self._recover):
                self._recover = None
            p_c, quat_c = kin.fk(self.q_cmd, self.shoulder_roll_rad)
            out[JOINT.q_cmd_rad] = self.q_cmd
            out[JOINT.cart_err_m] = float(np.linalg.norm(pos - p_c))
            out[JOINT.cart_err_rad] = q_angle(q4, quat_c)
            self._post_flags(rt, bool(kin.singular_sets(self.q_cmd)), False, out)
            return
        r = kin.ik_step_ex(self.q_cmd, pos, q4, dt, lo_rad=self.lo, hi_rad=self.hi,
                           shoulder_roll_rad=self.shoulder_roll_rad)
        self.last_step = r
        self.q_cmd = r.q_rad
        out[JOINT.q_cmd_rad] = self.q_cmd
        out[JOINT.cart_err_m] = r.pos_err_m
        out[JOINT.cart_err_rad] = r.rot_err_rad
        singular = r.singular or bool(kin.singular_sets(self.q_cmd))
        self._post_flags(rt, singular, r.limited, out)
        blocked = r.limited and (r.pos_err_m > STUCK_POS_M or r.rot_err_rad > STUCK_ROT_RAD)
        self._stuck_runs = self._stuck_runs + 1 if blocked else 0
        if self._stuck_runs == int(round(STUCK_S / dt)):
            # Damped least squares can end on a soft limit on the wrong side of a singular set
            # (e.g. the wrist flipped while passing wrist yaw -90 deg). If the pose has a
            # closed-form solution inside the limits, go there in joint space.
            try:
                self._recover = kin.ik(pos, q4, self.q_cmd, self.shoulder_roll_rad, self.lo, self.hi)
                rt.post(self.key, Level.WARNING, "blocked at a soft limit: joint-space move to the "
                                                 "closed-form solution of the Cartesian command")
            except kin.KinematicsError as err:
                rt.post(self.key, Level.WARNING, f"blocked at a soft limit, holding: {err}")

    # --- joint moves (msp.jmove_*) -------------------------------------------------------
    def _joint_move(self, rt: "LayerContext", v: dict, out: dict) -> None:
        seq = int(v[_JM[JMOVE.jmove_seq]])
        if seq != self._jm_seen:
            self._jm_seen = seq
            if self._jm is not None:
                self._jmove_end(rt, JMOVE_STOPPED, f"joint move {seq} took over", out)
            self._set_mode(rt, self.MODE_JOINT, out)
            self._jmove_start(rt, seq, v, out)
            if self._jm is None:
                return
        jm = self._jm
        assert jm is not None
        if bool(v[_JM[JMOVE.jmove_stop]]) and jm.stop_t is None:
            jm.request_stop(rt.now)
            rt.post(self.key, Level.INFO, f"joint move {jm.seq}: stop requested")
        s, finished = jm.sample(rt.now)
        self.q_cmd = jm.q0 + s * jm.d
        out[JOINT.q_cmd_rad] = self.q_cmd
        if finished:
            self._jmove_end(rt, JMOVE_STOPPED if jm.stop_t is not None and s < 1.0 - 1e-12 else JMOVE_REACHED,
                            "", out)

    def _jmove_start(self, rt: "LayerContext", seq: int, v: dict, out: dict) -> None:
        from controller.kinematics import RATE_LIMIT_RAD_S
        from controller.profile import plan_trapezoid
        goal = np.asarray(v[_JM[JMOVE.jmove_goal_rad]], dtype=float)
        speed = float(v[_JM[JMOVE.jmove_speed]])
        if not (np.all(np.isfinite(goal)) and math.isfinite(speed) and 0.0 < speed <= 1.0):
            rt.post(self.key, Level.ERROR, f"joint move {seq} refused: goal {goal.tolist()} / speed {speed!r} "
                                           f"(needs finite angles and a speed 0..1)")
            out.update({JOINT.jmove_done_seq: seq, JOINT.jmove_done_code: JMOVE_REFUSED})
            return
        goal = np.clip(goal, self.lo, self.hi)
        d = goal - self.q_cmd
        big = np.abs(d) > 1e-12
        if big.any():
            vn = float(np.min(RATE_LIMIT_RAD_S[big] * speed / np.abs(d[big])))
            prof = plan_trapezoid(1.0, vn, vn / JMOVE_ACCEL_S)
        else:
            prof = plan_trapezoid(0.0, 1.0, 1.0)
        self._jm = _JointMove(seq, self.q_cmd.copy(), d, rt.now, prof)
        out[JOINT.jmove_active] = True
        rt.post(self.key, Level.INFO, f"joint move {seq}: to " + " ".join(f"{x:+.4f}" for x in goal)
                + f" rad in {prof.duration_s:.2f} s")

    def _jmove_end(self, rt: "LayerContext", code: int, why: str, out: dict) -> None:
        jm = self._jm
        assert jm is not None
        self._jm = None
        out.update({JOINT.jmove_active: False, JOINT.jmove_done_seq: jm.seq, JOINT.jmove_done_code: code})
        if code != JMOVE_REACHED:
            rt.post(self.key, Level.INFO, f"joint move {jm.seq} stopped" + (f": {why}" if why else ""))

    def _joint_goal(self, rt: "LayerContext", v: dict, out: dict) -> None:
        seq = int(v[JOINT.goal_seq])
        if seq == self._seen_goal:
            return
        self._seen_goal = seq
        goal = np.asarray(v[JOINT.goal_rad], dtype=float)
        q = np.clip(goal, self.lo, self.hi)
        clipped = bool(np.any(q != goal))
        if clipped:
            rt.post(self.key, Level.WARNING, f"goal {seq} clipped to the soft limits")
        self._post_flags(rt, False, clipped, out)
        self.q_cmd = q
        out[JOINT.q_cmd_rad] = q
        rt.post(self.key, Level.INFO, f"goal {seq}: " + " ".join(f"{x:+.4f}" for x in q) + " rad")


class _JointMove:
    """A joint move in time: ``q0 + s(t) d`` with ``s`` on a trapezoid, and its controlled stop."""

    def __init__(self, seq: int, q0: np.ndarray, d: np.ndarray, t0: float, profile) -> None:
        self.seq, self.q0, self.d, self.t0, self.profile = seq, q0, d, t0, profile
        self.stop_t: float | None = None
        self._stop_s = self._stop_v = 0.0

    def request_stop(self, t: float) -> None:
        s, v, _ = self.profile.sample(t - self.t0)
        self.stop_t, self._stop_s, self._stop_v = t, s, v

    def sample(self, t: float) -> tuple[float, bool]:
        """(s, finished) at time ``t``."""
        if self.stop_t is None:
            s, _, _ = self.profile.sample(t - self.t0)
            return s, t - self.t0 >= self.profile.duration_s
        a = self.profile.a
        dur = self._stop_v / a if a > 0 else 0.0
        tau = min(t - self.stop_t, dur)
        s = min(1.0, self._stop_s + self._stop_v * tau - 0.5 * a * tau * tau)
        return s, t - self.stop_t >= dur
