"""Multi-Segment Path Planner layer (20 Hz): records paths and plays them back.

IRSS report 2.2.1: "This layer manages tasks that handle multi-segment path manipulation
(recording and execution) and generates intermediate level commands for the Trajectory
Path Planner Layer which exists below it. ... Tasks at this layer execute at relatively
low frequencies (20 Hz)". 2.2.8: "a small menu tree within the multi-segment path
planner used to edit various path buffers" - here ``pfma path`` and :class:`PathStore`.

The layer (:class:`MultiSegmentLayer`): ``msp.mode`` 1 records the measured tool
pose ``joint.tool_pos_m``/``joint.tool_quat`` (a teach point each time ``msp.teach``
changes; continuous capture whenever the pose moved ``msp.capture_dist_m`` or turned
``msp.capture_angle_rad`` since the last point) and saves the path under
``msp.path_id`` when the mode leaves 1; ``msp.mode`` 2 loads path ``msp.path_id``,
plans it and hands the segments one at a time to the Trajectory Planner
(:mod:`controller.trajectory`), the next one each time ``traj.done_seq`` reports the
last one done. Mode 0 during a playback stops it (the Trajectory Planner decelerates).

A **move-to request** (``msp.move_request``, :mod:`controller.paths.move`) is a pose (one
segment through the Trajectory Planner) or a joint goal (a straight line in joint space the
Joint Planner runs from ``msp.jmove_*``). A playback or a move is first **checked**, the
whole interpolated motion sampled, a slice per run (:mod:`controller.paths.check`: tool
rotation beyond ``msp.max_turn_rad``, soft limits, singular sets; refused naming the point
and the reason, before anything moves), then run while the **tracking error** is measured
every run: the measured tool pose's distance from the segment being run (and the one before
it: the arm's lag), a joint move's joint deviation from its line. It ends OK only when the
worst error stayed within ``msp.track_tol_m`` / ``msp.track_tol_rad``, else FAILED naming
the worst error and where. Points without an orientation keep the tool's
(:func:`controller.paths.model.resolve_orientations`, with the orientation the Trajectory
Planner starts from).
"""

from __future__ import annotations

import math
import threading
from dataclasses import replace
from typing import TYPE_CHECKING, Sequence

import numpy as np

from controller.gripper import GRIP, MSP_GRIP, path_request_specs
from controller.layers import JMOVE, JMOVE_SPEED, JOINT, Layer
from controller.messages import Level
from controller.relays import at
from controller.paths.check import MAX_TURN_RAD, SAMPLES_PER_RUN, MotionCheck, Target
from controller.paths.model import DEFAULT_LIMITS, Path, PathError, PathPoint
from controller.paths.move import MOVE_REQUEST_LEN, MoveKind, MoveRequest
from controller.paths.planner import PlannedSegment, plan_path, segment_deviation
from controller.paths.store import PathStore, _now_text, path_missing
from controller.quat import q_angle, q_normalize
from controller.trajectory import SEG, TRAJ, DoneCode, segment_specs
from controller.worldmodel import VarSpec
from controller.variables import CART, DAQ
from controller.worldmodel.var import Var, VarGroup, var
from pfma.gripper import ACTION_NAMES as GRIPPER_ACTION_NAMES, ACTIONS as GRIPPER_ACTIONS, COMPLETE, IN_PROGRESS

if TYPE_CHECKING:  # pragma: no cover
    from controller.context import LayerContext

#: continuous capture thresholds (assumed): a point per 5 mm or 2 degrees
CAPTURE_DIST_M = 0.005
CAPTURE_ANGLE_RAD = math.radians(2.0)
#: tracking tolerance of a playback or move (assumed, this project): twice the nominal
#: servo's static error at the ready pose (10.2 mm / 2.3 deg, docs/controller.md
#: "Kinematics and the Joint Planner"); a joint move's joint deviation counts against the angle
TRACK_TOL_M = 0.02
TRACK_TOL_RAD = math.radians(5.0)
#: a joint move's speed: this fraction of the software rate limits (8.2), times msp.speed_scale
#: (assumed: a quarter, as a path's default speeds are half the trajectory caps)
#: the start pose may move this much while the motion is checked (else refused: checked
#: from another start; assumed, a tenth of the check's sampling)
START_MOVED_M = 0.5e-3
START_MOVED_RAD = math.radians(0.1)
#: bytes of ``msp.result_text``
RESULT_TEXT_BYTES = 320


class MspMode:
    """``msp.mode`` (user) and ``msp.state`` (the layer)."""

    IDLE = 0
    RECORD = 1
    PLAY = 2
    MOVE = 3  #: msp.state only: a move-to request runs (msp.move_request)
    NAMES = {0: "IDLE", 1: "RECORD", 2: "PLAY", 3: "MOVE"}


class MspResult:
    """``msp.result``: how the last recording or playback ended (``msp.finished`` counts them)."""

    OK = 0
    CANCELLED = 1  #: playback stopped by the user or the layer shutting down
    NO_POSE = 2  #: no measured tool pose (Joint Planner kinematics missing)
    NO_PATH = 3  #: path id unknown or its file bad
    EMPTY = 4  #: nothing recorded / nothing to play
    REFUSED = 5  #: refused before it started (the check, busy, not in trajectory mode) or by the Trajectory Planner
    SAVE_FAILED = 6
    FAILED = 7  #: ran to its end, but the arm did not follow within the tracking tolerance
    GRIPPER = 8  #: a gripper event of the path was refused or failed (Servo Control's answer)
    NAMES = {0: "OK", 1: "CANCELLED", 2: "NO POSE", 3: "NO PATH", 4: "EMPTY", 5: "REFUSED", 6: "SAVE FAILED",
             7: "FAILED", 8: "GRIPPER FAILED"}


#: What this layer reads of the layers further down is the Trajectory Planner's copy
#: (controller/relays.py): the measured tool pose (the Joint Planner's), the Cartesian
#: command (the Cartesian engine's), the joint command, a joint move's end and the
#: shoulder-roll index (the Joint Planner's), the gripper's events and answers (Servo Control's)
TOOL_POS, TOOL_QUAT = at("msp", JOINT.tool_pos_m), at("msp", JOINT.tool_quat)
CMD_VALID, CMD_POS, CMD_QUAT = (at("msp", n) for n in (CART.cmd_valid, CART.pos_cmd_m, CART.quat_cmd))
TOOL_POSE = (TOOL_POS, TOOL_QUAT)
CMD_POSE = (CMD_VALID, CMD_POS, CMD_QUAT)
#: the gripper's accepted user requests (Servo Control, controller/gripper.py): a recording stores each
EVENT_SEQ, EVENT, EVENT_FORCE = (at("msp", n) for n in (GRIP.event_seq, GRIP.event, GRIP.event_force_n))
GRIPPER_EVENT = (EVENT_SEQ, EVENT, EVENT_FORCE)
GRIP_DONE_SEQ, GRIP_DONE_CODE = at("msp", GRIP.msp_done_seq), at("msp", GRIP.msp_done_code)
GRIPPER_DONE = (GRIP_DONE_SEQ, GRIP_DONE_CODE)
#: what the check and the tracking read from the layers below, when the model has them
Q_CMD, Q_CMD_VALID = at("msp", JOINT.q_cmd_rad), at("msp", JOINT.q_cmd_valid)
JOINT_VARS = (Q_CMD, Q_CMD_VALID, DAQ.joint_angle_rad)
ROLL_VAR = at("msp", JOINT.shoulder_roll_rad)
CART_MODE = CART.mode
JM_DONE_SEQ, JM_DONE_CODE = at("msp", JOINT.jmove_done_seq), at("msp", JOINT.jmove_done_code)
JMOVE_DONE = (JM_DONE_SEQ, JM_DONE_CODE)
#: cart.mode that follows the Trajectory Planner (controller.cartesian MODE_TRAJECTORY)
CART_TRAJECTORY = 2


def joint_move_specs() -> list[VarSpec]:
    """The joint-move hand-over to the Joint Planner (owned by the Multi-Segment Path Planner)."""
    return JMOVE.specs()


def _request_problem(req: MoveRequest) -> str:
    """What is wrong with a move request's numbers ("" nothing; written by hand with ``pfma
    wm set``, a request is not checked before it reaches the layer)."""
    if req.kind == MoveKind.JOINTS:
        return "" if all(math.isfinite(x) for x in req.joints_rad) else f"joint angles {req.joints_rad} not finite"
    if not all(math.isfinite(x) for x in req.pos_m):
        return f"position {req.pos_m} not finite"
    if req.quat is not None:
        n = math.sqrt(sum(x * x for x in req.quat))
        if not (math.isfinite(n) and abs(n - 1.0) <= 1e-3):
            return f"orientation {req.quat} is not a unit quaternion (norm {n:.6f})"
    return ""


class _Job:
    """A playback or move: its check, then its run and tracking."""

    def __init__(self, kind: str, label: str, move_seq: int = 0) -> None:
        self.kind = kind  #: "path", "pose" or "joint"
        self.label = label  #: "path demo (id 3)", "move 4"
        self.move_seq = move_seq  #: the move request (0: a playback)
        self.check: MotionCheck | None = None
        self.start_p = np.zeros(3)
        self.start_q = np.array([1.0, 0.0, 0.0, 0.0])
        self.q0 = np.zeros(6)  #: joint move: the line's start (the Joint Planner's command)
        self.goal = np.zeros(6)
        self.points = 0
        self.tol_m = TRACK_TOL_M
        self.tol_rad = TRACK_TOL_RAD
        self.err_m = 0.0  #: worst tracking error so far
        self.err_rad = 0.0
        self.where = ""  #: where the worst (position or angle, whichever is the larger fraction) was
        self.worst_frac = 0.0
        self.warned = False
        self.running = False  #: checked and started
        self.jseq = 0  #: joint move number posted


class RecordSource:
    """``msp.record_source``: which pose a recording stores."""

    MEASURED = 0  #: the measured tool pose (fk of the resolver angles): where the tool was
    COMMAND = 1  #: the Cartesian command: played back, the arm retraces the recorded motion
    #: including the servo's static error (teach-and-repeat: repeatability, not accuracy)
    NAMES = {0: "MEASURED", 1: "COMMAND"}


class MspVars(VarGroup, prefix="msp", writer="msp"):
    """The Multi-Segment Path Planner's user requests (writer ``user``) and statuses. Its
    hand-overs to the layers below are declared where they are read: ``SEG``
    (controller.trajectory), ``JMOVE`` (controller.layers), ``MSP_GRIP`` (controller.gripper)."""

    mode: Var[int] = var("command_input", "i2", (), 0, writer="user",
                         doc="path planner mode (RECORD into, PLAY: path msp.path_id)",
                         enum={k: v for k, v in MspMode.NAMES.items() if k != MspMode.MOVE})
    path_id: Var[int] = var("command_input", "i4", (), 0, writer="user",
                            doc="the path to record into or play (the id in its file; pfma path list)")
    teach: Var[int] = var("command_input", "i4", (), 0, writer="user",
                          doc="increment while recording to store the present tool pose as a teach point")
    capture: Var[bool] = var("command_input", "b1", (), True, writer="user",
                             doc="while recording, also capture points continuously (distance/angle threshold)")
    capture_dist_m: Var[float] = var("command_input", "f8", (), CAPTURE_DIST_M, "m", writer="user",
                                     doc="continuous capture: a point each time the tool moved this far")
    capture_angle_rad: Var[float] = var("command_input", "f8", (), CAPTURE_ANGLE_RAD, "rad", writer="user",
                                        doc="continuous capture: a point each time the tool turned this far")
    record_source: Var[int] = var(
        "command_input", "i2", (), RecordSource.MEASURED, writer="user",
        doc="recording stores the MEASURED tool pose (joint.tool_*) or the Cartesian COMMAND "
            "(cart.pos_cmd_m/quat_cmd: playback repeats the recorded motion)", enum=RecordSource.NAMES)
    speed_scale: Var[float] = var("command_input", "f8", (), 1.0, "1", writer="user", valid=(0.0, 10.0),
                                  doc="playback speed factor on the path's speeds (capped by traj.*_max)")
    max_turn_rad: Var[float] = var(
        "command_input", "f8", (), MAX_TURN_RAD, "rad", writer="user",
        doc="a playback or move that would turn the tool more than this from its starting orientation "
            "is refused before it starts (a move request may carry its own)")
    track_tol_m: Var[float] = var(
        "command_input", "f8", (), TRACK_TOL_M, "m", writer="user",
        doc="tracking tolerance: a playback or move ends OK only if the measured tool point stayed "
            "this close to the path")
    track_tol_rad: Var[float] = var(
        "command_input", "f8", (), TRACK_TOL_RAD, "rad", writer="user",
        doc="tracking tolerance: tool orientation from the path's (a joint move: joint deviation from its line)")
    move_request: Var[np.ndarray] = var(
        "command_input", "f8", (MOVE_REQUEST_LEN,), [0.0] * MOVE_REQUEST_LEN, "mixed", writer="user",
        valid=(-1e9, 1e9),  # a packed record: the layer checks each field (_request_problem)
        doc="move-to request: [seq, kind 0 stop 1 pose 2 joints, x y z m, qw qx qy qz (0: keep the "
            "orientation), 6 joint rad, max turn rad (0: msp.max_turn_rad)]; a new seq is a new request")
    state: Var[int] = var("status_output", "i2", (), 0,
                          doc="path planner state: idle, recording, playing, moving (a move request)",
                          enum=MspMode.NAMES)
    points: Var[int] = var("status_output", "i4", (), 0,
                           doc="points recorded so far (recording) or in the path (playing)")
    segment: Var[int] = var("status_output", "i4", (), 0, doc="playback: the segment running (1-based; 0 none)")
    segments: Var[int] = var("status_output", "i4", (), 0, doc="playback: segments in the plan")
    finished: Var[int] = var("status_output", "i4", (), 0,
                             doc="counts recordings saved and playbacks ended (msp.result says how)")
    result: Var[int] = var(
        "status_output", "i2", (), 0,
        doc="how the last recording/playback/move ended (FAILED: not followed within the tracking tolerance)",
        enum=MspResult.NAMES)
    result_text: Var[np.ndarray] = var(
        "status_output", "u1", (RESULT_TEXT_BYTES,), [0] * RESULT_TEXT_BYTES,
        doc="how the last recording/playback/move ended, in words (UTF-8, zero-padded)")
    move_seq: Var[int] = var("status_output", "i4", (), 0, doc="the move request taken last (msp.move_request[0])")
    move_done_seq: Var[int] = var("status_output", "i4", (), 0,
                                  doc="the move request answered last (msp.result, msp.result_text say how)")
    track_err_m: Var[float] = var(
        "status_output", "f8", (), 0.0, "m",
        doc="worst tracking error of the running (or last) playback or move: tool point")
    track_err_rad: Var[float] = var("status_output", "f8", (), 0.0, "rad",
                                    doc="worst tracking error: tool orientation (a joint move: joint deviation)")


MSP = MspVars
USER_VARS = (MSP.mode, MSP.path_id, MSP.teach, MSP.capture, MSP.capture_dist_m, MSP.capture_angle_rad,
             MSP.speed_scale, MSP.record_source)
#: the user variables of moves and of the checks (read with USER_VARS every run)
MOVE_USER_VARS = (MSP.move_request, MSP.max_turn_rad, MSP.track_tol_m, MSP.track_tol_rad)
_RUN_VARS = USER_VARS + MOVE_USER_VARS


class MultiSegmentLayer(Layer):
    """Multi-Segment Path Planner: path recording and playback (see the module doc).

    :param store: where paths are saved and loaded (default: :class:`PathStore` in the
        default directory)
    :param background_save: write recordings from a thread (the real-time task only hands
        the points over); tests may turn it off or call :meth:`wait_saved`
    """

    key = "msp"
    title = "Multi-Segment Path Planner"
    short = "MSPP"
    #: other layers' variables read (controller/neighbours.py; the far ones are listed there)
    reads = (
        "cart.mode", "daq.joint_angle_rad", "traj.cart_cmd_valid", "traj.cart_pos_cmd_m", "traj.cart_quat_cmd",
        "traj.done_code", "traj.done_seq", "traj.gripper_event", "traj.gripper_event_force_n",
        "traj.gripper_event_seq", "traj.gripper_msp_done_code", "traj.gripper_msp_done_seq",
        "traj.joint_jmove_done_code", "traj.joint_jmove_done_seq", "traj.joint_shoulder_roll_rad",
        "traj.joint_tool_pos_m", "traj.joint_tool_quat", "traj.servo_q_cmd_rad", "traj.servo_q_cmd_valid",
    )

    def __init__(self, store: PathStore | None = None, background_save: bool = True) -> None:
        super().__init__()
        self.store = store if store is not None else PathStore()
        self.background_save = background_save
        self.periodic["msp_planner"] = self.plan_task  # while START UP COMPLETE (controller/tables/msp.py)
        self.periodic["msp_requests"] = self.requests_task  # in every other status
        self.runs = {"msp_planner": 0}  #: task runs (as the placeholder counted them)
        self.state = MspMode.IDLE
        self._mode_seen = MspMode.IDLE
        self._teach_seen = 0
        self._rec: list[PathPoint] = []
        self._rec_id = 0
        self._source = RecordSource.MEASURED
        self._rec_t0 = 0.0
        self._plan: list[PlannedSegment] = []
        self._seg_i = 0
        self._seg_seq = 0
        self._grip_event_seen = 0  # gripper.event_seq when last looked at (recording)
        self._grip_seq = 0  # the path's gripper requests made (msp.gripper_seq)
        self._grip_wait = False  # playback waits for the gripper's answer to _grip_seq
        self._job: _Job | None = None
        self._move_seen = 0
        self._jmove_seq = 0
        self._deferred: MoveRequest | str | None = None  # a start waiting one run for cart.mode ("play": a playback)
        self._finished = 0
        self._end_lock = threading.Lock()
        self._names: set[str] | None = None
        self._saver: threading.Thread | None = None
        self.last_saved: Path | None = None
        self.last_error = ""

    def specs(self) -> list[VarSpec]:
        return self.state_specs() + segment_specs() + joint_move_specs() + path_request_specs() + MSP.specs()

    # --- helpers ---------------------------------------------------------------------------
    def _has(self, rt: "LayerContext", names: Sequence[str]) -> bool:
        if self._names is None:
            self._names = set(rt.wm.names())
        return all(n in self._names for n in names)

    def _tool_pose(self, rt: "LayerContext") -> tuple[np.ndarray, np.ndarray] | None:
        if self._source == RecordSource.COMMAND:
            if not self._has(rt, CMD_POSE):
                return None
            v = rt.wm.get_task_inputs(CMD_POSE)
            if not bool(v[CMD_VALID]):
                return None
            return np.asarray(v[CMD_POS], dtype=float), q_normalize(v[CMD_QUAT])
        if not self._has(rt, TOOL_POSE):
            return None
        v = rt.wm.get_task_inputs(TOOL_POSE)
        q = np.asarray(v[TOOL_QUAT], dtype=float)
        if float(q @ q) < 0.5:
            return None
        return np.asarray(v[TOOL_POS], dtype=float), q_normalize(q)

    def _status(self, rt: "LayerContext", **kw: int) -> None:
        rt.wm.post_task_outputs("msp", {getattr(MSP, k): v for k, v in kw.items()})

    def _end(self, rt: "LayerContext", result: int, text: str, idle: bool = True, move_seq: int = 0) -> None:
        """A recording, playback or move ended: msp.finished, msp.result, msp.result_text (and
        msp.move_done_seq for a move request), and the message ``text -> RESULT``."""
        with self._end_lock:  # the background save ends recordings from its thread
            self._finished += 1
            n = self._finished
        if idle:
            self.state = MspMode.IDLE
            self._job = None
            self._status(rt, state=MspMode.IDLE, segment=0)
        tail = f" -> {MspResult.NAMES[result]}"
        line = text + tail
        words = np.zeros(RESULT_TEXT_BYTES, dtype=np.uint8)
        raw = line.encode()
        if len(raw) > RESULT_TEXT_BYTES:  # the result stays readable at the end
            raw = text.encode()[:RESULT_TEXT_BYTES - len(tail) - 3] + b"..." + tail.encode()
        words[:len(raw)] = np.frombuffer(raw, dtype=np.uint8)
        out = {MSP.finished: n, MSP.result: result, MSP.result_text: words}
        if move_seq:
            out[MSP.move_done_seq] = move_seq
        rt.wm.post_task_outputs("msp", out)
        lvl = Level.INFO if result == MspResult.OK else Level.WARNING
        rt.post(self.key, lvl, line)

    # --- recording -------------------------------------------------------------------------
    def _add_point(self, rt, p: np.ndarray, q: np.ndarray, kind: str) -> None:
        self._rec.append(PathPoint(tuple(float(x) for x in p), tuple(float(x) for x in q), kind,
                                   round(rt.now - self._rec_t0, 6)))

    def _start_record(self, rt, v) -> None:
        self._source = int(v[MSP.record_source])
        if self._source not in RecordSource.NAMES:
            rt.post(self.key, Level.WARNING, f"msp.record_source {self._source} unknown; recording the measured pose")
            self._source = RecordSource.MEASURED
        pose = self._tool_pose(rt)
        self._rec_id = int(v[MSP.path_id])
        if pose is None:
            self._end(rt, MspResult.NO_POSE, f"record: no {RecordSource.NAMES[self._source].lower()} tool pose "
                                             f"({'cart.pos_cmd_m' if self._source else 'joint.tool_pos_m'})")
            return
        self._rec, self._rec_t0 = [], rt.now
        self._teach_seen = int(v[MSP.teach])
        if self._has(rt, GRIPPER_EVENT):
            self._grip_event_seen = int(rt.wm.get(EVENT_SEQ))
        self.state = MspMode.RECORD
        if bool(v[MSP.capture]):
            self._add_point(rt, *pose, "capture")
        self._status(rt, state=MspMode.RECORD, points=len(self._rec))
        rt.post(self.key, Level.INFO, f"recording path id {self._rec_id} "
                                      f"({RecordSource.NAMES[self._source].lower()} pose)")

    def _record(self, rt, v) -> None:
        pose = self._tool_pose(rt)
        if pose is None:
            return
        p, q = pose
        n0 = len(self._rec)
        teach = int(v[MSP.teach])
        if teach != self._teach_seen:
            self._teach_seen = teach
            self._add_point(rt, p, q, "teach")
            rt.post(self.key, Level.INFO, f"teach point {len(self._rec) - 1}: "
                                          + " ".join(f"{x:+.4f}" for x in p) + " m")
        elif bool(v[MSP.capture]):
            if not self._rec:
                self._add_point(rt, p, q, "capture")
            else:
                last = self._rec[-1]
                moved = float(np.linalg.norm(p - np.array(last.pos_m)))
                turned = q_angle(q, last.quat)
                if moved >= float(v[MSP.capture_dist_m]) or turned >= float(v[MSP.capture_angle_rad]):
                    self._add_point(rt, p, q, "capture")
        self._record_gripper(rt, p, q)
        if len(self._rec) != n0:
            self._status(rt, points=len(self._rec))

    def _record_gripper(self, rt, p: np.ndarray, q: np.ndarray) -> None:
        """A gripper request the user made while recording (accepted by Servo Control): a
        gripper event at the present pose, with the grip force in force after it."""
        if not self._has(rt, GRIPPER_EVENT):
            return
        g = rt.wm.get_task_inputs(GRIPPER_EVENT)
        seq = int(g[EVENT_SEQ])
        if seq == self._grip_event_seen:
            return
        self._grip_event_seen = seq
        action = GRIPPER_ACTION_NAMES.get(int(g[EVENT]))
        if action not in ("open", "close", "stop"):
            return  # a grip force alone: each event carries the force in force
        self._rec.append(PathPoint(tuple(float(x) for x in p), tuple(float(x) for x in q), "gripper",
                                   round(rt.now - self._rec_t0, 6), gripper=action,
                                   force_n=round(float(g[EVENT_FORCE]), 3)))
        rt.post(self.key, Level.INFO, f"gripper event {len(self._rec) - 1}: {action} at "
                                      f"{float(g[EVENT_FORCE]):.0f} N")

    def _stop_record(self, rt, v) -> None:
        pose = self._tool_pose(rt)
        if pose is not None:
            self._record_gripper(rt, *pose)  # a request answered since the last run is part of the path
        if pose is not None and bool(v[MSP.capture]) and self._rec:
            last = self._rec[-1]
            if np.linalg.norm(pose[0] - np.array(last.pos_m)) > 1e-4 or q_angle(pose[1], last.quat) > 1e-3:
                self._add_point(rt, *pose, "capture")  # the end of the motion is part of the path
        pts, pid = tuple(self._rec), self._rec_id
        self._rec = []
        if not pts:
            self._end(rt, MspResult.EMPTY, f"record path id {pid}: no points")
            return
        self.state = MspMode.IDLE
        self._status(rt, state=MspMode.IDLE, points=len(pts))
        if self.background_save:
            self.wait_saved()
            self._saver = threading.Thread(target=self._save, args=(rt, pid, pts), daemon=True,
                                           name="msp-save")
            self._saver.start()
        else:
            self._save(rt, pid, pts)

    def _save(self, rt, pid: int, pts: tuple[PathPoint, ...]) -> None:
        """Write a recording into path ``pid`` (a new ``path-<id>`` if there is none). Posts
        msp.finished / msp.result (a post is thread-safe: it goes to the next segment)."""
        try:
            try:
                old = self.store.by_id(pid) if pid > 0 else None
            except PathError:
                old = None
            if old is not None:
                saved = self.store.save(replace(old, points=pts))
            else:
                if pid <= 0:
                    pid = self.store.next_id()
                name = f"path-{pid}"
                now = _now_text()
                saved = self.store.save(Path(name, pid, pts, DEFAULT_LIMITS, 0, now, now,
                                             "recorded by the controller"), force=True)
            self.last_saved = saved
            self._end(rt, MspResult.OK, f"recorded {len(pts)} points into path {saved.name} (id {saved.id}, "
                                        f"revision {saved.revision})", idle=False)
        except Exception as err:  # noqa: BLE001 - a failed save is reported, never a crash
            self.last_error = f"{type(err).__name__}: {err}"
            self._end(rt, MspResult.SAVE_FAILED, f"saving path id {pid} failed: {self.last_error}", idle=False)

    def wait_saved(self, timeout_s: float = 10.0) -> None:
        """Wait for a background save to finish (host time; not a world wait)."""
        t = self._saver
        if t is not None:
            t.join(timeout_s)
            self._saver = None

    # --- playback and moves: start ------------------------------------------------------------
    def _traj_start(self, rt) -> tuple[np.ndarray, np.ndarray] | None:
        """The pose the Trajectory Planner starts a playback from (its own choice: the
        Cartesian command if valid, else the measured tool pose)."""
        if self._has(rt, CMD_POSE):
            v = rt.wm.get_task_inputs(CMD_POSE)
            if bool(v[CMD_VALID]):
                return np.asarray(v[CMD_POS], dtype=float), q_normalize(v[CMD_QUAT])
        if self._has(rt, TOOL_POSE):
            v = rt.wm.get_task_inputs(TOOL_POSE)
            q = np.asarray(v[TOOL_QUAT], dtype=float)
            if float(q @ q) > 0.5:
                return np.asarray(v[TOOL_POS], dtype=float), q_normalize(q)
        return None

    def _joint_start(self, rt) -> np.ndarray | None:
        """The Joint Planner's joint command (the arm's branch), else the measured angles;
        None without either in the model."""
        if not self._has(rt, JOINT_VARS):
            return None
        v = rt.wm.get_task_inputs(JOINT_VARS)
        if bool(v[Q_CMD_VALID]):
            return np.asarray(v[Q_CMD], dtype=float).copy()
        return np.asarray(v[DAQ.joint_angle_rad], dtype=float).copy()

    def _roll(self, rt) -> float:
        return float(rt.wm.get_task_inputs((ROLL_VAR,))[ROLL_VAR]) if self._has(rt, (ROLL_VAR,)) else 0.0

    def _cart_mode_ok(self, rt, what: str, retry: MoveRequest | str, first: bool) -> bool:
        """A Cartesian playback or move needs cart.mode TRAJECTORY. Not so at the first look:
        looked at again at the next run (a user's cart.mode write made just before the
        request may be applied a frame after it); still not: refused."""
        if not self._has(rt, (CART_MODE,)):
            return True
        mode = int(rt.wm.get_task_inputs((CART_MODE,))[CART_MODE])
        if mode == CART_TRAJECTORY:
            return True
        if first:
            self._deferred = retry
            return False
        from controller.cartesian import MODE_NAMES
        job = self._job
        self._job = None
        self._end(rt, MspResult.REFUSED, f"{what} refused: cart.mode is {mode} {MODE_NAMES.get(mode, '?')}, the "
                                         f"Cartesian Engine follows the Trajectory Planner only in cart.mode 2 "
                                         f"TRAJECTORY (pfma wm set cart.mode 2)",
                  move_seq=job.move_seq if job is not None else 0)
        return False

    def _start_play(self, rt, v, first: bool = True) -> None:
        pid = int(v[MSP.path_id])
        start = self._traj_start(rt)
        if start is None:
            self._end(rt, MspResult.NO_POSE, f"play path id {pid}: no start pose (no valid Cartesian command and no "
                                             f"measured tool pose)")
            return
        try:
            path = self.store.by_id(pid)
            plan = plan_path(path, float(v[MSP.speed_scale]), start_quat=start[1])
        except PathError as err:
            self.last_error = str(err)
            self._end(rt, MspResult.NO_PATH if path_missing(err) else MspResult.EMPTY,
                      f"play path id {pid}: {err}")
            return
        if any(s.gripper for s in plan) and not self._has(rt, GRIPPER_DONE):
            self._end(rt, MspResult.GRIPPER, f"play path id {pid}: it has gripper events and this controller "
                                             f"has no gripper (Servo Control's gripper.* variables)")
            return
        self._grip_wait = False
        job = _Job("path", f"path {path.name} (id {pid})")
        job.points = len(path.points)
        self._job = job
        if not self._cart_mode_ok(rt, f"play {job.label}", "play", first):
            return
        self._plan = plan
        self._begin(rt, v, job, start, [Target(f"point {s.index}", s.pos_m, s.quat) for s in plan])

    def _start_move(self, rt, v, req: MoveRequest, first: bool = True) -> None:
        label = f"move {req.seq}"
        if req.kind == MoveKind.JOINTS:
            job = _Job("joint", label, req.seq)
            q0 = self._joint_start(rt)
            if q0 is None:
                self._end(rt, MspResult.NO_POSE, f"{label} ({req.describe()}): no joint angles in the world model",
                          move_seq=req.seq)
                return
            self._job = job
            job.q0, job.goal = q0, np.asarray(req.joints_rad, dtype=float)
            self._begin(rt, v, job, None, None, req.max_turn_rad)
            return
        start = self._traj_start(rt)
        if start is None:
            self._end(rt, MspResult.NO_POSE, f"{label} ({req.describe()}): no start pose (no valid Cartesian command "
                                             f"and no measured tool pose)", move_seq=req.seq)
            return
        job = _Job("pose", label, req.seq)
        self._job = job
        if not self._cart_mode_ok(rt, f"{label} ({req.describe()})", req, first):
            return
        quat = start[1] if req.quat is None else np.asarray(req.quat, dtype=float)
        base = DEFAULT_LIMITS.scaled(float(v[MSP.speed_scale]))
        self._plan = [PlannedSegment(0, np.asarray(req.pos_m, dtype=float), quat, base)]
        self._begin(rt, v, job, start, [Target("the target", self._plan[0].pos_m, quat)], req.max_turn_rad)

    def _begin(self, rt, v, job: _Job, start, targets, max_turn: float | None = None) -> None:
        """Set the job up and start its check (or, with no joint angles in the model, start
        at once, saying the motion was not checked)."""
        job.tol_m, job.tol_rad = float(v[MSP.track_tol_m]), float(v[MSP.track_tol_rad])
        turn = max_turn if max_turn else float(v[MSP.max_turn_rad])
        bad = [f"{n} {x!r}" for n, x in ((MSP.track_tol_m, job.tol_m), (MSP.track_tol_rad, job.tol_rad),
                                         (MSP.max_turn_rad, turn)) if not (math.isfinite(x) and x > 0.0)]
        if bad:
            self._end(rt, MspResult.REFUSED, f"{job.label} refused: {', '.join(bad)} must be > 0",
                      move_seq=job.move_seq)
            return
        self.state = MspMode.MOVE if job.move_seq else MspMode.PLAY
        self._seg_i = 0
        out = {"state": self.state, "segment": 0, "segments": len(self._plan) if job.kind != "joint" else 1,
               "points": job.points}
        if job.move_seq:
            out["move_seq"] = job.move_seq
        self._status(rt, **out)
        rt.wm.post_task_outputs("msp", {MSP.track_err_m: 0.0, MSP.track_err_rad: 0.0})
        roll = self._roll(rt)
        if job.kind == "joint":
            job.check = MotionCheck.joint(job.q0, job.goal, max_turn_rad=turn, shoulder_roll_rad=roll)
            what = "joints " + ", ".join(f"{math.degrees(x):+.1f}" for x in job.goal) + " deg"
        else:
            job.start_p, job.start_q = start
            q0 = self._joint_start(rt)
            if q0 is None:
                rt.post(self.key, Level.WARNING, f"{job.label}: no joint angles in the world model: the motion is not "
                                                 f"checked (rotation, soft limits, singular sets) before it starts")
                self._go(rt, job)
                return
            job.check = MotionCheck.cartesian(q0, job.start_p, job.start_q, targets, max_turn_rad=turn,
                                              shoulder_roll_rad=roll)
            what = f"{len(targets)} segment(s)" + (f" from {job.points} points" if job.points else
                                                   f" to {targets[0].label}")
        rt.post(self.key, Level.INFO, f"{job.label}: checking {what} (tool rotation <= {math.degrees(turn):.0f} deg, "
                                      f"soft limits, singular sets)")

    # --- playback and moves: check, run, track, end ----------------------------------------------
    def _advance_check(self, rt, job: _Job) -> None:
        c = job.check
        assert c is not None
        if not c.advance(SAMPLES_PER_RUN):
            return
        if c.refusal is not None:
            self._end(rt, MspResult.REFUSED, f"{job.label} refused before it started: {c.refusal.text()}",
                      move_seq=job.move_seq)
            return
        if job.kind == "joint":
            q_now = self._joint_start(rt)
            moved = q_now is None or float(np.max(np.abs(q_now - job.q0))) > START_MOVED_RAD
        else:
            start = self._traj_start(rt)
            moved = start is None or (float(np.linalg.norm(start[0] - job.start_p)) > START_MOVED_M
                                      or q_angle(start[1], job.start_q) > START_MOVED_RAD)
        if moved:
            self._end(rt, MspResult.REFUSED, f"{job.label} refused: the arm's command moved while the motion was "
                                             f"checked (hand controller?); request it again", move_seq=job.move_seq)
            return
        rt.post(self.key, Level.INFO, f"{job.label}: checked ({c.samples} samples, the tool turns at most "
                                      f"{math.degrees(c.worst_turn_rad):.1f} deg): starting")
        self._go(rt, job)

    def _go(self, rt, job: _Job) -> None:
        job.running = True
        if job.kind == "joint":
            self._jmove_seq += 1
            job.jseq = self._jmove_seq
            speed = min(1.0, JMOVE_SPEED * float(rt.wm.get_task_inputs((MSP.speed_scale,))[MSP.speed_scale]))
            rt.wm.post_task_outputs("msp", {JMOVE.jmove_seq: job.jseq, JMOVE.jmove_goal_rad: job.goal,
                                            JMOVE.jmove_speed: speed, JMOVE.jmove_stop: False, MSP.segment: 1})
            return
        if job.kind == "path":
            rt.post(self.key, Level.INFO, f"playing {job.label}: {len(self._plan)} segments from {job.points} points")
        self._send(rt)

    def _send(self, rt) -> None:
        s = self._plan[self._seg_i]
        self._seg_seq += 1
        rt.wm.post_task_outputs("msp", {
            SEG.seg_seq: self._seg_seq, SEG.seg_pos_m: s.pos_m, SEG.seg_quat: s.quat,
            SEG.seg_limits: np.array(s.limits, dtype=float), SEG.seg_last: self._seg_i == len(self._plan) - 1,
            SEG.seg_stop: False, MSP.segment: self._seg_i + 1})

    def _segment_geometry(self, job: _Job, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(p0, q0, p1, q1) of segment ``i`` of the plan (segment 0 from the start pose)."""
        if i == 0:
            p0, q0 = job.start_p, job.start_q
        else:
            p0, q0 = self._plan[i - 1].pos_m, self._plan[i - 1].quat
        return p0, q0, self._plan[i].pos_m, self._plan[i].quat

    def _where(self, job: _Job, i: int) -> str:
        if job.kind == "path":
            return f"in segment {i + 1} (into point {self._plan[i].index})"
        return "on the way to the target"

    def _track(self, rt, job: _Job) -> None:
        """The tracking error now; the worst kept with where it was."""
        if job.kind == "joint":
            if not self._has(rt, (DAQ.joint_angle_rad,)):
                return
            q = np.asarray(rt.wm.get_task_inputs((DAQ.joint_angle_rad,))[DAQ.joint_angle_rad], dtype=float)
            d = job.goal - job.q0
            dd = float(d @ d)
            u = min(1.0, max(0.0, float((q - job.q0) @ d) / dd)) if dd > 1e-12 else 1.0
            err_m, err_rad = 0.0, float(np.max(np.abs(q - (job.q0 + u * d))))
            where = f"at {u * 100:.0f} % of the way"
        else:
            if not self._has(rt, TOOL_POSE):
                return
            v = rt.wm.get_task_inputs(TOOL_POSE)
            qm = np.asarray(v[TOOL_QUAT], dtype=float)
            if float(qm @ qm) < 0.5:
                return
            x = np.asarray(v[TOOL_POS], dtype=float)
            i = self._seg_i
            tol = (job.tol_m, job.tol_rad)
            err_m, err_rad = segment_deviation(x, qm, *self._segment_geometry(job, i), tol=tol)
            if i > 0:  # the arm may still be finishing the segment before (its lag)
                e2 = segment_deviation(x, qm, *self._segment_geometry(job, i - 1), tol=tol)
                if max(e2[0] / job.tol_m, e2[1] / job.tol_rad) < max(err_m / job.tol_m, err_rad / job.tol_rad):
                    err_m, err_rad = e2
            where = f"{self._where(job, i)}, tool at ({x[0]:+.3f}, {x[1]:+.3f}, {x[2]:+.3f}) m"
        if err_m <= job.err_m and err_rad <= job.err_rad:
            return
        job.err_m, job.err_rad = max(job.err_m, err_m), max(job.err_rad, err_rad)
        rt.wm.post_task_outputs("msp", {MSP.track_err_m: job.err_m, MSP.track_err_rad: job.err_rad})
        frac = max(err_m / job.tol_m, err_rad / job.tol_rad)
        if frac > job.worst_frac:
            job.worst_frac, job.where = frac, where
        if frac > 1.0 and not job.warned:
            job.warned = True
            rt.post(self.key, Level.WARNING, f"{job.label}: tracking error {err_m * 1e3:.1f} mm / "
                                             f"{math.degrees(err_rad):.2f} deg beyond the tolerance "
                                             f"{job.tol_m * 1e3:.0f} mm / {math.degrees(job.tol_rad):.1f} deg, {where}")

    def _finish(self, rt, job: _Job, what: str) -> None:
        """The motion ran to its end: OK within the tracking tolerance, else FAILED."""
        errs = f"worst tracking error {job.err_m * 1e3:.1f} mm / {math.degrees(job.err_rad):.2f} deg"
        if job.kind == "joint":
            errs = f"worst joint deviation {math.degrees(job.err_rad):.2f} deg"
        tol = (f"tolerance {job.tol_m * 1e3:.0f} mm / {math.degrees(job.tol_rad):.1f} deg" if job.kind != "joint"
               else f"tolerance {math.degrees(job.tol_rad):.1f} deg")
        if job.err_m <= job.tol_m and job.err_rad <= job.tol_rad:
            self._end(rt, MspResult.OK, f"{what} ({errs}, {tol})", move_seq=job.move_seq)
        else:
            self._end(rt, MspResult.FAILED, f"{what}: not followed within its tolerance: {errs} ({tol}), worst "
                                            f"{job.where}", move_seq=job.move_seq)

    def _play(self, rt, job: _Job) -> None:
        self._track(rt, job)
        if job.kind == "joint":
            self._jmove_poll(rt, job)
            return
        if self._grip_wait:
            self._wait_gripper(rt, job)
            return
        v = rt.wm.get_task_inputs((TRAJ.done_seq, TRAJ.done_code))
        if int(v[TRAJ.done_seq]) != self._seg_seq:
            return
        code = int(v[TRAJ.done_code])
        if code == DoneCode.REFUSED:
            self._end(rt, MspResult.REFUSED, f"{job.label}: segment {self._seg_i + 1} refused by the "
                                             f"Trajectory Planner", move_seq=job.move_seq)
            return
        if code == DoneCode.STOPPED:
            self._end(rt, MspResult.CANCELLED, f"{job.label}: segment {self._seg_i + 1} stopped",
                      move_seq=job.move_seq)
            return
        s = self._plan[self._seg_i]
        if s.gripper:  # the segment's end is a gripper event: do it before going on
            self._grip_seq += 1
            self._grip_wait = True
            rt.wm.post_task_outputs("msp", {MSP_GRIP.gripper_request: int(GRIPPER_ACTIONS[s.gripper]),
                                            MSP_GRIP.gripper_force_n: s.force_n or 0.0,
                                            MSP_GRIP.gripper_seq: self._grip_seq})
            rt.post(self.key, Level.INFO, f"{job.label}: segment {self._seg_i + 1} reached; gripper {s.gripper}"
                                          + (f" at {s.force_n:g} N" if s.force_n else ""))
            return
        self._next(rt, job)

    def _wait_gripper(self, rt, job: _Job) -> None:
        """The path's gripper event: go on when Servo Control answers it COMPLETE; end the
        playback (GRIPPER FAILED) when it refuses or fails it."""
        v = rt.wm.get_task_inputs(GRIPPER_DONE)
        if int(v[GRIP_DONE_SEQ]) != self._grip_seq:
            return
        code = int(v[GRIP_DONE_CODE])
        if code == IN_PROGRESS:
            return
        self._grip_wait = False
        s = self._plan[self._seg_i]
        if code != COMPLETE:
            self._end(rt, MspResult.GRIPPER, f"{job.label}: gripper {s.gripper} after segment {self._seg_i + 1} "
                                             f"refused or failed (Servo Control's messages say why)")
            return
        self._next(rt, job)

    def _next(self, rt, job: _Job) -> None:
        self._seg_i += 1
        if self._seg_i >= len(self._plan):
            what = (f"playback done ({len(self._plan)} segments)" if job.kind == "path" else f"{job.label} done")
            self._finish(rt, job, what)
            return
        self._send(rt)

    def _jmove_poll(self, rt, job: _Job) -> None:
        if not self._has(rt, JMOVE_DONE):
            return
        v = rt.wm.get_task_inputs(JMOVE_DONE)
        if int(v[JM_DONE_SEQ]) != job.jseq:
            return
        code = int(v[JM_DONE_CODE])
        if code == DoneCode.REACHED:
            self._finish(rt, job, f"{job.label} done")
        elif code == DoneCode.STOPPED:
            self._end(rt, MspResult.CANCELLED, f"{job.label}: joint move stopped", move_seq=job.move_seq)
        else:
            self._end(rt, MspResult.REFUSED, f"{job.label}: joint move refused by the Joint Planner",
                      move_seq=job.move_seq)

    def _cancel_play(self, rt, why: str) -> None:
        job = self._job
        if self._grip_wait:  # a gripper move of the path: stop it too
            self._grip_wait = False
            self._grip_seq += 1
            rt.wm.post_task_outputs("msp", {MSP_GRIP.gripper_request: int(GRIPPER_ACTIONS["stop"]),
                                            MSP_GRIP.gripper_force_n: 0.0, MSP_GRIP.gripper_seq: self._grip_seq})
        if job is not None and job.running:
            rt.wm.post_task_outputs("msp", {JMOVE.jmove_stop: True} if job.kind == "joint" else {SEG.seg_stop: True})
        what = "playback" if job is None or job.kind == "path" else job.label
        self._end(rt, MspResult.CANCELLED, f"{what} stopped: {why}", move_seq=job.move_seq if job is not None else 0)

    # --- move requests --------------------------------------------------------------------------
    def _move_request(self, rt, v, req: MoveRequest) -> None:
        if req.kind == MoveKind.STOP:
            if self.state in (MspMode.PLAY, MspMode.MOVE):
                what = self._job.label if self._job is not None else "the playback"
                self._cancel_play(rt, f"stop request {req.seq}")
                self._end(rt, MspResult.OK, f"move {req.seq} (stop): stopped {what}", move_seq=req.seq)
            else:
                self._end(rt, MspResult.OK, f"move {req.seq} (stop): nothing was moving", idle=False,
                          move_seq=req.seq)
            return
        if req.kind not in (MoveKind.POSE, MoveKind.JOINTS):
            self._end(rt, MspResult.REFUSED, f"move {req.seq}: kind {req.kind} unknown (0 stop, 1 pose, 2 joints)",
                      idle=False, move_seq=req.seq)
            return
        why = _request_problem(req)
        if why:
            self._end(rt, MspResult.REFUSED, f"move {req.seq} refused: {why}", idle=False, move_seq=req.seq)
            return
        if self.state != MspMode.IDLE:
            busy = self._job.label if self._job is not None else MspMode.NAMES.get(self.state, "?").lower()
            self._end(rt, MspResult.REFUSED, f"move {req.seq} ({req.describe()}) refused: busy ({busy}; stop it "
                                             f"first)", idle=False, move_seq=req.seq)
            return
        rt.wm.post_task_outputs("msp", {MSP.move_seq: req.seq})
        rt.post(self.key, Level.INFO, f"move {req.seq}: {req.describe()}")
        self._start_move(rt, v, req)

    # --- sequences and the periodic task --------------------------------------------------------
    def _leave(self, rt, why: str) -> None:
        if self.state in (MspMode.PLAY, MspMode.MOVE):
            self._cancel_play(rt, why)
        elif self.state == MspMode.RECORD:
            v = rt.wm.get_task_inputs(USER_VARS)
            self._stop_record(rt, v)  # keep what was recorded

    def seq_shutdown(self, rt: "LayerContext"):
        self._leave(rt, "shut down")
        return super().seq_shutdown(rt)

    def task_deleted(self, rt: "LayerContext", name: str) -> None:
        """The table deleted the planner (the layer left START UP COMPLETE): what it was
        recording, playing or moving ends, and a mode still set acts again at the next
        start up."""
        if name != "msp_planner":
            return
        if self.state != MspMode.IDLE:
            self._leave(rt, "Multi-Segment Path Planner not running")
        self._mode_seen = MspMode.IDLE
        self._deferred = None

    def requests_task(self, rt: "LayerContext") -> None:
        """While the layer is not START UP COMPLETE (the planner does not exist): a move
        request is answered at once, refused."""
        self._refuse_while_down(rt)

    def plan_task(self, rt: "LayerContext") -> None:
        self.runs["msp_planner"] += 1
        v = rt.wm.get_task_inputs(_RUN_VARS)
        if self._deferred is not None:  # a start that waited one run for cart.mode
            retry = self._deferred
            self._deferred = None
            if isinstance(retry, MoveRequest):
                self._start_move(rt, v, retry, first=False)
            else:
                self._start_play(rt, v, first=False)
            return
        mode = int(v[MSP.mode])
        if mode != self._mode_seen:
            old, self._mode_seen = self._mode_seen, mode
            if self.state == MspMode.RECORD:
                self._stop_record(rt, v)
            elif self.state in (MspMode.PLAY, MspMode.MOVE):
                self._cancel_play(rt, f"msp.mode {MspMode.NAMES.get(old, old)} -> {MspMode.NAMES.get(mode, mode)}")
            if mode == MspMode.RECORD:
                self._start_record(rt, v)
            elif mode == MspMode.PLAY:
                self._start_play(rt, v)
            elif mode != MspMode.IDLE:
                rt.post(self.key, Level.WARNING, f"msp.mode {mode} unknown (0 idle, 1 record, 2 play)")
            return
        seq = int(v[MSP.move_request][0])
        if seq != self._move_seen:
            self._move_seen = seq
            self._move_request(rt, v, MoveRequest.from_array(v[MSP.move_request]))
            return
        if self.state == MspMode.RECORD:
            self._record(rt, v)
        elif self.state in (MspMode.PLAY, MspMode.MOVE) and self._job is not None:
            if self._job.running:
                self._play(rt, self._job)
            else:
                self._advance_check(rt, self._job)

    def _refuse_while_down(self, rt) -> None:
        """A move request while the layer is not running is answered at once (never run later)."""
        seq = int(rt.wm.get_task_inputs((MSP.move_request,))[MSP.move_request][0])
        if seq != self._move_seen:
            self._move_seen = seq
            self._end(rt, MspResult.REFUSED, f"move {seq} refused: the Multi-Segment Path Planner is not running "
                                             f"(power up first)", idle=False, move_seq=seq)
