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
"""

from __future__ import annotations

import math
import threading
from dataclasses import replace
from typing import TYPE_CHECKING, Sequence

import numpy as np

from controller.decision import Status
from controller.gripper import path_request_specs
from controller.layers import Layer
from controller.messages import Level
from controller.paths.model import DEFAULT_LIMITS, Path, PathError, PathPoint
from controller.paths.planner import PlannedSegment, plan_path
from controller.paths.store import PathStore, _now_text, path_missing
from controller.quat import q_angle, q_normalize
from controller.trajectory import DoneCode, segment_specs
from controller.worldmodel import VarSpec
from pfma.gripper import ACTION_NAMES as GRIPPER_ACTION_NAMES, ACTIONS as GRIPPER_ACTIONS, COMPLETE, IN_PROGRESS

if TYPE_CHECKING:  # pragma: no cover
    from controller.context import LayerContext

#: continuous capture thresholds (assumed): a point per 5 mm or 2 degrees
CAPTURE_DIST_M = 0.005
CAPTURE_ANGLE_RAD = math.radians(2.0)


class MspMode:
    """``msp.mode`` (user) and ``msp.state`` (the layer)."""

    IDLE = 0
    RECORD = 1
    PLAY = 2
    NAMES = {0: "IDLE", 1: "RECORD", 2: "PLAY"}


class MspResult:
    """``msp.result``: how the last recording or playback ended (``msp.finished`` counts them)."""

    OK = 0
    CANCELLED = 1  #: playback stopped by the user or the layer shutting down
    NO_POSE = 2  #: no measured tool pose (Joint Planner kinematics missing)
    NO_PATH = 3  #: path id unknown or its file bad
    EMPTY = 4  #: nothing recorded / nothing to play
    REFUSED = 5  #: the Trajectory Planner refused a segment
    SAVE_FAILED = 6
    GRIPPER = 7  #: a gripper event of the path was refused or failed (Servo Control's answer)
    NAMES = {0: "OK", 1: "CANCELLED", 2: "NO POSE", 3: "NO PATH", 4: "EMPTY", 5: "REFUSED", 6: "SAVE FAILED",
             7: "GRIPPER FAILED"}


TOOL_POSE = ("joint.tool_pos_m", "joint.tool_quat")
CMD_POSE = ("cart.cmd_valid", "cart.pos_cmd_m", "cart.quat_cmd")
USER_VARS = ("msp.mode", "msp.path_id", "msp.teach", "msp.capture", "msp.capture_dist_m", "msp.capture_angle_rad",
             "msp.speed_scale", "msp.record_source")
#: the gripper's accepted user requests (Servo Control, controller/gripper.py): a recording stores each
GRIPPER_EVENT = ("gripper.event_seq", "gripper.event", "gripper.event_force_n")
GRIPPER_DONE = ("gripper.msp_done_seq", "gripper.msp_done_code")


class RecordSource:
    """``msp.record_source``: which pose a recording stores."""

    MEASURED = 0  #: the measured tool pose (fk of the resolver angles): where the tool was
    COMMAND = 1  #: the Cartesian command: played back, the arm retraces the recorded motion
    #: including the servo's static error (teach-and-repeat: repeatability, not accuracy)
    NAMES = {0: "MEASURED", 1: "COMMAND"}


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

    def __init__(self, store: PathStore | None = None, background_save: bool = True) -> None:
        super().__init__()
        self.store = store if store is not None else PathStore()
        self.background_save = background_save
        self.periodic["msp_planner"] = self.plan_task
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
        self._finished = 0
        self._end_lock = threading.Lock()
        self._names: set[str] | None = None
        self._saver: threading.Thread | None = None
        self.last_saved: Path | None = None
        self.last_error = ""

    def specs(self) -> list[VarSpec]:
        return self.state_specs() + segment_specs() + path_request_specs() + [
            VarSpec("msp.mode", "command_input", "i2", (), "user", 0,
                    doc="path planner mode: 0 idle, 1 record, 2 play (path msp.path_id)"),
            VarSpec("msp.path_id", "command_input", "i4", (), "user", 0,
                    doc="the path to record into or play (the id in its file; pfma path list)"),
            VarSpec("msp.teach", "command_input", "i4", (), "user", 0,
                    doc="increment while recording to store the present tool pose as a teach point"),
            VarSpec("msp.capture", "command_input", "b1", (), "user", True,
                    doc="while recording, also capture points continuously (distance/angle threshold)"),
            VarSpec("msp.capture_dist_m", "command_input", "f8", (), "user", CAPTURE_DIST_M, "m",
                    doc="continuous capture: a point each time the tool moved this far"),
            VarSpec("msp.capture_angle_rad", "command_input", "f8", (), "user", CAPTURE_ANGLE_RAD, "rad",
                    doc="continuous capture: a point each time the tool turned this far"),
            VarSpec("msp.record_source", "command_input", "i2", (), "user", RecordSource.MEASURED,
                    doc="recording stores 0 the measured tool pose (joint.tool_*) or 1 the Cartesian command "
                        "(cart.pos_cmd_m/quat_cmd: playback repeats the recorded motion)"),
            VarSpec("msp.speed_scale", "command_input", "f8", (), "user", 1.0,
                    doc="playback speed factor on the path's speeds (capped by traj.*_max)"),
            VarSpec("msp.state", "status_output", "i2", (), "msp", 0,
                    doc="path planner state: 0 idle, 1 recording, 2 playing"),
            VarSpec("msp.points", "status_output", "i4", (), "msp", 0,
                    doc="points recorded so far (recording) or in the path (playing)"),
            VarSpec("msp.segment", "status_output", "i4", (), "msp", 0,
                    doc="playback: the segment running (1-based; 0 none)"),
            VarSpec("msp.segments", "status_output", "i4", (), "msp", 0,
                    doc="playback: segments in the plan"),
            VarSpec("msp.finished", "status_output", "i4", (), "msp", 0,
                    doc="counts recordings saved and playbacks ended (msp.result says how)"),
            VarSpec("msp.result", "status_output", "i2", (), "msp", 0,
                    doc="last recording/playback: 0 OK 1 CANCELLED 2 NO POSE 3 NO PATH 4 EMPTY 5 REFUSED "
                        "6 SAVE FAILED 7 GRIPPER FAILED"),
        ]

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
            if not bool(v["cart.cmd_valid"]):
                return None
            return np.asarray(v["cart.pos_cmd_m"], dtype=float), q_normalize(v["cart.quat_cmd"])
        if not self._has(rt, TOOL_POSE):
            return None
        v = rt.wm.get_task_inputs(TOOL_POSE)
        q = np.asarray(v["joint.tool_quat"], dtype=float)
        if float(q @ q) < 0.5:
            return None
        return np.asarray(v["joint.tool_pos_m"], dtype=float), q_normalize(q)

    def _status(self, rt: "LayerContext", **kw: int) -> None:
        rt.wm.post_task_outputs("msp", {f"msp.{k}": v for k, v in kw.items()})

    def _end(self, rt: "LayerContext", result: int, text: str, idle: bool = True) -> None:
        with self._end_lock:  # the background save ends recordings from its thread
            self._finished += 1
            n = self._finished
        if idle:
            self.state = MspMode.IDLE
            self._status(rt, state=MspMode.IDLE, segment=0)
        self._status(rt, finished=n, result=result)
        lvl = Level.INFO if result == MspResult.OK else Level.WARNING
        rt.post(self.key, lvl, f"{text} -> {MspResult.NAMES[result]}")

    # --- recording -------------------------------------------------------------------------
    def _add_point(self, rt, p: np.ndarray, q: np.ndarray, kind: str) -> None:
        self._rec.append(PathPoint(tuple(float(x) for x in p), tuple(float(x) for x in q), kind,
                                   round(rt.now - self._rec_t0, 6)))

    def _start_record(self, rt, v) -> None:
        self._source = int(v["msp.record_source"])
        if self._source not in RecordSource.NAMES:
            rt.post(self.key, Level.WARNING, f"msp.record_source {self._source} unknown; recording the measured pose")
            self._source = RecordSource.MEASURED
        pose = self._tool_pose(rt)
        self._rec_id = int(v["msp.path_id"])
        if pose is None:
            self._end(rt, MspResult.NO_POSE, f"record: no {RecordSource.NAMES[self._source].lower()} tool pose "
                                             f"({'cart.pos_cmd_m' if self._source else 'joint.tool_pos_m'})")
            return
        self._rec, self._rec_t0 = [], rt.now
        self._teach_seen = int(v["msp.teach"])
        if self._has(rt, GRIPPER_EVENT):
            self._grip_event_seen = int(rt.wm.get("gripper.event_seq"))
        self.state = MspMode.RECORD
        if bool(v["msp.capture"]):
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
        teach = int(v["msp.teach"])
        if teach != self._teach_seen:
            self._teach_seen = teach
            self._add_point(rt, p, q, "teach")
            rt.post(self.key, Level.INFO, f"teach point {len(self._rec) - 1}: "
                                          + " ".join(f"{x:+.4f}" for x in p) + " m")
        elif bool(v["msp.capture"]):
            if not self._rec:
                self._add_point(rt, p, q, "capture")
            else:
                last = self._rec[-1]
                moved = float(np.linalg.norm(p - np.array(last.pos_m)))
                turned = q_angle(q, last.quat)
                if moved >= float(v["msp.capture_dist_m"]) or turned >= float(v["msp.capture_angle_rad"]):
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
        seq = int(g["gripper.event_seq"])
        if seq == self._grip_event_seen:
            return
        self._grip_event_seen = seq
        action = GRIPPER_ACTION_NAMES.get(int(g["gripper.event"]))
        if action not in ("open", "close", "stop"):
            return  # a grip force alone: each event carries the force in force
        self._rec.append(PathPoint(tuple(float(x) for x in p), tuple(float(x) for x in q), "gripper",
                                   round(rt.now - self._rec_t0, 6), gripper=action,
                                   force_n=round(float(g["gripper.event_force_n"]), 3)))
        rt.post(self.key, Level.INFO, f"gripper event {len(self._rec) - 1}: {action} at "
                                      f"{float(g['gripper.event_force_n']):.0f} N")

    def _stop_record(self, rt, v) -> None:
        pose = self._tool_pose(rt)
        if pose is not None:
            self._record_gripper(rt, *pose)  # a request answered since the last run is part of the path
        if pose is not None and bool(v["msp.capture"]) and self._rec:
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

    # --- playback --------------------------------------------------------------------------
    def _start_play(self, rt, v) -> None:
        pid = int(v["msp.path_id"])
        try:
            path = self.store.by_id(pid)
            self._plan = plan_path(path, float(v["msp.speed_scale"]))
        except PathError as err:
            self.last_error = str(err)
            self._end(rt, MspResult.NO_PATH if path_missing(err) else MspResult.EMPTY,
                      f"play path id {pid}: {err}")
            return
        if any(s.gripper for s in self._plan) and not self._has(rt, GRIPPER_DONE):
            self._end(rt, MspResult.GRIPPER, f"play path id {pid}: it has gripper events and this controller "
                                             f"has no gripper (Servo Control's gripper.* variables)")
            return
        self.state = MspMode.PLAY
        self._seg_i = 0
        self._grip_wait = False
        self._status(rt, state=MspMode.PLAY, points=len(path.points), segments=len(self._plan))
        rt.post(self.key, Level.INFO, f"playing path {path.name} (id {pid}): {len(self._plan)} segments "
                                      f"from {len(path.points)} points")
        self._send(rt)

    def _send(self, rt) -> None:
        s = self._plan[self._seg_i]
        self._seg_seq += 1
        rt.wm.post_task_outputs("msp", {
            "msp.seg_seq": self._seg_seq, "msp.seg_pos_m": s.pos_m, "msp.seg_quat": s.quat,
            "msp.seg_limits": np.array(s.limits, dtype=float), "msp.seg_last": self._seg_i == len(self._plan) - 1,
            "msp.seg_stop": False, "msp.segment": self._seg_i + 1})

    def _play(self, rt) -> None:
        if self._grip_wait:
            self._wait_gripper(rt)
            return
        v = rt.wm.get_task_inputs(("traj.done_seq", "traj.done_code"))
        if int(v["traj.done_seq"]) != self._seg_seq:
            return
        code = int(v["traj.done_code"])
        if code == DoneCode.REFUSED:
            self._end(rt, MspResult.REFUSED, f"playback: segment {self._seg_i + 1} refused by the "
                                             f"Trajectory Planner")
            return
        if code == DoneCode.STOPPED:
            self._end(rt, MspResult.CANCELLED, f"playback: segment {self._seg_i + 1} stopped")
            return
        s = self._plan[self._seg_i]
        if s.gripper:  # the segment's end is a gripper event: do it before going on
            self._grip_seq += 1
            self._grip_wait = True
            rt.wm.post_task_outputs("msp", {"msp.gripper_request": int(GRIPPER_ACTIONS[s.gripper]),
                                            "msp.gripper_force_n": s.force_n or 0.0,
                                            "msp.gripper_seq": self._grip_seq})
            rt.post(self.key, Level.INFO, f"playback: segment {self._seg_i + 1} reached; gripper {s.gripper}"
                                          + (f" at {s.force_n:g} N" if s.force_n else ""))
            return
        self._next(rt)

    def _wait_gripper(self, rt) -> None:
        """The path's gripper event: go on when Servo Control answers it COMPLETE; end the
        playback (GRIPPER FAILED) when it refuses or fails it."""
        v = rt.wm.get_task_inputs(GRIPPER_DONE)
        if int(v["gripper.msp_done_seq"]) != self._grip_seq:
            return
        code = int(v["gripper.msp_done_code"])
        if code == IN_PROGRESS:
            return
        self._grip_wait = False
        s = self._plan[self._seg_i]
        if code != COMPLETE:
            self._end(rt, MspResult.GRIPPER, f"playback: gripper {s.gripper} after segment {self._seg_i + 1} "
                                             f"refused or failed (Servo Control's messages say why)")
            return
        self._next(rt)

    def _next(self, rt) -> None:
        self._seg_i += 1
        if self._seg_i >= len(self._plan):
            self._end(rt, MspResult.OK, f"playback done ({len(self._plan)} segments)")
            return
        self._send(rt)

    def _cancel_play(self, rt, why: str) -> None:
        if self._grip_wait:  # a gripper move of the path: stop it too
            self._grip_wait = False
            self._grip_seq += 1
            rt.wm.post_task_outputs("msp", {"msp.gripper_request": int(GRIPPER_ACTIONS["stop"]),
                                            "msp.gripper_force_n": 0.0, "msp.gripper_seq": self._grip_seq})
        rt.wm.post_task_outputs("msp", {"msp.seg_stop": True})
        self._end(rt, MspResult.CANCELLED, f"playback stopped: {why}")

    # --- sequences and the periodic task --------------------------------------------------------
    def _leave(self, rt, why: str) -> None:
        if self.state == MspMode.PLAY:
            self._cancel_play(rt, why)
        elif self.state == MspMode.RECORD:
            v = rt.wm.get_task_inputs(USER_VARS)
            self._stop_record(rt, v)  # keep what was recorded

    def seq_shutdown(self, rt: "LayerContext"):
        self._leave(rt, "shut down")
        return super().seq_shutdown(rt)

    def plan_task(self, rt: "LayerContext") -> None:
        self.runs["msp_planner"] += 1
        if rt.wm.get_state_variable(self.v_status) != Status.START_UP_COMPLETE:
            if self.state != MspMode.IDLE:
                self._leave(rt, "Multi-Segment Path Planner not running")
            self._mode_seen = MspMode.IDLE  # a mode still set at the next start up acts again
            return
        v = rt.wm.get_task_inputs(USER_VARS)
        mode = int(v["msp.mode"])
        if mode != self._mode_seen:
            old, self._mode_seen = self._mode_seen, mode
            if self.state == MspMode.RECORD:
                self._stop_record(rt, v)
            elif self.state == MspMode.PLAY:
                self._cancel_play(rt, f"msp.mode {MspMode.NAMES.get(old, old)} -> {MspMode.NAMES.get(mode, mode)}")
            if mode == MspMode.RECORD:
                self._start_record(rt, v)
            elif mode == MspMode.PLAY:
                self._start_play(rt, v)
            elif mode != MspMode.IDLE:
                rt.post(self.key, Level.WARNING, f"msp.mode {mode} unknown (0 idle, 1 record, 2 play)")
            return
        if self.state == MspMode.RECORD:
            self._record(rt, v)
        elif self.state == MspMode.PLAY:
            self._play(rt)
